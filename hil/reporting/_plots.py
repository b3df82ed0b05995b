"""Plot helpers every report shares: one figure size and DPI, the legend below the axes, PNG out
(matplotlib's Agg backend: no display is needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

DPI = 100


def new_figure(rows: int = 1, cols: int = 1, height: float = 3.6) -> tuple[Any, Any]:
    from matplotlib.figure import Figure as MplFigure  # noqa: PLC0415  (heavy: loaded only when a figure is drawn; no pyplot: no global state, no GUI backend)

    fig = MplFigure(figsize=(9.0, height * rows), layout="constrained")
    return fig, fig.subplots(rows, cols, squeeze=False)


def save_figure(fig: Any, path: Path) -> Path:
    fig.savefig(path, dpi=DPI, format="png")
    return path


def legend_below(fig: Any, *axes: Any) -> None:
    """The legend of the lines of ``axes`` (one, or twins sharing an x axis) under the axes, outside them
    (constrained layout makes room): never over data."""
    handles: list[Any] = []
    labels: list[str] = []
    for ax in axes:
        h, lab = ax.get_legend_handles_labels()
        handles += h
        labels += lab
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(handles), 4), frameon=False)
