"""The fit report (Markdown + HTML, the campaign report's style): every parameter with its estimate, uncertainty and
source, the residuals per log, and logged against simulated signals: the noise spectra, the frequency responses, the
torque balance, and each log's session re-run on the fitted twin with the ``sim`` clock."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.fit.logs import FitLog
from hil.fit.rerun import UNITS, rerun_log, session_metrics
from hil.fit.twin import TwinFit
from hil.log import read_log
from hil.reporting import (
    Banner,
    Bullets,
    Cell,
    Figure,
    Heading,
    Item,
    ReportFiles,
    Table,
    Text,
    format_number,
    legend_below,
    new_figure,
    render_html,
    render_markdown,
    save_figure,
)


@dataclass
class TwinCheck:
    """One log's session re-run on the twin: the same metric, logged and simulated."""

    log: str
    metric: str
    unit: str
    logged: float
    twin: float

    @property
    def ratio(self) -> float:
        return self.twin / self.logged if self.logged else math.nan


def rerun_on_twin(fit: TwinFit, plant_path: Path, work_dir: Path) -> tuple[list[TwinCheck], dict[str, Any]]:
    """Each static and swing log's session, re-run on the twin (``sim`` clock, the log's own config and seed; the
    emulator's plant replaced): its metrics beside the log's. Ident logs are checked by their FRF instead."""

    checks: list[TwinCheck] = []
    traces: dict[str, Any] = {}
    for lg in fit.logs:
        if lg.kind == "ident":
            continue
        try:
            log_path = rerun_log(lg, plant_path, work_dir)
        except Exception as exc:  # a session that cannot be re-run is reported, not fatal to the fit
            fit.notes.append(f"{lg.name}: not re-run on the twin: {exc}")
            continue
        if log_path is None:
            continue
        sim = read_log(log_path)
        orig = read_log(lg.path)
        got = session_metrics(sim.groups["loop"], sim.groups.get("image") or {}, lg.dt_s)
        want = session_metrics(orig.groups["loop"], orig.groups.get("image") or {}, lg.dt_s)
        for key in want:
            if key in got:
                checks.append(TwinCheck(lg.name, key, UNITS[key], want[key], got[key]))
        traces[lg.name] = (orig.groups["loop"], sim.groups["loop"])
    return checks, traces


def _plot_psd(fit: TwinFit, path: Path) -> Path | None:

    psd = fit.noise.get("psd") or {}
    if not psd:
        return None
    fig, axes = new_figure(1, len(psd), height=3.2)
    for ax, (name, d) in zip(axes[0], psd.items(), strict=False):
        ax.loglog(d["f_hz"], d["psd"], color="0.5", lw=0.8, label="logged (static)")
        ax.loglog(d["f_hz"], d["model"], color="C3", lw=1.5, label="fitted model, as the estimator reads it")
        ax.set_title(f"gyro {name}")
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel("PSD ((deg/s)^2/Hz)")
        ax.grid(True, which="both", alpha=0.3)
    legend_below(fig, axes[0][0])
    return save_figure(fig, path)


def _plot_frf(fit: TwinFit, path: Path) -> Path | None:

    if not fit.frf:
        return None
    fig, axes = new_figure(2, len(fit.frf), height=2.8)
    for j, f in enumerate(fit.frf):
        frf = f.frf
        good = frf.coherence >= 0.8
        model = f.response(frf.freq_hz)
        if f.reading is not None:  # as the sweep's estimator reads it, so that it meets the logged points
            model = model * f.reading
        mag, ph = axes[0][j], axes[1][j]
        mag.semilogx(frf.freq_hz[good], 20 * np.log10(np.abs(frf.response[good])), ".", ms=2, color="0.4",
                     label="logged (coherence >= 0.8)")
        mag.semilogx(frf.freq_hz, 20 * np.log10(np.abs(model)), color="C3", lw=1.3, label="fitted model")
        ph.semilogx(frf.freq_hz[good], np.degrees(np.angle(frf.response[good] / model[good])), ".", ms=2,
                    color="0.4")
        mag.set_title(f"{f.axis}: drive -> gyro ({f.log})", fontsize=8)
        mag.set_ylabel("dB (deg/s per count)")
        ph.set_ylabel("phase residual (deg)")
        ph.set_xlabel("frequency (Hz)")
        for a in (mag, ph):
            a.grid(True, which="both", alpha=0.3)
    legend_below(fig, axes[0][0])
    return save_figure(fig, path)


def _plot_torque(fit: TwinFit, path: Path) -> Path | None:

    rows = [(axis, name, tr) for axis, mf in fit.mechanics.items() for name, tr in mf.traces.items()]
    if not rows:
        return None
    fig, axes = new_figure(len(rows), 1, height=1.9)
    for ax, (axis, name, tr) in zip(axes[:, 0], rows, strict=False):
        t = tr["t_s"]
        a = int(np.searchsorted(t, t[0] + 3.0))
        b = min(t.size, a + 2000)
        ax.plot(t[a:b], tr["measured_n_m"][a:b], color="0.5", lw=0.8, label="logged: J dw/dt - motor torque")
        ax.plot(t[a:b], tr["model_n_m"][a:b], color="C3", lw=1.0,
                label="fitted: friction + cable + imbalance")
        hidden = ~tr["kept"][a:b]
        if hidden.any():
            ax.fill_between(t[a:b], 0, 1, where=hidden, transform=ax.get_xaxis_transform(), color="C0", alpha=0.08,
                            label="left out (stick)")
        ax.set_title(f"{axis}: {name}", fontsize=8)
        ax.set_ylabel("N m")
        ax.grid(True, alpha=0.3)
    axes[-1][0].set_xlabel("board time (s)")
    legend_below(fig, axes[0][0])
    return save_figure(fig, path)


def _plot_rerun(traces: dict[str, Any], path: Path) -> Path | None:

    if not traces:
        return None
    fig, axes = new_figure(len(traces), 1, height=2.0)
    for ax, (name, (orig, sim)) in zip(axes[:, 0], traces.items(), strict=False):
        t = np.asarray(orig["t_s"])
        a = int(np.searchsorted(t, t[0] + 3.0))
        b = min(t.size, a + 2000, np.asarray(sim["t_s"]).size)
        ax.plot(t[a:b], np.asarray(orig["rate_err_el_dps"])[a:b], color="0.5", lw=0.7, label="logged")
        ax.plot(t[a:b], np.asarray(sim["rate_err_el_dps"])[a:b], color="C3", lw=0.7, alpha=0.8,
                label="twin (sim clock, same session)")
        ax.set_title(f"elevation rate error: {name}", fontsize=8)
        ax.set_ylabel("deg/s")
        ax.grid(True, alpha=0.3)
    axes[-1][0].set_xlabel("board time (s)")
    legend_below(fig, axes[0][0])
    return save_figure(fig, path)


def _fmt(x: float | None, sig: float | None = None) -> str:

    if x is None:
        return "-"
    text = format_number(x)
    return text if sig is None else f"{text} +- {format_number(sig)}"


def write_fit_report(fit: TwinFit, plant_path: Path, out_dir: Path, *, rerun: bool = True,
                     command: str = "hil fit") -> tuple[Any, list[TwinCheck]]:
    """fit.md, fit.html and the plots into ``out_dir``; re-runs the static and swing sessions on the twin (``sim``)
    unless ``rerun`` is False. Returns the ReportFiles and the twin checks."""

    out_dir.mkdir(parents=True, exist_ok=True)
    checks, traces = rerun_on_twin(fit, plant_path, out_dir / "twin-runs") if rerun else ([], {})
    n_fit = sum(e.status == "fitted" for e in fit.estimates)
    worst = max((abs(c.ratio - 1.0) for c in checks if math.isfinite(c.ratio)), default=math.nan)
    head = f"{n_fit} of {len(fit.estimates)} parameters fitted from {len(fit.logs)} logs"
    text = (f"Plant written to {plant_path}. "
            + (f"The logged sessions re-run on the twin: every metric within {worst * 100:.0f} % of the log's."
               if checks else "No static or swing session was re-run on the twin."))
    doc: list[Any] = [Heading(1, f"Digital twin: {plant_path.stem}"), Banner(head, text, bool(checks) or not rerun)]
    doc.append(Heading(2, "Parameters"))
    rows = []
    for e in fit.estimates:
        rows.append([Cell(e.name), Cell(_fmt(e.value, e.sigma)), Cell(e.unit), Cell(_fmt(e.prior)),
                     Cell(e.status, status="pass" if e.status == "fitted" else None),
                     Cell(e.source + (f" ({e.note})" if e.note else ""))])
    doc.append(Table(["parameter", "value +- 1 sigma", "unit", "prior", "status", "from"], rows, align="lllrll"))
    doc.append(Text("fitted: determined by the logs within its target accuracy; weak: fitted, but its 1-sigma is wider "
                    "than the target (the note says what to record); prior: the logs cannot determine it, the prior's "
                    "value is kept; bound: not reached in the logs (a limit at least the value shown)."))
    doc.append(Heading(2, "Logs and residuals"))
    lrows = []
    for lg in fit.logs:
        res = ", ".join(f"{ax} {mf.rms_n_m[lg.name]:.3g} N m" for ax, mf in fit.mechanics.items()
                        if lg.name in mf.rms_n_m)
        frf = next((f for f in fit.frf if f.log == lg.name), None)
        if frf is not None:
            res = (res + "; " if res else "") + f"FRF {frf.rms_db:.2f} dB / {frf.rms_deg:.1f} deg rms"
        lrows.append([Cell(lg.name), Cell(_kind(lg)), Cell(f"{lg.duration_s:.1f}"), Cell(lg.controller),
                      Cell(res or "-")])
    doc.append(Table(["log", "kind", "driven (s)", "controller", "residual rms"], lrows, align="llrll"))
    if fit.notes:
        doc.append(Bullets([Item(n) for n in fit.notes]))
    if checks:
        doc.append(Heading(2, "The logged sessions on the twin"))
        doc.append(Text("Each static and swing session re-run with its own configuration and seed on the fitted plant "
                        "(sim clock); first second left out."))
        doc.append(Table(["log", "metric", "logged", "twin", "twin / logged"],
                         [[Cell(c.log), Cell(f"{c.metric} ({c.unit})"), Cell(_fmt(c.logged)), Cell(_fmt(c.twin)),
                           Cell(f"{c.ratio:.3f}")] for c in checks], align="ll"))
    pngs: list[Path] = []
    for maker, name, caption in ((_plot_psd, "fit-noise.png", "gyro noise spectra, static logs: logged and fitted"),
                                 (_plot_frf, "fit-frf.png", "frequency responses of the ident logs: logged and fitted"),
                                 (_plot_torque, "fit-torque.png", "torque balance, 2 s of each log: logged and "
                                                                  "fitted (shaded: left out, stick)")):
        png = maker(fit, out_dir / name)
        if png is not None:
            pngs.append(png)
            doc.append(Figure(png, caption))
    png = _plot_rerun(traces, out_dir / "fit-twin.png")
    if png is not None:
        pngs.append(png)
        doc.append(Figure(png, "elevation rate error, logged and the same session on the twin"))
    doc.append(Text(f"Command: {command}"))
    md, html = out_dir / "fit.md", out_dir / "fit.html"
    md.write_text(render_markdown(doc, out_dir), encoding="utf-8")
    html.write_text(render_html(doc), encoding="utf-8")
    return ReportFiles(md, html, pngs), checks


def _kind(lg: FitLog) -> str:
    return f"{lg.kind} ({lg.axis})" if lg.axis else lg.kind
