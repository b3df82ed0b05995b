"""The campaign report: Markdown, self-contained HTML and PNG plots from a campaign directory.

``write_report(CAMPAIGN_DIR)`` reads ``campaign.json`` (a :class:`~hil.campaign.model.CampaignResult`)
and, for the plots, each controller's first logged seed per profile. It writes ``report.md``,
``report.html`` (PNGs embedded as data URIs, inline CSS: one file to mail) and the PNGs into
``CAMPAIGN_DIR/report/``. Contents (docs/campaigns.md, "Reports"): a verdict banner (which controller
won on the campaign's primary metrics, by how much, acceptance PASS/FAIL), per profile the paper's table
(mean over seeds, min–max, the paper's value, gain vs the baseline, and with an ``oracle`` in the campaign the
fraction of the baseline-to-oracle gap each controller closes) and plots (rate error, miss distance, PSD, metric
bars, the analysis's own filter plot), the acceptance rules, every cell's pass/fail and the run info. The oracle
(hil.control.oracle: the plant's truth, sim clock only) is a reference: it is never the winner or the best
of a column. A lag is ranked and compared by its magnitude (hil.campaign.metrics.score): a lead is no
improvement over a lag of the same size.

The document is built once as a list of neutral blocks (:class:`Heading`, :class:`Table`, ...) and
rendered twice, so the Markdown and the HTML always say the same thing.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.analysis import welch_layout, welch_options
from hil.campaign.metrics import METRICS, gain_pct, gap_closed, improvement_pct, low_pass, score
from hil.campaign.model import CampaignResult, slug
from hil.campaign.runner import load_results
from hil.control.registry import needs_truth
from hil.log import LogError, read_log
from hil.reporting import (
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
    legend_below,
    new_figure,
    render_html,
    render_markdown,
    save_figure,
)

SETTLE_S = 1.0  # as hil.campaign.metrics.compute_metrics: the plots start after the swing ramped in
WINDOW_S = 2.0  # the rate-error time series
STATIC_WINDOW_S = 0.2  # seed 000 Fig. 12
LAG_PERIODS = 4  # seed 000 Fig. 13: a few periods of the excitation sine
PSD_SEGMENT = 1024  # Welch segment length, samples


# --- the neutral document --------------------------------------------------------------------


# --- numbers ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stat:
    mean: float
    lo: float
    hi: float
    n: int


def _stat(result: CampaignResult, profile: str, controller: str, metric: str) -> Stat:
    v = [x for x in result.values(profile, controller, metric) if math.isfinite(x)]
    if not v:
        return Stat(math.nan, math.nan, math.nan, 0)
    return Stat(float(np.mean(v)), min(v), max(v), len(v))


def _value(metric: str, x: float, fmt: Callable[[float], str] = format_number) -> str:
    """As the paper writes it: '+-0.72' for a range (half peak-to-peak), '0.32' for a std."""
    return f"+-{fmt(x)}" if "_range_" in metric and math.isfinite(x) else fmt(x)


def format_values(values: list[float], *, metric: str | None = None) -> str:
    """One metric over the seeds of a cell of the tables, the same in the terminal, Markdown and HTML: the mean to
    three significant digits (never an exponent), then ``(min–max)`` when more than one value, e.g.
    ``0.290 (0.280–0.300)``; ``n/a`` when there is no finite value. Non-finite values are left out. With
    ``metric`` a range metric gets the paper's ``+-`` (``+-0.290 (0.280–0.300)``)."""
    v = [float(x) for x in values if math.isfinite(x)]
    if not v:
        return "n/a"
    mean = _value(metric, float(np.mean(v))) if metric is not None else format_number(float(np.mean(v)))
    return mean + (f" ({format_number(min(v))}–{format_number(max(v))})" if len(v) > 1 else "")


def _pct(x: float) -> str:
    return f"{x:+.1f} %" if math.isfinite(x) else "n/a"


def _score_mean(result: CampaignResult, profile: str, controller: str, metric: str) -> float:
    """The mean over the seeds of the metric as better-or-worse compares it (hil.campaign.metrics.score: the
    magnitude of a lag, else the value itself, so then the table's mean)."""
    v = [score(metric, x) for x in result.values(profile, controller, metric) if math.isfinite(x)]
    return float(np.mean(v)) if v else math.nan


def _best(scores: dict[str, float], lower_is_better: bool) -> str | None:
    """The controller with the best mean score, if at least two have one."""
    have = {c: s for c, s in scores.items() if math.isfinite(s)}
    if len(have) < 2:
        return None
    return (min if lower_is_better else max)(have, key=lambda c: have[c])


def _labels(result: CampaignResult) -> list[str]:
    return [c.label for c in result.config.controllers]


def _baseline(result: CampaignResult) -> str | None:
    return result.config.baseline if len(result.config.controllers) > 1 else None


def _oracles(result: CampaignResult) -> list[str]:
    """The labels of the campaign's oracle entries (controllers that need the plant's truth)."""

    return [c.label for c in result.config.controllers if needs_truth(c.name)]


def _ranked(result: CampaignResult) -> list[str]:
    """The controllers that compete for the verdict and the best of each column: all but the oracle."""
    oracles = _oracles(result)
    return [c for c in _labels(result) if c not in oracles]


def oracle_label(result: CampaignResult) -> str | None:
    """The oracle the gap-closed column measures against: the first oracle entry, if the campaign has a baseline
    that is not an oracle; else None (no column)."""
    base, oracles = _baseline(result), _oracles(result)
    return oracles[0] if base is not None and oracles and base not in oracles else None


def gap_closed_fraction(result: CampaignResult, profile: str, controller: str, metric: str) -> float:
    """The fraction of the gap from the baseline to the oracle that ``controller`` closes on ``metric`` in
    ``profile``, from the means over seeds (hil.campaign.metrics.gap_closed); NaN without an oracle and a baseline,
    or without the values."""
    oracle, base = oracle_label(result), _baseline(result)
    if oracle is None or base is None:
        return math.nan
    return gap_closed(_score_mean(result, profile, controller, metric), _score_mean(result, profile, base, metric),
                      _score_mean(result, profile, oracle, metric))


# --- the verdict -----------------------------------------------------------------------------


def _columns(result: CampaignResult) -> list[tuple[str, str]]:
    """The verdict's columns: every profile x the campaign's primary metrics (CampaignConfig.verdict_metrics)."""
    return [(p.label, m) for p in result.config.profiles for m in result.config.verdict_metrics]


def _wins(result: CampaignResult) -> tuple[dict[str, int], int]:
    wins = dict.fromkeys(_ranked(result), 0)
    total = 0
    for profile, metric in _columns(result):
        best = _best({c: _score_mean(result, profile, c, metric) for c in wins}, METRICS[metric].lower_is_better)
        if best is not None:
            wins[best] += 1
            total += 1
    return wins, total


def _gains(result: CampaignResult, controller: str, ref: str) -> list[float]:
    out = [gain_pct(_score_mean(result, p, controller, m), _score_mean(result, p, ref, m),
                    METRICS[m].lower_is_better) for p, m in _columns(result)]
    return [g for g in out if math.isfinite(g)]


def _on_what(result: CampaignResult) -> str:
    """Which metrics the verdict is on, and which of the table's columns it leaves out."""
    primary = result.config.verdict_metrics
    others = [m for m in result.config.metrics if m not in primary]
    default = "" if result.config.primary_metrics is not None else " (by default the error metrics)"
    text = f"Verdict on the primary metric{'s' * (len(primary) != 1)}{default}: " \
           f"{', '.join(METRICS[m].label for m in primary) or 'none'}"
    return text + (f"; shown, not in the verdict: {', '.join(METRICS[m].label for m in others)}." if others else ".")


def _acceptance_summary(result: CampaignResult) -> str:
    total = len(result.config.cells())
    parts = [f"{sum(r.passed for r in result.acceptance)}/{len(result.acceptance)} acceptance rules hold",
             f"{sum(c.passed for c in result.cells)}/{total} cells pass"]
    if not result.complete:
        parts.append(f"partial campaign: {len(result.cells)}/{total} cells run")
    return f"{'PASS' if result.passed else 'FAIL'} ({'; '.join(parts)})"


def verdict(result: CampaignResult) -> Banner:
    """Which controller won (best in most primary columns: profile x primary metric), by how much (mean gain over
    the baseline on the primary metrics, or over the runner-up when the baseline won), and the campaign's PASS/FAIL.
    The table's other columns (drive ripple, ...) are not in it. The oracle is a reference, not ranked."""
    labels = _ranked(result)
    wins, total = _wins(result)
    oracles = _oracles(result)
    accept = f"Acceptance: {_acceptance_summary(result)}."
    if oracles:
        who = "The oracle" if oracles[0].lower() == "oracle" else f"The oracle ({oracles[0]})"
        accept = f"{who} is a reference, not ranked: it runs on the plant's truth (sim clock only). {accept}"
    if not labels:
        return Banner("No winner: only the oracle ran", accept, result.passed)
    if len(labels) < 2:
        besides = " besides the oracle" if oracles else ""
        return Banner(f"{labels[0]} (one controller{besides}, no comparison)", accept, result.passed)
    if not result.config.verdict_metrics:
        return Banner("No winner: no primary metric to rank on (name `primary_metrics` in the campaign)",
                      f"{_on_what(result)} {accept}", result.passed)
    if total == 0:
        return Banner("No winner: no results to compare yet", f"{_on_what(result)} {accept}", result.passed)
    ranked = sorted(labels, key=lambda c: -wins[c])  # stable: the campaign's order breaks ties
    winner = ranked[0]
    baseline = result.config.baseline
    ref = baseline if baseline is not None and baseline not in (winner, *oracles) else ranked[1]
    gains = _gains(result, winner, ref)
    if gains:
        mean = float(np.mean(gains))
        by = (f"{abs(mean):.1f} % {'better' if mean >= 0 else 'worse'} than {ref} on average "
              f"({_pct(min(gains))} to {_pct(max(gains))})")
    else:
        by = f"no primary metric to compare with {ref}"
    return Banner(f"{winner} wins", f"Best in {wins[winner]} of {total} primary columns; {by}. {_on_what(result)} "
                                    f"{accept}", result.passed)


# --- tables ----------------------------------------------------------------------------------


def _gain_cell(result: CampaignResult, profile: str, metric: str, controller: str) -> Cell:
    base = _baseline(result)
    assert base is not None
    if controller == base:
        return Cell("baseline")
    lower = METRICS[metric].lower_is_better
    text = _pct(gain_pct(_score_mean(result, profile, controller, metric), _score_mean(result, profile, base, metric),
                         lower))
    paper = result.config.paper.get(profile, {})
    theirs = improvement_pct(metric, paper.get(controller, {}).get(metric, math.nan),
                             paper.get(base, {}).get(metric, math.nan))
    return Cell(text + (f" (paper {_pct(theirs)})" if math.isfinite(theirs) else ""))


def _gap_text(fraction: float) -> str:
    return f"{100.0 * fraction:.1f} %" if math.isfinite(fraction) else "n/a"


def _metric_columns(result: CampaignResult, profile: str, metric: str) -> list[tuple[str, list[Cell]]]:
    """Ours (best emphasised, the oracle never), the paper's value if it has one, the gain vs the baseline, the
    fraction of the baseline-to-oracle gap closed (with an oracle)."""
    meta, labels = METRICS[metric], _labels(result)
    best = _best({c: _score_mean(result, profile, c, metric) for c in _ranked(result)}, meta.lower_is_better)
    cols = [(f"{meta.label} [{meta.unit}]",
             [Cell(format_values(result.values(profile, c, metric), metric=metric), best=c == best) for c in labels])]
    paper = result.config.paper.get(profile, {})
    if any(metric in paper.get(c, {}) for c in labels):
        theirs = [paper.get(c, {}).get(metric) for c in labels]
        cols.append(("paper", [Cell("—" if x is None else _value(metric, x, "{:g}".format)) for x in theirs]))
    if _baseline(result) is not None:
        cols.append((f"vs {_baseline(result)}", [_gain_cell(result, profile, metric, c) for c in labels]))
    if oracle_label(result) is not None:
        cols.append(("gap closed", [Cell(_gap_text(gap_closed_fraction(result, profile, c, metric)))
                                    for c in labels]))
    return cols


def _seeds_done(result: CampaignResult, profile: str, controller: str) -> str:
    done = sum(1 for s in result.config.seeds
               if (c := result.cell(profile, controller, s)) is not None and c.status == "completed")
    return f"{done}/{len(result.config.seeds)}"


def profile_table(result: CampaignResult, profile: str) -> Table:
    """The paper's table for one profile: one row per controller, the configured metrics as columns."""
    labels = _labels(result)
    columns = [("Controller", [Cell(c) for c in labels]),
               ("seeds", [Cell(_seeds_done(result, profile, c)) for c in labels])]
    for metric in result.config.metrics:
        columns += _metric_columns(result, profile, metric)
    return Table([h for h, _ in columns], [list(row) for row in zip(*(cells for _, cells in columns), strict=True)],
                 align="l")


def _pass_cell(passed: bool) -> Cell:
    return Cell("PASS" if passed else "FAIL", status="pass" if passed else "fail")


def cells_table(result: CampaignResult) -> Table:
    """Every cell of the matrix, run or not."""
    rows = []
    for spec in result.config.cells():
        c = result.cell(spec.profile.label, spec.controller.label, spec.seed)
        head = [Cell(spec.profile.label), Cell(spec.controller.label), Cell(str(spec.seed))]
        if c is None:
            rows.append([*head, Cell("not run"), Cell(""), Cell("—"), Cell("missing from the campaign")])
            continue
        why = "; ".join(c.failures) or (c.message if c.status != "completed" else "")
        rows.append([*head, Cell(c.status), Cell(f"{c.wall_s:.1f}"), _pass_cell(c.passed), Cell(why)])
    return Table(["profile", "controller", "seed", "status", "wall [s]", "result", "failures"], rows, "llrlrll")


# --- the document ----------------------------------------------------------------------------


def _thresholds(result: CampaignResult) -> str:
    parts = []
    for metric, t in result.config.thresholds.items():
        bounds = [f"<= {t.max:g}" if t.max is not None else "", f">= {t.min:g}" if t.min is not None else ""]
        parts.append(f"{metric} {' and '.join(b for b in bounds if b)} {METRICS[metric].unit}")
    return "Thresholds per cell: " + ("; ".join(parts) if parts else "none") + "."


def _run_info(result: CampaignResult, campaign_dir: Path) -> Bullets:
    total = len(result.config.cells())
    missing = total - len(result.cells)
    state = "complete" if result.complete else f"partial ({missing} cell{'s' * (missing != 1)} missing)"
    return Bullets([Item(f"Campaign: {state}, {len(result.cells)} of {total} cells run"),
                    Item(f"Matrix: {len(result.config.profiles)} profiles x {len(result.config.controllers)} "
                         f"controllers x {len(result.config.seeds)} seeds; analysis {result.config.analysis}"),
                    Item(f"Jobs: {result.jobs}"), Item(f"Wall time: {result.wall_s:.1f} s"),
                    Item(f"Campaign directory: {campaign_dir}")])


# --- provenance ------------------------------------------------------------------------------

SOFTWARE = [("hil", "hil_version"), ("git commit", "git_commit"), ("Python", "python"), ("numpy", "numpy"),
            ("h5py", "h5py"), ("HDF5", "hdf5"), ("scipy", "scipy"), ("numba", "numba")]
NOT_RECORDED = "Not recorded: no cell log holds the software and parameters it ran with (logs written before " \
               "the bench recorded them, or no log)."


def _cell_log(campaign_dir: Path, log: str) -> Path:
    return Path(log) if Path(log).is_absolute() else campaign_dir / log


def cell_provenance(result: CampaignResult, campaign_dir: Path) -> list[tuple[str, str, dict[str, Any]]]:
    """``(cell_id, controller label, provenance)`` of every run cell whose log recorded it, in run order
    (``hil.log.provenance.read_provenance``; an old log, an unreadable one, or a bench without that module gives
    nothing)."""
    try:
        from hil.log.provenance import read_provenance  # noqa: PLC0415  (optional: its absence is handled here)
    except ImportError:
        return []

    out = []
    for spec in result.config.cells():
        cell = result.cell(spec.profile.label, spec.controller.label, spec.seed)
        if cell is None or not cell.log:
            continue
        try:
            record = read_provenance(_cell_log(campaign_dir, cell.log))
        except (OSError, KeyError, ValueError, LogError):
            continue
        if isinstance(record, dict) and record:
            out.append((cell.cell_id, cell.controller, record))
    return out


def _text(value: Any) -> str:
    """A recorded value for the tables: floats to 12 significant digits (0.034**2 shows as 0.001156), JSON for
    lists and mappings."""
    if value is None:
        return "n/a"
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.12g}"
    return json.dumps(value, sort_keys=True)


def _software(record: dict[str, Any]) -> tuple[Any, ...]:
    return (*(record.get(key) for _, key in SOFTWARE), record.get("plant"))


def _plant_text(plant: Any) -> str:
    if not isinstance(plant, dict):
        return "none recorded (the real lab, or the emulator's plant file unreadable)"
    return f"{plant.get('path')} (SHA-256 {plant.get('sha256')})"


def provenance_blocks(result: CampaignResult, campaign_dir: Path) -> list[Block]:
    """The "Software and parameters" section: the software versions, git commit and plant file once (from the
    first cell log that recorded them; cells that ran with other software are named), then per controller the
    effective parameters it ran with, defaults included. "Not recorded" for logs that predate provenance."""
    records = cell_provenance(result, campaign_dir)
    doc: list[Block] = [Heading(2, "Software and parameters")]
    if not records:
        return [*doc, Text(NOT_RECORDED)]
    first_id, _, first = records[0]
    rows = [[Cell(name), Cell(_text(first.get(key)))] for name, key in SOFTWARE]
    rows.append([Cell("plant file"), Cell(_plant_text(first.get("plant")))])
    doc += [Text(f"Software, from the log of cell {first_id}:"), Table(["item", "recorded"], rows, "ll")]
    others = [cid for cid, _, rec in records[1:] if _software(rec) != _software(first)]
    if others:
        doc.append(Text(f"Other software or plant file in {len(others)} cell{'s' * (len(others) != 1)}: "
                        f"{', '.join(others)} (a resumed campaign?)."))
    for entry in result.config.controllers:
        doc.append(Heading(3, f"{entry.label} ({entry.name}): effective parameters"))
        mine = [(cid, rec["controller"]) for cid, label, rec in records
                if label == entry.label and isinstance(rec.get("controller"), dict)]
        if not mine:
            doc.append(Text("Not recorded."))
            continue
        cid, ctrl = mine[0]
        params = ctrl.get("params") if isinstance(ctrl.get("params"), dict) else {}
        doc.append(Table(["parameter", "value"], [[Cell(k), Cell(_text(v))] for k, v in params.items()], "ll")
                   if params else Text("No parameters recorded."))
        if "error" in ctrl:
            doc.append(Text(f"As given, not resolved: {ctrl['error']}"))
        differ = [c for c, other in mine[1:] if other.get("params") != ctrl.get("params")]
        if differ:
            doc.append(Text(f"From cell {cid}; other values in {', '.join(differ)}."))
    return doc


def build_document(result: CampaignResult, campaign_dir: Path, figures: dict[str, list[Figure]],
                   extra: list[Figure]) -> list[Block]:
    cfg = result.config
    doc: list[Block] = [Heading(1, cfg.title), verdict(result)]
    doc += [Text(cfg.description.strip())] if cfg.description.strip() else []
    doc += [Text(f"Source of the paper's values: {cfg.source}")] if cfg.source else []
    for p in cfg.profiles:
        doc += [Heading(2, p.label), profile_table(result, p.label), *figures.get(p.label, [])]
    if extra:
        doc += [Heading(2, "Identification"), *extra]
    doc += [Heading(2, "Acceptance"),
            Bullets([Item(r.rule, "pass" if r.passed else "fail", r.details) for r in result.acceptance]
                    or [Item("no acceptance rules configured")]),
            Heading(2, "Cells"), Text(_thresholds(result)), cells_table(result),
            *provenance_blocks(result, campaign_dir),
            Heading(2, "Run"), _run_info(result, campaign_dir)]
    return doc


# --- Markdown --------------------------------------------------------------------------------


# --- HTML ------------------------------------------------------------------------------------


# --- signals ---------------------------------------------------------------------------------


def welch(x: np.ndarray, fs: float, nperseg: int = PSD_SEGMENT) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density (unit²/Hz) by ``scipy.signal.welch`` with the segments and window of
    hil.analysis's FRF (Hann, >= 50 % overlap ending at the record's end, each segment detrended)."""
    from scipy import signal  # noqa: PLC0415  (heavy: loaded only when this computation runs)


    x = np.asarray(x, dtype=float)
    n = min(nperseg, x.size)
    if n < 8:
        return np.zeros(0), np.zeros(0)
    skip, noverlap = welch_layout(x.size, n)
    f, pxx = signal.welch(x[skip:], **welch_options(n, noverlap, fs))
    return f, pxx


@dataclass(frozen=True)
class Trace:
    """One controller's logged run (its first seed with a readable log) in one profile."""

    controller: str
    seed: int
    loop: dict[str, np.ndarray]
    image: dict[str, np.ndarray]
    config: dict[str, Any]

    @property
    def t(self) -> np.ndarray:
        t = self.loop["t_s"].astype(float)
        return t - t[0] if t.size else t

    @property
    def fs(self) -> float:
        dt = np.diff(self.loop["t_s"])
        return 1.0 / float(np.median(dt)) if dt.size and np.median(dt) > 0 else 1000.0

    def end(self) -> float:
        """End of the run proper (the log goes on while the swing winds down)."""
        return min(float(self.t[-1]), float(self.config.get("duration_s") or math.inf))

    def window(self, length_s: float) -> np.ndarray:
        """A ``length_s`` mask starting after settling (earlier if the run is short)."""
        end = self.end()
        start = min(SETTLE_S, max(0.0, end - length_s))
        return (self.t >= start) & (self.t < min(start + length_s, end))

    def settled(self) -> np.ndarray:
        end = self.end()
        return self.window(end - SETTLE_S if end > SETTLE_S else end)


def _read_trace(result: CampaignResult, campaign_dir: Path, profile: str, controller: str) -> Trace | None:

    for seed in result.config.seeds:
        cell = result.cell(profile, controller, seed)
        if cell is None or not cell.log:
            continue
        try:
            data = read_log(_cell_log(campaign_dir, cell.log))
        except (OSError, KeyError, ValueError, LogError):
            continue
        loop = data.groups.get("loop", {})
        if loop.get("t_s", np.zeros(0)).size < 2:
            continue
        config = data.attrs.get("config")
        return Trace(controller, seed, loop, data.groups.get("image", {}), config if isinstance(config, dict) else {})
    return None


# --- plots -----------------------------------------------------------------------------------


def _color(result: CampaignResult, controller: str) -> str:
    return f"C{_labels(result).index(controller) % 10}"


def plot_rate_error(result: CampaignResult, profile: str, traces: list[Trace], path: Path) -> Path | None:
    fig, ax = new_figure()
    for tr in traces:
        keep = tr.window(WINDOW_S)
        ax[0, 0].plot(tr.t[keep], tr.loop["rate_err_el_dps"][keep], lw=0.8, color=_color(result, tr.controller),
                      label=f"{tr.controller} (seed {tr.seed})")
    ax[0, 0].set(title=f"{profile}: elevation rate error (command - gyro)", xlabel="time [s]",
                 ylabel="rate error [deg/s]")
    legend_below(fig, ax[0, 0])
    ax[0, 0].grid(alpha=0.3)
    return save_figure(fig, path)


def _valid_frames(tr: Trace) -> np.ndarray:
    valid = tr.image.get("track_valid")
    return np.zeros(0, dtype=bool) if valid is None else valid.astype(bool)


def plot_miss(result: CampaignResult, profile: str, traces: list[Trace], path: Path) -> Path | None:
    with_frames = [tr for tr in traces if _valid_frames(tr).any()]
    if not with_frames:
        return None
    fig, ax = new_figure(2, 1, height=2.8)
    for tr in with_frames:
        t = tr.image["t_exposure_s"] - float(tr.loop["t_s"][0])
        keep = _valid_frames(tr) & (t >= min(SETTLE_S, float(t.max()))) & (t < tr.end())
        for a, axis in zip(ax[:, 0], ("y", "x"), strict=True):
            a.plot(t[keep], tr.image[f"miss_{axis}_px"][keep], lw=0.8, color=_color(result, tr.controller),
                   label=f"{tr.controller} (seed {tr.seed})")
    for a, axis in zip(ax[:, 0], ("y", "x"), strict=True):
        a.set(ylabel=f"miss {axis} [px]")
        a.grid(alpha=0.3)
    ax[0, 0].set(title=f"{profile}: miss distance (valid frames)")
    ax[1, 0].set(xlabel="time [s]")
    legend_below(fig, ax[0, 0])
    return save_figure(fig, path)


def plot_psd(result: CampaignResult, profile: str, traces: list[Trace], path: Path) -> Path | None:
    fig, ax = new_figure()
    for tr in traces:
        f, p = welch(tr.loop["rate_err_el_dps"][tr.settled()], tr.fs)
        if f.size > 1:  # DC left out: no place on a log axis
            ax[0, 0].loglog(f[1:], p[1:], lw=0.9, color=_color(result, tr.controller), label=tr.controller)
    ax[0, 0].set(title=f"{profile}: PSD of the elevation rate error (Welch)", xlabel="frequency [Hz]",
                 ylabel="PSD [(deg/s)²/Hz]")
    legend_below(fig, ax[0, 0])
    ax[0, 0].grid(alpha=0.3, which="both")
    return save_figure(fig, path)


def _bars(ax: Any, result: CampaignResult, profile: str, metric: str) -> bool:
    """One metric's bars (mean, min–max over seeds) and the paper's values as diamonds; True if it drew any."""
    labels = _labels(result)
    stats = [_stat(result, profile, c, metric) for c in labels]
    x = np.arange(len(labels))
    mean = np.array([s.mean for s in stats])
    err = np.nan_to_num(np.array([[s.mean - s.lo for s in stats], [s.hi - s.mean for s in stats]]))
    ax.bar(x, np.nan_to_num(mean), yerr=err, capsize=4, color=[_color(result, c) for c in labels])
    paper = result.config.paper.get(profile, {})
    px = [i for i, c in enumerate(labels) if metric in paper.get(c, {})]
    if px:
        ax.plot(px, [paper[labels[i]][metric] for i in px], "kD", ms=7, label="the paper's value", zorder=3)
    ax.set_xticks(x, labels, rotation=20)
    ax.set(title=METRICS[metric].label.replace("+-", "±"), ylabel=METRICS[metric].unit)
    ax.grid(alpha=0.3, axis="y")
    return bool(px)


def plot_metrics(result: CampaignResult, profile: str, traces: list[Trace], path: Path) -> Path | None:
    metrics = result.config.metrics
    cols = min(3, len(metrics))
    rows = -(-len(metrics) // cols)
    fig, ax = new_figure(rows, cols, height=3.4)
    with_paper = [a for a, metric in zip(ax.flat, metrics, strict=False) if _bars(a, result, profile, metric)]
    for a in list(ax.flat)[len(metrics) :]:
        a.set_visible(False)
    fig.suptitle(f"{profile}: mean over seeds (error bars: min–max)")
    if with_paper:  # one legend for every panel, below them
        legend_below(fig, with_paper[0])
    return save_figure(fig, path)


def _filter_window_s(result: CampaignResult, tr: Trace) -> float:
    if result.config.analysis == "filter_lag":
        freq = float((tr.config.get("excitation") or {}).get("freq_hz", math.nan))
        if math.isfinite(freq) and freq > 0:
            return LAG_PERIODS / freq
    return STATIC_WINDOW_S


def plot_filters(result: CampaignResult, profile: str, traces: list[Trace], path: Path) -> Path | None:
    """Seed 000 Figs. 12/13: the raw elevation gyro, the 150 Hz low-pass of it and the KF estimate."""
    fig, ax = new_figure(len(traces), 1, height=2.8)
    for a, tr in zip(ax[:, 0], traces, strict=True):
        raw = tr.loop["gyro_y_dps"].astype(float)
        keep = tr.window(_filter_window_s(result, tr))
        t = tr.t[keep]
        # raw: each 1 ms sample a dot, so it shows where the filters follow it closely; the filters thin, on top
        a.plot(t, raw[keep], ".-", lw=0.5, ms=3.0, color="0.25", zorder=1, label="raw gyro (each sample)")
        a.plot(t, low_pass(raw)[keep], lw=1.0, color="C1", alpha=0.9, zorder=2, label="150 Hz low-pass")
        a.plot(t, tr.loop["rate_fb_el_dps"][keep], lw=1.0, color="C0", alpha=0.9, zorder=3, label="KF (fed back)")
        a.set(title=f"{profile}, {tr.controller} (seed {tr.seed})", ylabel="EL rate [deg/s]")
        a.grid(alpha=0.3)
    ax[-1, 0].set(xlabel="time [s]")
    legend_below(fig, ax[0, 0])
    return save_figure(fig, path)


Plotter = Callable[[CampaignResult, str, list[Trace], Path], Path | None]

PLOTS: list[tuple[str, Plotter, str]] = [
    ("rate-error", plot_rate_error, "elevation rate error, {w:g} s after settling, first logged seed"),
    ("miss", plot_miss, "miss distance y (top) and x (bottom), valid frames"),
    ("psd", plot_psd, "PSD of the elevation rate error after settling (Welch, Hann, 50 % overlap)"),
    ("metrics", plot_metrics, "the table's metrics per controller: mean, min–max over seeds, the paper's value"),
]
FILTER_PLOTS = {"static_noise": "at rest: raw gyro vs 150 Hz low-pass vs KF over {s:g} s (seed 000 Fig. 12)",
                "filter_lag": "sine on the rate command: raw gyro vs 150 Hz low-pass vs KF, "
                              f"{LAG_PERIODS} periods (seed 000 Fig. 13)"}


def _profile_plots(result: CampaignResult, campaign_dir: Path, out_dir: Path, profile: str) -> list[Figure]:
    traces = [tr for c in _labels(result) if (tr := _read_trace(result, campaign_dir, profile, c)) is not None]
    plots = list(PLOTS)
    if result.config.analysis in FILTER_PLOTS:
        plots.append(("filters", plot_filters, FILTER_PLOTS[result.config.analysis]))
    figures = []
    for name, plot, caption in plots:
        if not traces and name != "metrics":
            continue
        path = plot(result, profile, traces, out_dir / f"{slug(profile)}-{name}.png")
        if path is not None:
            figures.append(Figure(path, f"{profile}: {caption.format(w=WINDOW_S, s=STATIC_WINDOW_S)}"))
    return figures


def _bode_figures(campaign_dir: Path, out_dir: Path) -> list[Figure]:
    found = sorted(p for p in campaign_dir.rglob("bode*.png") if out_dir.resolve() not in p.resolve().parents)
    return [Figure(p, f"{p.relative_to(campaign_dir).as_posix()} (hil ident)") for p in found]


# --- entry point -----------------------------------------------------------------------------


def write_report(campaign_dir: Path, out_dir: Path | None = None) -> ReportFiles:
    """Write report.md, report.html and the PNGs of the campaign in ``campaign_dir`` (default output:
    ``campaign_dir/report/``). Raises hil.campaign.CampaignError if it holds no campaign.json."""
    campaign_dir = Path(campaign_dir)
    result = load_results(campaign_dir)
    out = Path(out_dir) if out_dir is not None else campaign_dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    figures = {p.label: _profile_plots(result, campaign_dir, out, p.label) for p in result.config.profiles}
    extra = _bode_figures(campaign_dir, out)
    doc = build_document(result, campaign_dir, figures, extra)
    md, page = out / "report.md", out / "report.html"
    md.write_text(render_markdown(doc, out), encoding="utf-8")
    page.write_text(render_html(doc), encoding="utf-8")
    return ReportFiles(md, page, [f.path for fs in figures.values() for f in fs] + [f.path for f in extra])
