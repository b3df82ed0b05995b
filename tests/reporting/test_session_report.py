"""A session's report and its charts' series from its log (hil.reporting.write_session_report, session_series;
docs/service.md, "Results"): the decimation keeps every extreme and at most the points asked for, every chart names
its channels' units, the report holds the metrics table and a plot per chart with a unit on every axis, and a
report that cannot be written leaves a service item as it ended, its message saying why."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import hil
from hil.config import PROFILES, load_session
from hil.log import read_log
from hil.reporting import SESSION_CHARTS, envelope, metric_rows, session_series, write_session_report
from hil.reporting import _session as session_module

UNITS = {"rate": {"rate error": "deg/s"}, "drive": {"drive": "counts"}, "miss": {"miss distance": "px"},
         "gyro": {"gyro rate": "deg/s"}, "pose": {"position": "mm", "rotation": "deg"}}


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s demo session on the sim clock (its boards in this process): a log with every group."""
    config = load_session(PROFILES / "sessions" / "demo.yaml").model_copy(update={"duration_s": 3.0})
    result = hil.run(config, clock="sim", out=tmp_path_factory.mktemp("log"))
    assert result.status == "completed" and result.log_path is not None, result.message
    return result.log_path


def test_the_envelope_keeps_every_extreme_within_the_points_asked_for() -> None:
    t = np.arange(10_001) * 1e-3
    v = np.sin(t * 7.0)
    v[5003], v[777] = 100.0, -50.0  # one-sample spikes
    w = v.copy()
    w[2000:4000] = np.nan  # a span without values stays without
    x, cols = envelope(t, {"v": v, "w": w}, 100)
    assert x.size <= 100 and np.all(np.diff(x) > 0) and x[0] == t[0] and x[-1] == t[-1]
    assert cols["v"].max() == 100.0 and cols["v"].min() == -50.0
    assert np.isnan(cols["w"][(x > 2.3) & (x < 3.7)]).all() and np.isfinite(cols["w"][x < 1.7]).all()
    x2, cols2 = envelope(t[:50], {"v": v[:50]}, 100)  # fewer samples than asked for: as they are
    assert np.array_equal(x2, t[:50]) and np.array_equal(cols2["v"], v[:50])


def test_the_series_have_every_chart_with_its_units_within_max_points(log: Path) -> None:
    charts = {c.spec.name: c for c in session_series(read_log(log), max_points=300)}
    assert set(charts) == {spec.name for spec in SESSION_CHARTS} == set(UNITS)
    for name, chart in charts.items():
        data = chart.as_json()
        assert 0 < len(data["t"]) <= 300 and data["rows"] >= len(data["t"]), name
        assert all(len(col) == len(data["t"]) for col in data["columns"].values()), name
        assert {a["label"]: a["unit"] for a in data["axes"]} == UNITS[name]
        assert data["x"]["unit"] == "s" and all(line["unit"] for line in data["lines"])
        assert data["t"] == sorted(data["t"]), name
        assert chart.has_data(), name


def test_the_report_has_the_metrics_and_a_plot_per_chart_with_units_on_every_axis(
        log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    drawn: list[Any] = []
    save = session_module.save_figure

    def spy(fig: Any, path: Path) -> Path:
        drawn.append(fig)
        return save(fig, path)

    monkeypatch.setattr(session_module, "save_figure", spy)
    summary = hil.report(log)
    files = write_session_report(log, tmp_path / "report", summary, notes=["ended completed."])
    assert len(files.pngs) == len(SESSION_CHARTS) == len(drawn)
    for fig in drawn:
        for ax in fig.axes:  # each y axis (twins too) and the time axis name their unit
            assert ax.get_ylabel().endswith("]") and "[" in ax.get_ylabel(), ax.get_ylabel()
        assert fig.axes[0].get_xlabel().endswith("[s]")
        labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
        assert labels and all(label.endswith("]") for label in labels), labels
    md = files.markdown.read_text()
    assert "| metric | value | unit |" in md and "ended completed." in md
    for metric, value, unit in metric_rows(summary):
        assert f"| {metric} | {value} | {unit} |" in md
    assert all(f"]({png.name})" in md for png in files.pngs)
    page = files.html.read_text()
    assert page.count("data:image/png;base64,") == len(files.pngs) and "<script" not in page
    assert "rate error el: std" in page and "deg/s" in page


def test_a_report_that_fails_leaves_the_item_as_it_ended_and_says_why(tmp_path: Path) -> None:
    from hil.service._worker import Running, with_report

    bad = tmp_path / "broken.h5"
    bad.write_bytes(b"not an HDF5 file")
    done = {"status": "completed", "exit_code": 0, "message": "", "log": str(bad), "summary": {}, "report": None}
    out = with_report(Running("u1", "session"), done, bad, {"duration_s": 1.0})
    assert out["status"] == "completed" and out["exit_code"] == 0 and out["report"] is None
    assert out["message"].startswith("its report could not be written (") and "\n" not in out["message"]
    assert with_report(Running("u1", "session"), done, None, {}) == done  # no log: no report, nothing said
