"""One session's report and its plotted channels, from its log (docs/service.md, "Results").

:data:`SESSION_CHARTS` names what a session is looked at by: its rate error, drive, miss distance, gyro rates and
hexapod pose, each channel with the unit its log gives it. :func:`session_series` reads them from a log's data,
on one time axis (seconds since the loop's first sample, on the board's clock), decimated to at most
``max_points`` a channel by their envelope (each bucket's minimum and maximum, in the order they came), so a
spike survives any decimation. The service's page plots them as they are (``GET /api/history/UID/series``), and
:func:`write_session_report` draws the same series into report.md and a self-contained report.html beside the
metrics table (:func:`metric_rows`) of the log's summary (``hil report LOG``: hil.analysis.summarize_log, which
the caller passes: the analysis and the reports are packages of one layer that do not import each other).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.log import LogData, read_log
from hil.reporting._document import (
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
from hil.reporting._plots import legend_below, new_figure, save_figure
from hil.reporting._render import render_html, render_markdown

TIME_LABEL = "time since the loop's first sample"
REPORT_POINTS = 4000  # a report's plots: the envelope at this many points a channel (a PNG is 900 px wide)


@dataclass(frozen=True)
class Line:
    """One channel of a chart: its log column, its legend label, and the quantity its axis shows."""

    column: str
    label: str
    axis: str


@dataclass(frozen=True)
class ChartSpec:
    """A chart of one log group's channels (one time base); one y axis per quantity, each with its unit."""

    name: str
    title: str
    group: str
    lines: tuple[Line, ...]


SESSION_CHARTS: tuple[ChartSpec, ...] = (
    ChartSpec("rate", "Rate error (command - gyro)", "loop",
              (Line("rate_err_el_dps", "el", "rate error"), Line("rate_err_az_dps", "az", "rate error"))),
    ChartSpec("drive", "Drive command", "loop",
              (Line("drive_el_counts", "el", "drive"), Line("drive_az_counts", "az", "drive"))),
    ChartSpec("miss", "Miss distance (valid frames)", "image",
              (Line("miss_x_px", "x", "miss distance"), Line("miss_y_px", "y", "miss distance"))),
    ChartSpec("gyro", "Gyro rate", "loop",
              (Line("gyro_y_dps", "y (elevation)", "gyro rate"), Line("gyro_z_dps", "z (cross-elevation)",
                                                                        "gyro rate"))),
    ChartSpec("pose", "Hexapod pose", "hexapod",
              (Line("x_mm", "x", "position"), Line("y_mm", "y", "position"), Line("z_mm", "z", "position"),
               Line("roll_deg", "roll", "rotation"), Line("pitch_deg", "pitch", "rotation"),
               Line("yaw_deg", "yaw", "rotation"))),
)


@dataclass(frozen=True)
class Axis:
    label: str
    unit: str

    @property
    def text(self) -> str:
        return f"{self.label} ({self.unit})"


@dataclass(frozen=True)
class ChartSeries:
    """A chart's channels as read from a log: the time ``t`` (s) and a column per line, with their units."""

    spec: ChartSpec
    t: np.ndarray
    columns: dict[str, np.ndarray]
    units: dict[str, str]
    rows: int  # the group's rows in the log, before decimation

    @property
    def axes(self) -> list[Axis]:
        """One y axis per quantity, in the order the lines name them."""
        seen: dict[str, Axis] = {}
        for line in self.spec.lines:
            seen.setdefault(line.axis, Axis(line.axis, self.units[line.column]))
        return list(seen.values())

    def legend(self, line: Line) -> str:
        return f"{line.label} ({self.units[line.column]})"

    def has_data(self) -> bool:
        return self.t.size > 0 and any(np.isfinite(c).any() for c in self.columns.values())

    def as_json(self) -> dict[str, Any]:
        """The chart as plain data: its axes and lines with their units, ``t`` and the columns (null for no value)."""
        axes = self.axes
        index = {a.label: i for i, a in enumerate(axes)}
        return {"name": self.spec.name, "title": self.spec.title, "group": self.spec.group, "rows": self.rows,
                "x": {"label": TIME_LABEL, "unit": "s"},
                "axes": [{"label": a.label, "unit": a.unit} for a in axes],
                "lines": [{"column": ln.column, "label": ln.label, "unit": self.units[ln.column],
                           "axis": index[ln.axis]} for ln in self.spec.lines],
                "t": _json_numbers(self.t), "columns": {k: _json_numbers(v) for k, v in self.columns.items()}}


def _json_numbers(values: np.ndarray) -> list[float | None]:
    """Seven significant digits (what a chart can show), None for NaN."""
    return [float(f"{v:.7g}") if math.isfinite(v) else None for v in values.tolist()]


def envelope(t: np.ndarray, columns: Mapping[str, np.ndarray], max_points: int) -> tuple[np.ndarray,
                                                                                         dict[str, np.ndarray]]:
    """``t`` and ``columns`` decimated to at most ``max_points`` samples: in each of ``max_points // 2`` buckets its
    first and last time, with each column's minimum and maximum there in the order they came (NaN ignored; a
    bucket of NaN stays NaN). Nothing is done to as few samples as ``max_points``."""
    cols = {k: np.asarray(v, dtype=float) for k, v in columns.items()}
    n = t.size
    if n <= max(2, max_points):
        return t.astype(float), cols
    buckets = max(1, max_points // 2)
    size = -(-n // buckets)
    starts = np.arange(0, n, size)
    ends = np.minimum(starts + size, n) - 1
    x = np.empty(2 * starts.size)
    x[0::2], x[1::2] = t[starts], t[ends]
    out = {}
    for name, v in cols.items():
        padded = np.full(starts.size * size, np.nan)
        padded[:n] = v
        grid = padded.reshape(starts.size, size)
        blank = np.isnan(grid)
        lo_at = np.where(blank, np.inf, grid).argmin(axis=1)
        hi_at = np.where(blank, -np.inf, grid).argmax(axis=1)
        rows = np.arange(starts.size)
        lo, hi = grid[rows, lo_at], grid[rows, hi_at]
        pair = np.empty(2 * starts.size)
        first = lo_at <= hi_at
        pair[0::2], pair[1::2] = np.where(first, lo, hi), np.where(first, hi, lo)
        out[name] = pair
    keep = np.r_[True, np.diff(x) > 0]  # a last bucket of one sample: its one time once
    return x[keep], {k: v[keep] for k, v in out.items()}


def _times(data: LogData, group: str) -> np.ndarray:
    """A group's sample times in seconds since the loop's first sample, on the board's clock: the loop's ``t_s``,
    the camera's ``t_exposure_s``, and for the hexapod (its own clock) its host times mapped onto the loop's."""
    loop = data.groups.get("loop", {})
    cols = data.groups.get(group, {})
    t_loop = np.asarray(loop.get("t_s", np.zeros(0)), dtype=float)
    t0 = t_loop[0] if t_loop.size else 0.0
    if group == "loop":
        return t_loop - t0
    if group == "image" and "t_exposure_s" in cols:
        return np.asarray(cols["t_exposure_s"], dtype=float) - t0
    host = np.asarray(cols.get("t_host_ns", np.zeros(0)), dtype=float)
    loop_host = np.asarray(loop.get("t_host_ns", np.zeros(0)), dtype=float)
    if loop_host.size >= 2 and loop_host[-1] > loop_host[0]:  # the board's seconds per host nanosecond
        return (host - loop_host[0]) * (t_loop[-1] - t0) / (loop_host[-1] - loop_host[0])
    return (host - (host[0] if host.size else 0.0)) / 1e9


def session_series(data: LogData, max_points: int = 2000) -> list[ChartSeries]:
    """Every chart of :data:`SESSION_CHARTS` whose group the log has, each channel decimated to at most
    ``max_points`` (:func:`envelope`); a miss distance only where the tracker had a valid target."""
    out = []
    for spec in SESSION_CHARTS:
        cols = data.groups.get(spec.group, {})
        if not all(line.column in cols for line in spec.lines):
            continue
        t = _times(data, spec.group)
        columns = {ln.column: np.asarray(cols[ln.column], dtype=float) for ln in spec.lines}
        if spec.group == "image" and "track_valid" in cols:
            invalid = np.asarray(cols["track_valid"]) == 0
            columns = {k: np.where(invalid, np.nan, v) for k, v in columns.items()}
        if t.size > 1 and np.any(np.diff(t) < 0):  # a board that restarted its clock: in time order still
            order = np.argsort(t, kind="stable")
            t, columns = t[order], {k: v[order] for k, v in columns.items()}
        t, columns = envelope(t, columns, max_points)
        units = {ln.column: data.units.get(spec.group, {}).get(ln.column, "") or "1" for ln in spec.lines}
        out.append(ChartSeries(spec, t, columns, units, rows=int(np.asarray(cols[spec.lines[0].column]).size)))
    return out


# --- the metrics -------------------------------------------------------------------------------


def _num(x: Any) -> str:
    return format_number(float(x)) if isinstance(x, int | float) and not isinstance(x, bool) else "n/a"


def metric_rows(summary: Mapping[str, Any]) -> list[tuple[str, str, str]]:
    """A session's summary (hil.analysis.summarize_log, as `hil report LOG` prints it; an ident's fit under
    ``ident``) as rows of (metric, value, unit), one value a row, so that items compare row by row."""
    s = summary
    rows: list[tuple[str, str, str]] = []
    if "duration_s" in s:
        rows.append(("duration", _num(s["duration_s"]), "s"))
    for axis in ("el", "az"):
        err = s.get(f"rate_error_{axis}_dps")
        if isinstance(err, Mapping):
            rows += [(f"rate error {axis}: range ±", _num(err.get("range_pm")), "deg/s"),
                     (f"rate error {axis}: std", _num(err.get("std")), "deg/s")]
    rows += [(f"drive ripple {axis} (std)", _num(s[f"drive_ripple_{axis}_counts"]), "counts")
             for axis in ("el", "az") if f"drive_ripple_{axis}_counts" in s]
    for axis in ("el", "az"):
        amps = s.get(f"motor_current_{axis}_a")
        if isinstance(amps, Mapping):
            rows += [(f"motor current {axis}: rms", _num(amps.get("rms")), "A"),
                     (f"motor current {axis}: peak", _num(amps.get("peak")), "A")]
    for axis in ("x", "y"):
        miss = s.get(f"miss_{axis}_px")
        if isinstance(miss, Mapping):
            rows += [(f"miss distance {axis}: range ±", _num(miss.get("range_pm")), "px"),
                     (f"miss distance {axis}: std", _num(miss.get("std")), "px")]
    if "miss_radial_px_rms" in s:
        rows.append(("miss distance: radial rms", _num(s["miss_radial_px_rms"]), "px"))
    pose = s.get("start_pose")
    if isinstance(pose, Mapping):
        rows += [("start pose: took", _num(pose.get("took_s")), "s"),
                 ("start pose: from el", _num(pose.get("from_el_deg")), "deg"),
                 ("start pose: from az", _num(pose.get("from_az_deg")), "deg")]
    if "frames" in s:
        rows.append(("frames tracked", f"{s.get('frames_valid', 0)} / {s['frames']}", "frames"))
    lat = s.get("latency_us")
    if isinstance(lat, Mapping):
        rows += [("bench latency p50", _num(lat.get("p50")), "us"), ("bench latency p99", _num(lat.get("p99")), "us")]
    board = s.get("board_latency_us")
    if isinstance(board, Mapping):
        rows += [("board-measured latency p50", _num(board.get("p50")), "us"),
                 ("board-measured latency p99", _num(board.get("p99")), "us")]
    for key, label in (("cycles", "cycles"), ("late_cycles", "late cycles (> 1 ms)"),
                       ("missed_cycles", "missed cycles"), ("faults", "faults"), ("host_stalls", "host stalls")):
        if key in s:
            rows.append((label, str(s[key]), "cycles" if "cycles" in key else "events"))
    errors = s.get("link_errors")
    if isinstance(errors, Mapping):
        rows += [(f"link errors {name}", str(n), "frames") for name, n in errors.items()]
    ident = s.get("ident")
    if isinstance(ident, Mapping):
        rows += [(f"ident {ident.get('axis', '')}: k_m", _num(ident.get("k_m_dps2_per_count")), "deg/s²/count"),
                 ("ident: gyro bandwidth", _num(ident.get("gyro_bandwidth_hz")), "Hz"),
                 ("ident: delay", _num(ident.get("delay_ms")), "ms"),
                 ("ident: fit rms error", _num(ident.get("rms_error_db")), "dB")]
    return rows


# --- the report --------------------------------------------------------------------------------


def plot_chart(series: ChartSeries, path: Path) -> Path:
    """One chart as a PNG: every line against time, one y axis per quantity (the second on the right), every axis
    and legend entry with its unit."""
    fig, ax = new_figure()
    axes = [ax[0, 0]]
    for _ in series.axes[1:]:
        axes.append(axes[0].twinx())
    index = {a.label: i for i, a in enumerate(series.axes)}
    for n, line in enumerate(series.spec.lines):
        second = index[line.axis] > 0
        axes[index[line.axis]].plot(series.t, series.columns[line.column], lw=0.8, color=f"C{n % 10}",
                                    ls="--" if second else "-", label=f"{line.label} [{series.units[line.column]}]")
    for a, axis in zip(axes, series.axes, strict=True):
        a.set_ylabel(f"{axis.label} [{axis.unit}]")
    axes[0].set(title=series.spec.title, xlabel=f"{TIME_LABEL} [s]")
    axes[0].grid(alpha=0.3)
    legend_below(fig, *axes)
    return save_figure(fig, path)


def _provenance(provenance: Mapping[str, Any]) -> list[Block]:
    if not provenance:
        return []
    rows = [[Cell(name), Cell(str(provenance[key]))] for name, key in
            (("hil", "hil_version"), ("git commit", "git_commit"), ("numpy", "numpy"), ("h5py", "h5py"))
            if provenance.get(key)]
    plant = provenance.get("plant")
    if isinstance(plant, Mapping):
        rows.append([Cell("plant file"), Cell(f"{plant.get('path')} (SHA-256 {plant.get('sha256')})")])
    controller = provenance.get("controller")
    if isinstance(controller, Mapping):
        params = controller.get("params")
        if not isinstance(params, Mapping):
            params = {}
        text = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in params.items())
        rows.append([Cell("controller"), Cell(f"{controller.get('name', '')}: {text}".rstrip(": "))])
    return [Heading(2, "Software and parameters"), Table(["item", "recorded"], rows, "ll")] if rows else []


def write_session_report(log: str | Path, out_dir: str | Path, summary: Mapping[str, Any], *,
                         notes: Sequence[str] = (), figures: Sequence[Figure] = ()) -> ReportFiles:
    """Write report.md, report.html (its plots inside) and the PNGs of the session whose log is ``log`` into
    ``out_dir``: the metrics of ``summary`` (the log's, hil.analysis.summarize_log), the charts of
    :data:`SESSION_CHARTS` over the whole session, ``notes`` (how the run ended) and further ``figures`` (an
    ident's Bode plot). Raises hil.log.LogError or OSError for a log it cannot read."""
    log, out = Path(log), Path(out_dir)
    data = read_log(log)
    out.mkdir(parents=True, exist_ok=True)
    name = str(summary.get("session") or data.attrs.get("session_name") or log.stem)
    controller = summary.get("controller") or data.attrs.get("controller") or "?"
    doc: list[Block] = [Heading(1, f"Session {name}")]
    head = (f"Controller {controller}; {_num(summary.get('duration_s'))} s of loop; the metrics leave out the first "
            f"{_num(summary.get('settle_s', 1.0))} s. Log: {log.name}.")
    doc += [Text(head), *(Text(n) for n in notes if n)]
    warnings = [str(summary["incomplete"])] if summary.get("incomplete") else []
    warnings += [f"fault: {why}" for why in summary.get("fault_reasons") or []]
    if summary.get("swing_gaps"):
        warnings.append(f"the table did not swing for {_num(summary.get('swing_gap_s'))} s; those spans are left out "
                        "of the metrics")
    if warnings:
        doc.append(Bullets([Item(w, "fail") for w in warnings]))
    rows = metric_rows(summary)
    doc += [Heading(2, "Metrics"), Table(["metric", "value", "unit"], [[Cell(m), Cell(v), Cell(u)]
                                                                      for m, v, u in rows], "lrl")
            if rows else Text("No metrics: the log holds no loop samples.")]
    doc.append(Heading(2, "Plots"))
    pngs = []
    for series in session_series(data, REPORT_POINTS):
        if not series.has_data():
            doc.append(Text(f"{series.spec.title}: nothing logged."))
            continue
        png = plot_chart(series, out / f"{series.spec.name}.png")
        pngs.append(png)
        shown = f"the envelope of {series.rows} samples" if series.t.size < series.rows else f"{series.rows} samples"
        doc.append(Figure(png, f"{series.spec.title}, the whole session ({shown})"))
    if figures:
        doc += [Heading(2, "Identification"), *figures]
    doc += _provenance(summary.get("provenance") or {})
    md, page = out / "report.md", out / "report.html"
    md.write_text(render_markdown(doc, out), encoding="utf-8")
    page.write_text(render_html(doc), encoding="utf-8")
    return ReportFiles(md, page, pngs + [f.path for f in figures])
