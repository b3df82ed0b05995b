"""Reports: the document model (blocks, tables, figures), its Markdown and HTML rendering, and the plot helpers that
the campaign, tune and fit reports share. The content of each report is its own package's (hil.campaign.report,
hil.tune, hil.fit).

Not ``hil.report``: that name is the public API's ``hil.report(PATH)``, which writes a campaign's report."""

from hil.reporting._document import (
    Banner,
    Block,
    Bullets,
    Cell,
    Figure,
    Heading,
    Item,
    ReportFiles,
    Table,
    Text,
    format_number,
)
from hil.reporting._plots import DPI, legend_below, new_figure, save_figure
from hil.reporting._render import render_html, render_markdown

__all__ = [
    "DPI",
    "Banner",
    "Block",
    "Bullets",
    "Cell",
    "Figure",
    "Heading",
    "Item",
    "ReportFiles",
    "Table",
    "Text",
    "format_number",
    "legend_below",
    "new_figure",
    "render_html",
    "render_markdown",
    "save_figure",
]
