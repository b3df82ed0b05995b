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


def legend_below(fig: Any, ax: Any) -> None:
    """The legend of ``ax``'s lines under the axes, outside them (constrained layout makes room): never over data."""
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(handles), 4), frameon=False)
