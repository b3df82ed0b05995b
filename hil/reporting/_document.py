"""The report document: a list of blocks (Heading, Text, Bullets, Banner, Table of Cells, Figure) that every report
of the bench builds (campaign, tune, fit) and :mod:`hil.reporting._render` writes as Markdown and HTML alike."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class Cell:
    text: str
    best: bool = False  # the best value of its column
    status: str | None = None  # "pass" or "fail"


@dataclass(frozen=True)
class Table:
    header: list[str]
    rows: list[list[Cell]]
    align: str = ""  # per column 'l' or 'r'; columns past its end are right-aligned (numbers)

    def right(self, i: int) -> bool:
        return (self.align[i:i + 1] or "r") == "r"


@dataclass(frozen=True)
class Heading:
    level: int
    text: str


@dataclass(frozen=True)
class Text:
    text: str


@dataclass(frozen=True)
class Item:
    text: str
    status: str | None = None
    sub: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Bullets:
    items: list[Item]


@dataclass(frozen=True)
class Banner:
    headline: str
    text: str
    passed: bool


@dataclass(frozen=True)
class Figure:
    path: Path
    caption: str


Block = Heading | Text | Bullets | Banner | Table | Figure


@dataclass(frozen=True)
class ReportFiles:
    markdown: Path
    html: Path
    pngs: list[Path]


def format_number(x: float) -> str:
    """Three significant digits (all of them from 1000 up), never an exponent: 0.281, 6.02, 15.6, 1234; 9.996
    rounds to 10.0 (not 10.00)."""
    if not math.isfinite(x):
        return "n/a"
    if x == 0:
        return "0"
    exponent = math.floor(math.log10(abs(x)))
    digits = max(0, 2 - exponent)
    if math.floor(math.log10(abs(round(x, digits)))) > exponent:  # rounding carried into the next decade
        digits = max(0, digits - 1)
    return f"{x:.{digits}f}"
