"""The live page's plotting library ships inside the package (a lab may have no internet): uPlot, its licence."""

from __future__ import annotations

from importlib.resources import files


def test_the_plot_library_is_in_the_package() -> None:
    uplot = files("hil.service") / "static" / "uplot"
    script = (uplot / "uPlot.iife.min.js").read_text()
    assert script.startswith("/*! https://github.com/leeoniya/uPlot (v1.6.32) */") and "var uPlot" in script
    assert len(script) > 40_000 and (uplot / "uPlot.min.css").read_text().startswith(".uplot")
    assert "The MIT License" in (uplot / "LICENSE").read_text()
