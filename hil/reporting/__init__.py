"""Reports: the document model (blocks, tables, figures), its Markdown and HTML rendering, and the plot helpers that
the campaign, tune and fit reports share. The content of each report is its own package's (hil.campaign.report,
hil.tune, hil.fit), except a session's: its report and its charts' series are here (``write_session_report``,
``session_series``), since every face shows them (the service's page and its items' reports).

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
from hil.reporting._session import (
    SESSION_CHARTS,
    ChartSeries,
    ChartSpec,
    envelope,
    metric_rows,
    plot_chart,
    session_series,
    write_session_report,
)

__all__ = [
    "DPI",
    "SESSION_CHARTS",
    "Banner",
    "Block",
    "Bullets",
    "Cell",
    "ChartSeries",
    "ChartSpec",
    "Figure",
    "Heading",
    "Item",
    "ReportFiles",
    "Table",
    "Text",
    "envelope",
    "format_number",
    "legend_below",
    "metric_rows",
    "new_figure",
    "plot_chart",
    "render_html",
    "render_markdown",
    "save_figure",
    "session_series",
    "write_session_report",
]
