"""Campaign report: a synthetic campaign directory (small HDF5 logs, a campaign.json, no sessions run)
rendered to Markdown, self-contained HTML and PNGs; partial campaigns; the filter analyses; Welch."""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.campaign import METRICS, report
from hil.campaign.model import CampaignConfig, CampaignResult, CellResult
from hil.campaign.report import format_values, gain_pct, profile_table, welch, write_report
from hil.campaign.runner import CAMPAIGN_JSON, judge
from hil.log import SCHEMA, SessionLog
from hil.log.schema import group_by_name
from hil.reporting._render import _esc as escape_html  # the page escapes as the renderer does

ROOT = Path(__file__).resolve().parents[2]
G = group_by_name(SCHEMA)
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
P1, P3 = "1 deg / 1 Hz", "3 deg / 1 Hz"

# per (profile, controller): the metric per seed (1, 2); ESO+KF clearly better
METRIC_VALUES = {
    ("ESO", "rate_err_el_range_dps"): [0.70, 0.74], ("ESO+KF", "rate_err_el_range_dps"): [0.28, 0.30],
    ("ESO", "rate_err_el_std_dps"): [0.30, 0.34], ("ESO+KF", "rate_err_el_std_dps"): [0.16, 0.18],
    ("ESO", "miss_std_px"): [6.0, 6.2], ("ESO+KF", "miss_std_px"): [2.7, 2.9],
}
PAPER = {P1: {"ESO": {"rate_err_el_range_dps": 0.72, "rate_err_el_std_dps": 0.32, "miss_std_px": 6.02},
              "ESO+KF": {"rate_err_el_range_dps": 0.28, "rate_err_el_std_dps": 0.17, "miss_std_px": 2.71}}}


def campaign_config(tmp_path: Path, **changes: Any) -> CampaignConfig:
    data: dict[str, Any] = {
        "name": "synthetic", "title": "ESO vs ESO+KF (synthetic)", "description": "A made-up campaign.",
        "source": "seed 000, Tables 1-2", "session": "profiles/sessions/swing-1deg-1hz-eso.yaml",
        "profiles": [{"label": P1, "path": "profiles/swing/swing-1deg-1hz.yaml"},
                     {"label": P3, "path": "profiles/swing/swing-3deg-1hz.yaml"}],
        "controllers": [{"label": "ESO", "name": "eso"}, {"label": "ESO+KF", "name": "eso_kf"}],
        "seeds": [1, 2], "baseline": "ESO",
        "metrics": ["rate_err_el_range_dps", "rate_err_el_std_dps", "miss_std_px"],
        "thresholds": {"miss_std_px": {"max": 7.0}},
        "acceptance": [{"metric": "miss_std_px", "better": "ESO+KF", "than": "ESO", "by_pct": 40}],
        "paper": PAPER,
    }
    data.update(changes)
    return CampaignConfig.model_validate(data, context={"base_dir": ROOT})


def _row(group: str, values: dict[str, Any]) -> tuple[Any, ...]:
    return tuple(values.get(c.name, 0) for c in G[group].channels)


def write_log(path: Path, noise: float, seed: int, n: int = 3000, config: dict[str, Any] | None = None) -> None:
    """A 1 kHz log of ``n`` cycles: elevation rate error = white noise of std ``noise`` plus a 1 Hz swing
    residual; the KF estimate a smoothed gyro; 100 Hz miss distances proportional to ``noise``."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 1000.0
    gyro = noise * rng.standard_normal(n) + 0.2 * noise * np.sin(2 * np.pi * t)
    kf = np.convolve(gyro, np.ones(8) / 8, mode="same")
    attrs = {"config": {"duration_s": n / 1000.0, **(config or {})}, "ident": {}, "seed": seed}
    with SessionLog(path, attrs=attrs, fsync=False) as log:
        for k in range(n):
            log.append("loop", _row("loop", {"tick": k, "t_s": 5.0 + t[k], "t_host_ns": 1_000_000 * (k + 1),
                                             "gyro_y_dps": gyro[k],
                                             "rate_fb_el_dps": kf[k], "rate_err_el_dps": -gyro[k]}))
        for f in range(n // 10):
            miss = 10 * noise * rng.standard_normal(2)
            log.append("image", _row("image", {"frame": f, "t_exposure_s": 5.0 + f / 100.0,
                                               "t_host_ns": 10_000_000 * (f + 1), "miss_x_px": miss[0],
                                               "miss_y_px": miss[1], "track_valid": int(f % 7 != 0)}))


def cell(config: CampaignConfig, profile: str, controller: str, seed: int, **kw: Any) -> CellResult:
    spec = next(s for s in config.cells()
                if (s.profile.label, s.controller.label, s.seed) == (profile, controller, seed))
    return CellResult(cell_id=spec.cell_id, profile=profile, controller=controller,
                      controller_name=spec.controller.name, seed=seed, wall_s=3.2,
                      **({"status": "completed", "exit_code": 0, "log": f"cells/{spec.cell_id}/session.h5"} | kw))


def make_campaign(out: Path, config: CampaignConfig, cells: list[CellResult], complete: bool) -> Path:
    for c in cells:
        if c.log:
            (out / c.log).parent.mkdir(parents=True, exist_ok=True)
            write_log(out / c.log, noise=0.3 if c.controller == "ESO" else 0.15, seed=c.seed)
    result = CampaignResult(config=config, cells=cells, acceptance=judge(config, cells), jobs=2, wall_s=12.5,
                            complete=complete)
    (out / CAMPAIGN_JSON).write_text(result.model_dump_json(indent=2))
    return out


def full_cells(config: CampaignConfig) -> list[CellResult]:
    return [cell(config, p, c, s, metrics={m: METRIC_VALUES[(c, m)][s - 1] for m in config.metrics})
            for p in (P1, P3) for c in ("ESO", "ESO+KF") for s in (1, 2)]


@pytest.fixture(scope="module")
def full(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    out = tmp_path_factory.mktemp("campaign")
    config = campaign_config(out)
    make_campaign(out, config, full_cells(config), complete=True)
    return out, write_report(out)


def _table_rows(md: str, heading: str) -> dict[str, str]:
    section = md.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return {line.split(" | ")[0].lstrip("| "): line for line in section.splitlines() if line.startswith("| ESO")}


def test_markdown_table_numbers_paper_and_gain(full):
    out, files = full
    assert files.markdown == out / "report" / "report.md" and files.html == out / "report" / "report.html"
    md = files.markdown.read_text()
    rows = _table_rows(md, P1)
    # ESO+KF best everywhere (bold); mean (min–max) over seeds; +- for ranges; the paper; the gain vs ESO
    assert rows["ESO+KF"] == ("| ESO+KF | 2/2 | **+-0.290 (0.280–0.300)** | +-0.28 | +59.7 % (paper +61.1 %) "
                              "| **0.170 (0.160–0.180)** | 0.17 | +46.9 % (paper +46.9 %) "
                              "| **2.80 (2.70–2.90)** | 2.71 | +54.1 % (paper +55.0 %) |")
    assert rows["ESO"] == ("| ESO | 2/2 | +-0.720 (0.700–0.740) | +-0.72 | baseline "
                           "| 0.320 (0.300–0.340) | 0.32 | baseline | 6.10 (6.00–6.20) | 6.02 | baseline |")
    header = md.split(f"## {P1}\n", 1)[1].strip().splitlines()[0]
    assert header == ("| Controller | seeds | EL rate error +- [deg/s] | paper | vs ESO | EL rate error std [deg/s] "
                      "| paper | vs ESO | miss std [px] | paper | vs ESO |")
    assert "paper" not in md.split(f"## {P3}\n", 1)[1].strip().splitlines()[0]  # no paper values for 3 deg
    assert "Source of the paper's values: seed 000, Tables 1-2" in md and "A made-up campaign." in md


def test_verdict_acceptance_cells_and_run_info(full):
    md = full[1].markdown.read_text()
    assert md.startswith("# ESO vs ESO+KF (synthetic)\n")
    verdict = md.splitlines()[2]
    assert verdict.startswith("> **Verdict: ESO+KF wins.** Best in 6 of 6 primary columns; ")
    assert "better than ESO on average" in verdict and "Acceptance: PASS" in verdict
    mean_gain = np.mean([gain_pct(b, a) for a, b in ((0.72, 0.29), (0.32, 0.17), (6.1, 2.8))])
    assert f"{mean_gain:.1f} % better than ESO" in verdict
    acceptance = md.split("## Acceptance\n", 1)[1].split("\n## ", 1)[0]
    assert "- **PASS** ESO+KF lowers miss_std_px vs ESO by >= 40 %" in acceptance
    assert "  - 1 deg / 1 Hz, seed 1: ESO 6 -> ESO+KF 2.7 (+55.0 %)" in acceptance
    cells = md.split("## Cells\n", 1)[1]
    assert "Thresholds per cell: miss_std_px <= 7 px." in cells
    assert cells.count("| completed | 3.2 | PASS |") == 8
    run = md.split("## Run\n", 1)[1]
    assert "Campaign: complete, 8 of 8 cells run" in run and "Jobs: 2" in run and "Wall time: 12.5 s" in run


def test_pngs_are_valid_and_the_html_is_self_contained(full):
    files = full[1]
    names = {p.name for p in files.pngs}
    for profile in ("1-deg-1-hz", "3-deg-1-hz"):
        assert {f"{profile}-{k}.png" for k in ("rate-error", "miss", "psd", "metrics")} <= names
    for p in files.pngs:
        assert p.read_bytes()[:8] == PNG_MAGIC, p
    page = files.html.read_text()
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", page, re.I)
    assert "<link" not in page and "<script" not in page
    assert page.count("data:image/png;base64,") == len(files.pngs)
    assert '<div class="banner pass"><div class="headline">ESO+KF wins</div>' in page
    assert '<td class="best">±0.290 (0.280–0.300)</td>' in page
    assert '<span class="pass">PASS</span>' in page and re.search(r'<td class="pass[ a-z]*">PASS</td>', page)
    md = files.markdown.read_text()
    assert md.count("](1-deg-1-hz-") == 4  # relative image links next to report.md


def test_bode_plots_are_included(tmp_path):
    config = campaign_config(tmp_path, profiles=[{"label": P1, "path": "profiles/swing/swing-1deg-1hz.yaml"}],
                             seeds=[1])
    cells = [cell(config, P1, c, 1, log=None, metrics={m: METRIC_VALUES[(c, m)][0] for m in config.metrics})
             for c in ("ESO", "ESO+KF")]
    make_campaign(tmp_path, config, cells, complete=True)
    (tmp_path / "ident").mkdir()
    first = write_report(tmp_path, tmp_path / "r1")
    shutil.copy(next(p for p in first.pngs if p.name.endswith("metrics.png")), tmp_path / "ident" / "bode-el.png")
    files = write_report(tmp_path, tmp_path / "r2")
    assert tmp_path / "ident" / "bode-el.png" in files.pngs
    assert "## Identification" in files.markdown.read_text()
    assert "](../ident/bode-el.png)" in files.markdown.read_text()
    assert files.html.read_text().count("data:image/png;base64,") == len(files.pngs)


def test_partial_campaign_renders_and_says_partial(tmp_path):
    config = campaign_config(tmp_path)
    cells = full_cells(config)
    cells.pop()  # 3 deg, ESO+KF, seed 2 never ran
    errored = cells.index(next(c for c in cells if (c.profile, c.controller, c.seed) == (P1, "ESO", 2)))
    cells[errored] = cell(config, P1, "ESO", 2, status="error", exit_code=2, log=None,
                          message="boom", failures=["session error: boom"])
    nan_cell = cells[0].model_copy(update={"metrics": {**cells[0].metrics, "rate_err_el_std_dps": float("nan")}})
    in_memory = CampaignResult(config=config, cells=[nan_cell, *cells[1:]])
    assert profile_table(in_memory, P1).rows[0][5].text == "n/a"  # NaN: not a number to show, not the best
    cells[0] = cells[0].model_copy(update={"metrics": {k: v for k, v in cells[0].metrics.items()
                                                       if k != "rate_err_el_std_dps"}})  # JSON has no NaN
    make_campaign(tmp_path, config, cells, complete=False)
    files = write_report(tmp_path)
    md = files.markdown.read_text()
    assert "Acceptance: FAIL" in md.splitlines()[2] and "partial campaign: 7/8 cells run" in md.splitlines()[2]
    assert "Campaign: partial (1 cell missing), 7 of 8 cells run" in md
    assert f"| {P3} | ESO+KF | 2 | not run |  | — | missing from the campaign |" in md
    assert f"| {P1} | ESO | 2 | error | 3.2 | **FAIL** | session error: boom |" in md
    rows = _table_rows(md, P1)
    assert rows["ESO"].startswith("| ESO | 1/2 | +-0.700 | +-0.72 | baseline | n/a | 0.32 | baseline |")
    assert _table_rows(md, P3)["ESO+KF"].startswith("| ESO+KF | 1/2 | **+-0.280** |")
    assert "not available" in md  # the acceptance rule on the missing cells
    assert '<div class="banner fail">' in files.html.read_text()
    assert all(p.read_bytes()[:8] == PNG_MAGIC for p in files.pngs)


LAG_LOG = {"excitation": {"axis": "el", "freq_hz": 15.0, "amplitude_dps": 5.0}}


def filter_campaign(tmp_path: Path, analysis: str, log_config: dict[str, Any]) -> Path:
    """A one-cell campaign of a filter analysis (static_noise or filter_lag) with its log."""
    config = campaign_config(tmp_path, analysis=analysis, profiles=[{"label": "static", "path":
                             "profiles/swing/static.yaml"}], controllers=[{"label": "ESO+KF", "name": "eso_kf"}],
                             seeds=[3], baseline=None, acceptance=[], paper={}, thresholds={},
                             metrics=["gyro_raw_peak_dps", "gyro_kf_peak_dps"] if analysis == "static_noise"
                             else ["lag_lpf_cycles", "lag_kf_cycles"], overrides={})
    c = cell(config, "static", "ESO+KF", 3, metrics={m: 1.5 for m in config.metrics})
    (tmp_path / c.log).parent.mkdir(parents=True)
    write_log(tmp_path / c.log, noise=0.2, seed=3, n=1500, config=log_config)
    result = CampaignResult(config=config, cells=[c], jobs=1, wall_s=2.0, complete=True)
    (tmp_path / CAMPAIGN_JSON).write_text(result.model_dump_json())
    return tmp_path


@pytest.mark.parametrize(("analysis", "log_config"), [("static_noise", {}), ("filter_lag", LAG_LOG)])
def test_filter_analyses_add_their_plot(tmp_path, monkeypatch, analysis, log_config):
    """The filter plot shows the raw gyro (a dot per sample, underneath) and the two filters (thin, on top)."""
    fig = _figures(filter_campaign(tmp_path, analysis, log_config), monkeypatch)["static-filters.png"]
    assert (tmp_path / "spied" / "static-filters.png").read_bytes()[:8] == PNG_MAGIC
    md = (tmp_path / "spied" / "report.md").read_text()
    assert "Verdict: ESO+KF (one controller, no comparison)" in md and "Acceptance: PASS" in md
    assert "| ESO+KF | 1/1 | 1.50 | 1.50 |" in md and "vs " not in md.split("## static\n", 1)[1].splitlines()[0]
    _legend_clear_of_the_data(fig)
    raw, lpf, kf = fig.axes[0].get_lines()
    assert raw.get_label().startswith("raw gyro") and lpf.get_label() == "150 Hz low-pass"
    assert kf.get_label() == "KF (fed back)"
    assert raw.get_zorder() < lpf.get_zorder() < kf.get_zorder()  # filters drawn over the raw samples
    assert raw.get_marker() == "." and raw.get_markersize() >= 2.5  # each raw sample a dot, visible around them
    assert raw.get_xdata().size == lpf.get_xdata().size > 100
    assert lpf.get_linewidth() <= 1.0 and kf.get_linewidth() <= 1.0


def test_welch_matches_white_noise_and_finds_a_sine():
    rng = np.random.default_rng(0)
    fs = 1000.0
    f, p = welch(2.0 * rng.standard_normal(20_000), fs)
    assert f[1] - f[0] == pytest.approx(fs / 1024)
    assert np.sum(p) * (f[1] - f[0]) == pytest.approx(4.0, rel=0.05)  # Parseval: the variance
    assert np.median(p) == pytest.approx(4.0 / (fs / 2), rel=0.15)
    t = np.arange(8192) / fs
    f, p = welch(np.sin(2 * np.pi * 50.0 * t), fs)
    assert abs(f[np.argmax(p)] - 50.0) <= fs / 1024
    assert welch(np.zeros(4), fs)[0].size == 0


def test_gain_pct():
    assert gain_pct(0.28, 0.72) == pytest.approx(61.11, abs=0.01)
    assert gain_pct(2.0, 1.0, lower_is_better=False) == pytest.approx(100.0)
    assert np.isnan(gain_pct(1.0, 0.0)) and np.isnan(gain_pct(float("nan"), 1.0))


# --- numbers alike in the terminal, Markdown and HTML ------------------------------------------------------------


def test_format_values():
    assert format_values([0.28, 0.30, 0.29]) == "0.290 (0.280–0.300)"
    assert format_values([0.28, 0.30, 0.29], metric="rate_err_el_range_dps") == "+-0.290 (0.280–0.300)"
    assert format_values([6.02], metric="miss_std_px") == "6.02"  # one seed: no spread
    assert format_values([1234.4, 1300.0]) == "1267 (1234–1300)"  # never an exponent
    assert format_values([0.000512]) == "0.000512"
    assert format_values([9.996]) == "10.0" and format_values([0.09996]) == "0.100"  # the rounding's digits
    assert format_values([999.7]) == "1000"
    assert format_values([-0.0123, 0.0]) == "-0.00615 (-0.0123–0)"
    assert format_values([2.0, float("nan")]) == "2.00"  # a NaN seed is left out
    assert format_values([]) == "n/a" and format_values([float("nan")]) == "n/a"


def test_every_metric_cell_is_format_values(full):
    out, files = full
    result = report.load_results(out)
    page = files.html.read_text()
    for profile in (P1, P3):
        table = profile_table(result, profile)
        for metric in result.config.metrics:
            col = table.header.index(f"{METRICS[metric].label} [{METRICS[metric].unit}]")
            for row in table.rows:
                values = result.values(profile, row[0].text, metric)
                assert len(values) == 2
                assert row[col].text == format_values(values, metric=metric)
                assert escape_html(row[col].text) in page
    assert "| **+-0.290 (0.280–0.300)** |" in files.markdown.read_text()


# --- provenance ----------------------------------------------------------------------------------------------------


def _provenance(controller: str, omega: float, commit: str = "0123abcd" * 5) -> dict[str, Any]:
    return {"hil_version": "0.1.0", "git_commit": commit, "python": "3.11.7", "numpy": "2.4.6", "h5py": "3.16.0",
            "scipy": "1.17.1", "numba": "0.68.1", "plant": {"path": "/lab/profiles/plant/default.yaml",
                                                            "sha256": "95fa" + "0" * 60},
            "controller": {"name": controller, "params": {"omega_o_rad_s": omega, "b0_dps2_per_count": 0.023,
                                                          "r_dps2": 0.034**2, "steady_state": True,
                                                          "u_max_counts": 32767}}}


def test_software_and_parameters_section(full, monkeypatch):
    from hil.log import provenance

    out = full[0]
    seen: list[Path] = []

    def fake(path: Path) -> dict[str, Any]:
        seen.append(Path(path))
        if "eso-kf" in Path(path).parent.name:
            return _provenance("eso_kf", 300.0, commit="fedc" * 10 if "3-deg" in str(path) else "0123abcd" * 5)
        return _provenance("eso", 150.0)

    monkeypatch.setattr(provenance, "read_provenance", fake)
    files = write_report(out, out / "report-provenance")
    assert len(seen) == 8 and all(p.is_file() for p in seen)  # every cell's log, nothing else
    md = files.markdown.read_text()
    section = md.split("## Software and parameters\n", 1)[1].split("\n## ", 1)[0]
    assert "Software, from the log of cell 1-deg-1-hz--eso--s1:" in section
    assert section.count("0123abcd" * 5) == 1 and section.count("| numpy | 2.4.6 |") == 1
    assert "| plant file | /lab/profiles/plant/default.yaml (SHA-256 95fa" in section
    # the ESO+KF cells of the 3 deg profile ran from another commit: named, not hidden
    assert "Other software or plant file in 2 cells: 3-deg-1-hz--eso-kf--s1, 3-deg-1-hz--eso-kf--s2" in section
    eso = section.split("### ESO (eso): effective parameters\n", 1)[1].split("###", 1)[0]
    kf = section.split("### ESO+KF (eso_kf): effective parameters\n", 1)[1]
    assert "| omega_o_rad_s | 150 |" in eso and "| omega_o_rad_s | 300 |" in kf
    assert "| r_dps2 | 0.001156 |" in kf and "| steady_state | true |" in kf and "| u_max_counts | 32767 |" in kf
    assert md.index("## Cells") < md.index("## Software and parameters") < md.index("## Run")
    page = files.html.read_text()
    assert "<h2>Software and parameters</h2>" in page and "<h3>ESO+KF (eso_kf): effective parameters</h3>" in page
    assert '<td class="l">omega_o_rad_s</td><td class="l">150</td>' in page


def test_logs_without_provenance_say_not_recorded(full, monkeypatch):
    out, files = full
    md = files.markdown.read_text()  # the synthetic logs predate provenance: read_provenance gives {}
    assert "## Software and parameters\n\n" + report.NOT_RECORDED in md
    assert "effective parameters" not in md
    monkeypatch.setitem(__import__("sys").modules, "hil.log.provenance", None)  # a bench without the module
    again = write_report(out, out / "report-again")
    assert report.NOT_RECORDED in again.markdown.read_text() and report.NOT_RECORDED in again.html.read_text()


# --- plots ---------------------------------------------------------------------------------------------------------


def _figures(campaign_dir: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Write the report and keep each PNG's matplotlib figure, laid out as saved."""
    figures: dict[str, Any] = {}
    save = report.save_figure

    def spy(fig: Any, path: Path) -> Path:
        figures[path.name] = fig
        return save(fig, path)

    monkeypatch.setattr(report, "save_figure", spy)
    write_report(campaign_dir, campaign_dir / "spied")
    for fig in figures.values():
        fig.draw_without_rendering()
    return figures


def _legend_clear_of_the_data(fig: Any) -> None:
    axes = [a for a in fig.axes if a.get_visible()]
    assert all(a.get_legend() is None for a in axes)  # no legend inside an axes
    assert len(fig.legends) == 1
    box = fig.legends[0].get_window_extent()
    assert box.y1 <= min(a.get_window_extent().y0 for a in axes)  # below every axes
    assert box.y0 >= 0 and box.x0 >= 0 and box.x1 <= fig.bbox.x1  # inside the page


def test_legends_are_below_the_axes_and_the_psd_is_on_log_axes(full, monkeypatch):
    figures = _figures(full[0], monkeypatch)
    for kind in ("rate-error", "miss", "psd", "metrics"):
        fig = figures[f"1-deg-1-hz-{kind}.png"]
        _legend_clear_of_the_data(fig)
    labels = [t.get_text() for t in figures["1-deg-1-hz-metrics.png"].legends[0].get_texts()]
    assert labels == ["the paper's value"]
    assert "3-deg-1-hz-metrics.png" in figures and not figures["3-deg-1-hz-metrics.png"].legends  # no paper values
    psd = figures["1-deg-1-hz-psd.png"].axes[0]
    assert psd.get_xscale() == "log" and psd.get_yscale() == "log"
    f_lo = min(float(np.min(line.get_xdata())) for line in psd.get_lines())
    assert f_lo == pytest.approx(1000.0 / 1024)  # the first bin above DC


# --- the oracle: the fraction of the baseline-to-oracle gap each controller closes ---------------------------------

ORACLE_VALUES = {**METRIC_VALUES, ("oracle", "rate_err_el_range_dps"): [0.10, 0.12],
                 ("oracle", "rate_err_el_std_dps"): [0.05, 0.07], ("oracle", "miss_std_px"): [1.0, 1.2]}


def oracle_result(tmp_path: Path, oracle: str = "oracle", **changes: Any) -> CampaignResult:
    """One profile, ESO (baseline), ESO+KF and the oracle (labelled ``oracle``), two seeds each, no logs."""
    config = campaign_config(tmp_path, profiles=[{"label": P1, "path": "profiles/swing/swing-1deg-1hz.yaml"}],
                             controllers=[{"label": "ESO", "name": "eso"}, {"label": "ESO+KF", "name": "eso_kf"},
                                          {"label": oracle, "name": "oracle"}], **changes)
    cells = [cell(config, P1, c, s, log=None,
                  metrics={m: ORACLE_VALUES[("oracle" if c == oracle else c, m)][s - 1] for m in config.metrics})
             for c in ("ESO", "ESO+KF", oracle) for s in (1, 2)]
    return CampaignResult(config=config, cells=cells, acceptance=judge(config, cells), jobs=1, wall_s=1.0,
                          complete=True)


def test_gap_closed_formula():
    from hil.campaign.metrics import gap_closed

    assert gap_closed(0.17, 0.32, 0.06) == pytest.approx(0.15 / 0.26)
    assert gap_closed(0.32, 0.32, 0.06) == 0.0 and gap_closed(0.06, 0.32, 0.06) == 1.0
    assert gap_closed(0.45, 0.32, 0.06) == pytest.approx(-0.5)  # worse than the baseline
    assert gap_closed(5.0, 2.0, 8.0) == 0.5  # higher is better: the same formula
    assert np.isnan(gap_closed(0.2, 0.3, 0.3)) and np.isnan(gap_closed(float("nan"), 0.3, 0.1))


def test_gap_closed_column_with_an_oracle(tmp_path):
    result = oracle_result(tmp_path)
    # means over the seeds: range ESO 0.72, ESO+KF 0.29, oracle 0.11; std 0.32, 0.17, 0.06; miss 6.1, 2.8, 1.1
    assert report.oracle_label(result) == "oracle"
    for metric, expected in (("rate_err_el_range_dps", 0.43 / 0.61), ("rate_err_el_std_dps", 0.15 / 0.26),
                             ("miss_std_px", 3.3 / 5.0)):
        assert report.gap_closed_fraction(result, P1, "ESO+KF", metric) == pytest.approx(expected)
        assert report.gap_closed_fraction(result, P1, "ESO", metric) == pytest.approx(0.0, abs=1e-12)
        assert report.gap_closed_fraction(result, P1, "oracle", metric) == pytest.approx(1.0)
    table = profile_table(result, P1)
    assert table.header == ["Controller", "seeds", "EL rate error +- [deg/s]", "paper", "vs ESO", "gap closed",
                            "EL rate error std [deg/s]", "paper", "vs ESO", "gap closed", "miss std [px]", "paper",
                            "vs ESO", "gap closed"]
    rows = {row[0].text: row for row in table.rows}
    assert [rows["ESO+KF"][i].text for i in (5, 9, 13)] == ["70.5 %", "57.7 %", "66.0 %"]
    assert [rows["ESO"][i].text for i in (5, 9, 13)] == ["0.0 %"] * 3
    assert [rows["oracle"][i].text for i in (5, 9, 13)] == ["100.0 %"] * 3
    # the oracle is a reference: the best of each column is the best real controller
    assert rows["ESO+KF"][2].best and not rows["oracle"][2].best
    assert rows["oracle"][2].text == "+-0.110 (0.100–0.120)" and rows["oracle"][3].text == "—"
    banner = report.verdict(result)
    assert banner.headline == "ESO+KF wins" and "Best in 3 of 3 primary columns" in banner.text
    assert "The oracle is a reference, not ranked: it runs on the plant's truth (sim clock only)." in banner.text
    renamed = oracle_result(tmp_path, oracle="truth")
    assert "The oracle (truth) is a reference" in report.verdict(renamed).text
    assert report.gap_closed_fraction(renamed, P1, "ESO+KF", "miss_std_px") == pytest.approx(3.3 / 5.0)

    make_campaign(tmp_path, result.config, result.cells, complete=True)
    files = write_report(tmp_path)
    md = files.markdown.read_text()
    assert ("| ESO+KF | 2/2 | **+-0.290 (0.280–0.300)** | +-0.28 | +59.7 % (paper +61.1 %) | 70.5 % "
            "| **0.170 (0.160–0.180)** | 0.17 | +46.9 % (paper +46.9 %) | 57.7 % "
            "| **2.80 (2.70–2.90)** | 2.71 | +54.1 % (paper +55.0 %) | 66.0 % |") in md
    assert "| oracle | 2/2 | +-0.110 (0.100–0.120) | — | +84.7 % | 100.0 % |" in md
    page = files.html.read_text()
    assert page.count("<th>gap closed</th>") == 3 and "<td>70.5 %</td>" in page


def test_no_gap_column_without_an_oracle_or_a_baseline(tmp_path):
    no_baseline = oracle_result(tmp_path, baseline=None)
    assert report.oracle_label(no_baseline) is None and "gap closed" not in profile_table(no_baseline, P1).header
    oracle_baseline = oracle_result(tmp_path, baseline="oracle")
    assert report.oracle_label(oracle_baseline) is None
    assert "gap closed" not in profile_table(oracle_baseline, P1).header
    plain = CampaignResult(config=campaign_config(tmp_path), cells=full_cells(campaign_config(tmp_path)))
    assert report.oracle_label(plain) is None and "gap closed" not in profile_table(plain, P1).header
