"""The `hil` command line (typer). Exit codes: 0 ok, 1 a check failed, 2 bad input."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from hil import __version__

app = typer.Typer(
    name="hil",
    help="Hardware-in-the-loop bench for electro-optical stabilized platforms.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
protocol_app = typer.Typer(help="The framed serial protocol: docs and capture decoding.", no_args_is_help=True)
app.add_typer(protocol_app, name="protocol")

console = Console()
err_console = Console(stderr=True, soft_wrap=True)


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print one line naming what is wrong and return the Exit to raise (the message is shown as is: a
    file name or value holding ``[...]`` is not taken for markup)."""
    from rich.markup import escape

    err_console.print(f"[bold red]error:[/] {escape(' '.join(message.split()))}", highlight=False)
    return typer.Exit(code)


def finite(option: str, value: float | None) -> None:
    """NaN and infinities are refused for every float option (click's ranges let NaN through)."""
    if value is not None and not math.isfinite(value):
        raise fail(f"{option}: {value!r} is not a finite number")


def check_out_dir(path: Path, option: str) -> None:
    """``path`` is a directory we may write into, or one we may create (nothing is created here); exit 2
    naming the option otherwise. Checked before anything starts, so a bad one never reaches a board."""
    import os

    target = path.absolute()
    if target.exists() and not target.is_dir():
        raise fail(f"{option} {path}: exists and is not a directory")
    parent = target
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise fail(f"{option} {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise fail(f"{option} {path}: {parent} is not writable")


def check_input_file(path: Path) -> None:
    """``path`` names a regular file (a FIFO, device or directory is refused unopened); exit 2 otherwise."""
    from hil.config import require_regular_file

    try:
        require_regular_file(path)
    except ValueError as exc:
        raise fail(str(exc)) from None


@app.callback(invoke_without_command=True)
def _main(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    if version:
        console.print(f"hil {__version__}")
        raise typer.Exit(0)


@app.command()
def selftest(
    ticks: Annotated[int, typer.Option(min=100, max=3_600_000, help="GYRO_SAMPLEs to stream at 1 kHz.")] = 3000,
    seed: Annotated[int, typer.Option(help="Seed of the injected faults.")] = 1,
    garbage_rate: Annotated[float, typer.Option(min=0, max=1, help="Chance of a garbage burst per frame.")] = 0.01,
    flip_rate: Annotated[float, typer.Option(min=0, max=1, help="Chance of a flipped bit per frame.")] = 0.005,
    json_out: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False,
) -> None:
    """Protocol self-test: the bench against an emulated servo board on a pty, with injected faults."""
    import dataclasses
    import json

    finite("--garbage-rate", garbage_rate)
    finite("--flip-rate", flip_rate)

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from hil.selftest import main_sync

    with Progress(
        TextColumn("[bold]selftest[/] GYRO_SAMPLE -> DRIVE_CMD"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
        disable=json_out,
    ) as bar:
        task = bar.add_task("frames", total=ticks)
        report = main_sync(
            ticks=ticks,
            seed=seed,
            garbage_rate=garbage_rate,
            flip_rate=flip_rate,
            progress=lambda n: bar.update(task, completed=n),
        )
    if json_out:
        console.print_json(json.dumps(dataclasses.asdict(report) | {"passed": report.passed}))
    else:
        _print_selftest(report)
    if not report.passed:
        raise typer.Exit(1)


def _print_selftest(report) -> None:  # type: ignore[no-untyped-def]
    b, c = report.board, report.counters
    t = Table(title="Protocol self-test: bench <-> emulated servo board on a pty")
    t.add_column("what")
    t.add_column("value", justify="right")
    t.add_column("unit / note")
    if report.ident:
        i = report.ident
        t.add_row("board", f"{i['board']} {i['firmware_version']}", f"fingerprint {i['catalogue_fingerprint']}")
    if b:
        t.add_row("GYRO_SAMPLE sent", str(b["ticks_sent"]), "1 kHz, board clock")
        t.add_row("  bit-flipped", str(len(b["corrupted_ticks"])), "injected")
        t.add_row("  garbage bursts", str(b["garbage_bursts"]), f"{b['garbage_bytes']} bytes injected")
        t.add_row("received by the bench", str(report.frames_received), "")
        t.add_row("uncorrupted lost", str(len(report.lost_untouched)), "must be 0")
        t.add_row("corrupted delivered", str(len(report.corrupted_delivered)), "must be 0")
        t.add_row("CRC errors / bad lengths", f"{c['crc_errors']} / {c['bad_lengths']}", "")
        t.add_row("resyncs / bytes discarded", f"{c['resyncs']} / {c['bytes_discarded']}", "")
        lat = b["latency_us"]
        if lat:
            t.add_row("sample k -> command k", f"{lat['p50']} / {lat['p99']} / {lat['max']}", "us p50/p99/max")
        t.add_row("late (>1 ms) / missing", f"{b['late_commands']} / {b['missing_commands']}", "missing = bit-flipped")
        r = report.bench_reaction_us
        if r:
            t.add_row("bench decode -> write", f"{r['p50']} / {r['p99']}", "us p50 / p99")
        pl = b["pacing_late_us"]
        if pl:
            t.add_row("board pacing lateness", f"{pl['p50']} / {pl['p99']}", "us p50 / p99")
    t.add_row("wall time", f"{report.wall_s:.1f}", "s")
    console.print(t)
    if report.passed:
        console.print("[bold green]PASS[/]: every uncorrupted frame arrived once, in order, and was answered.")
    else:
        for failure in report.failures:
            err_console.print(f"[bold red]FAIL[/]: {failure}", highlight=False)


def _load_session(path: Path):  # type: ignore[no-untyped-def]
    from hil.config import ConfigError, load_session

    try:
        return load_session(path)
    except ConfigError as exc:
        raise fail(str(exc)) from None


def run_session(config, out: Path | None, loopback: bool, clock: str | None, json_out: bool) -> int:  # type: ignore[no-untyped-def]
    """Run one session (optionally against a freshly started emulator); print the summary; return the exit code."""
    return _run_session(config, out, loopback, clock, json_out).exit_code


def _run_session(config, out: Path | None, loopback: bool, clock: str | None, json_out: bool):  # type: ignore[no-untyped-def]
    """Run one session, print its summary, return its SessionResult."""
    import asyncio

    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from hil.config import PortConfig, require_regular_file
    from hil.loopback import EmulatorProcess
    from hil.session import Session
    from hil.transport import LinkError

    out_dir = out or config.logging.dir
    check_out_dir(out_dir, "--out" if out else "logging.dir")
    emulator = None
    watchdog_ms = None
    if clock == "sim" and not loopback:
        raise fail("--clock sim: runs the emulated lab in this process; add --loopback")
    if loopback:
        clock = clock or config.emulator.clock
        try:  # the emulator validates it; a missing one is refused here, before anything starts
            require_regular_file(config.emulator.config)
        except ValueError as exc:
            raise fail(f"emulator.config: {exc}") from None
        if clock == "sim":
            return _run_sim(config, out_dir, json_out)
        emulator = EmulatorProcess(config.emulator.config, clock=clock, seed=config.seed,
                                   extra_args=config.emulator.process_args())
        try:
            ports = {name: PortConfig(port=path) for name, path in emulator.start().items() if name != "control"}
        except LinkError as exc:
            raise fail(str(exc)) from None
        if clock == "lockstep":  # the emulator waits for us, and we may wait for a descheduled emulator
            watchdog_ms = max(config.safety.watchdog_ms, 1000.0)
    elif config.ports is None:
        raise fail("ports: not set in the session file; give the lab's serial ports, or pass --loopback")
    elif config.safety.emulator_stall_grace_ms:
        raise fail("safety.emulator_stall_grace_ms: only for emulated boards (--loopback); real boards are never "
                   "late, so remove it from a lab session")
    else:
        ports = {name: getattr(config.ports, name) for name in ("servo", "driver", "image", "hexapod")}
    total = round(config.duration_s * 1000)
    with Progress(TextColumn(f"[bold]{config.name}[/] {config.controller.name}"), BarColumn(),
                  TextColumn("{task.fields[sim]:.1f} / {task.fields[total_s]:.1f} s"), TimeRemainingColumn(),
                  console=err_console, transient=True, disable=json_out) as bar:
        task = bar.add_task("run", total=total, sim=0.0, total_s=config.duration_s)
        session = Session(config, ports, out_dir, watchdog_ms=watchdog_ms,
                          progress=lambda n, _t: bar.update(task, completed=n, sim=n / 1000),
                          log_attrs={"loopback": bool(loopback), "clock": clock or "hardware"},
                          lockstep=clock == "lockstep", emulated=bool(loopback))
        try:
            result = asyncio.run(session.run())
        finally:
            if emulator is not None:
                emulator.stop()
    _print_result(result, json_out)
    return result


def _run_sim(config, out_dir: Path, json_out: bool):  # type: ignore[no-untyped-def]
    """``--loopback --clock sim``: the emulated lab in this process (hil.sim); print the summary."""
    import asyncio

    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from firmware_stub.config import ConfigError as EmulatorConfigError
    from hil.sim import run_sim_session

    total = round(config.duration_s * 1000)
    with Progress(TextColumn(f"[bold]{config.name}[/] {config.controller.name} (sim)"), BarColumn(),
                  TextColumn("{task.fields[sim]:.1f} / {task.fields[total_s]:.1f} s"), TimeRemainingColumn(),
                  console=err_console, transient=True, disable=json_out) as bar:
        task = bar.add_task("run", total=total, sim=0.0, total_s=config.duration_s)
        try:
            result, _ = asyncio.run(run_sim_session(
                config, out_dir, progress=lambda n, _t: bar.update(task, completed=n, sim=n / 1000)))
        except EmulatorConfigError as exc:
            raise fail(str(exc)) from None
    _print_result(result, json_out)
    return result


def _print_result(result, json_out: bool) -> None:  # type: ignore[no-untyped-def]
    import json

    from hil.report import summarize_log

    summary = summarize_log(result.log_path) if result.log_path and result.log_path.exists() else {}
    if json_out:
        console.print_json(json.dumps({"status": result.status, "exit_code": result.exit_code,
                                       "message": result.message, **summary}, default=str))
        return
    if summary:
        _print_summary(summary)
    colour = {"completed": "green", "interrupted": "yellow"}.get(result.status, "red")
    line = f"[bold {colour}]{result.status}[/]"
    if result.message:
        line += f": {result.message}"
    if result.log_path:
        line += f"   log: {result.log_path}"
    console.print(line, highlight=False)


def _fmt(x: float, digits: int = 3) -> str:
    return "-" if math.isnan(x) else f"{x:.{digits}f}"


def _print_summary(s: dict) -> None:  # type: ignore[type-arg]
    t = Table(title=f"{s.get('session', '')}  ({s.get('controller', '')}, {s['duration_s']:.1f} s, "
                    f"first {s['settle_s']:g} s left out)")
    t.add_column("metric")
    t.add_column("value", justify="right")
    t.add_column("unit")
    for axis in ("el", "az"):
        e = s[f"rate_error_{axis}_dps"]
        t.add_row(f"rate error {axis}: range +- / std", f"{_fmt(e['range_pm'])} / {_fmt(e['std'])}", "deg/s")
        t.add_row(f"drive ripple {axis} (std)", _fmt(s[f"drive_ripple_{axis}_counts"], 0), "counts")
    if "miss_x_px" in s:
        for axis in ("x", "y"):
            m = s[f"miss_{axis}_px"]
            t.add_row(f"miss distance {axis}: range +- / std", f"{_fmt(m['range_pm'], 2)} / {_fmt(m['std'], 2)}", "px")
        t.add_row("frames tracked", f"{s['frames_valid']} / {s['frames']}", "")
    lat, board = s["latency_us"], s["board_latency_us"]
    t.add_row("bench latency p50 / p99", f"{_fmt(lat['p50'], 0)} / {_fmt(lat['p99'], 0)}",
              "us, sample in -> command out")
    t.add_row("board-measured p50 / p99", f"{_fmt(board['p50'], 0)} / {_fmt(board['p99'], 0)}",
              "us, GYRO k written -> DRIVE_CMD k in")
    t.add_row("cycles / late / missed", f"{s['cycles']} / {s['late_cycles']} / {s['missed_cycles']}", "late: > 1 ms")
    t.add_row("link errors", " ".join(f"{k} {v}" for k, v in s["link_errors"].items()),
              "CRC + bad + refused + lost + reordered frames")
    t.add_row("faults", str(s["faults"]), "events")
    if s.get("host_stalls"):
        emulator = s.get("host_stalls_emulator", 0)
        t.add_row("host stalls: count / longest silence", f"{s['host_stalls']} / {_fmt(s['host_stall_max_ms'], 1)}",
                  f"ms; this host ran the bench late ({s['host_stalls'] - emulator}), or held up the emulator or its "
                  f"bytes ({emulator}): not board faults")
    console.print(t)
    if s.get("incomplete"):
        console.print(f"[bold yellow]incomplete:[/] {s['incomplete']}", highlight=False)
    reasons = s.get("fault_reasons", [])
    if reasons:
        note = (f"{len(reasons)} fault{'s' if len(reasons) > 1 else ''}, the first: {reasons[0]}. The loop was "
                "disarmed while it recovered; the figures above include those windows.")
        if any(r.startswith("watchdog") for r in reasons):
            note += (" A watchdog trip is a gap in the servo board's samples; against the emulator on a busy or "
                     "virtual machine, the emulator not being scheduled (docs/performance.md).")
        console.print(f"[yellow]{note}[/]", highlight=False)


@app.command()
def run(
    session: Annotated[Path, typer.Argument(help="Session YAML (see profiles/sessions/).")],
    loopback: Annotated[bool, typer.Option("--loopback", help="Run against the emulator (started here).")] = False,
    out: Annotated[Path | None, typer.Option(help="Directory for the log (default: the session's logging.dir)")] = None,
    clock: Annotated[str | None, typer.Option(
        help="Emulator clock with --loopback: realtime (paced 1 kHz over ptys) | lockstep (full protocol over "
             "ptys, byte-reproducible) | sim (boards and plant in this process; logs identical to lockstep).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON.")] = False,
) -> None:
    """Run a bench session: connect, arm, swing, stabilize and track, log; print the summary."""
    if clock not in (None, "realtime", "lockstep", "sim"):
        raise fail(f"--clock: {clock!r} is not realtime, lockstep or sim")
    raise typer.Exit(run_session(_load_session(session), out, loopback, clock, json_out))


MAX_EL_TRAVEL_DEG = 60.0  # hil ident: keep the elevation axis away from the az-el gimbal's 90 deg singularity


@app.command()
def ident(  # noqa: PLR0917 (typer maps parameters to options)
    session: Annotated[Path, typer.Argument(help="Session YAML: ports, controller (see profiles/sessions/).")],
    loopback: Annotated[bool, typer.Option("--loopback", help="Identify the emulator (started here).")] = False,
    out: Annotated[Path, typer.Option(help="Directory for the log, bode-AXIS.png and ident.json.")] = Path(
        "runs/ident"),
    axis: Annotated[str, typer.Option(help="el | az")] = "el",
    f_start_hz: Annotated[float, typer.Option(min=0.01, help="Sweep start.")] = 0.5,
    f_stop_hz: Annotated[float, typer.Option(max=450, help="Sweep stop (below the 500 Hz Nyquist).")] = 300.0,
    sweep_s: Annotated[float, typer.Option(min=1, help="Length of the sweep.")] = 20.0,
    amplitude_dps: Annotated[float, typer.Option(min=0, help="Sweep amplitude on the rate command.")] = 2.0,
    offset_dps: Annotated[float, typer.Option(
        help="Constant rate under the sweep, above its amplitude, so Coulomb friction stays on one side "
        "(docs/ident.md); the axis turns offset x (sweep + 1 s) deg.")] = 2.5,
    clock: Annotated[str | None, typer.Option(
        help="Emulator clock with --loopback: realtime | lockstep | sim (default: the session's).")] = None,
) -> None:
    """Frequency-sweep identification (seed 000 Figs. 8-9): a swept sine on the rate command of the closed rate
    loop, the plant's frequency response from the log (indirect closed-loop method), a Bode plot, and the fit of
    k_m (deg/s^2 per count), the gyro's bandwidth and the delay."""
    import json

    from pydantic import ValidationError

    from hil.config import SessionConfig, one_line
    from hil.control.registry import K_M_DEFAULT
    from hil.ident import SweptSine, bode_plot, identify_log
    from hil.log import read_log

    if axis not in ("el", "az"):
        raise fail(f"--axis: {axis!r} is not el or az")
    if clock not in (None, "realtime", "lockstep", "sim"):
        raise fail(f"--clock: {clock!r} is not realtime, lockstep or sim")
    for option, value in (("--f-start-hz", f_start_hz), ("--f-stop-hz", f_stop_hz), ("--sweep-s", sweep_s),
                          ("--amplitude-dps", amplitude_dps), ("--offset-dps", offset_dps)):
        finite(option, value)
    check_out_dir(out, "--out")
    base = _load_session(session)
    try:
        sweep = SweptSine(f_start_hz=f_start_hz, f_stop_hz=f_stop_hz, duration_s=sweep_s,
                          amplitude_dps=amplitude_dps, axis=axis, offset_dps=offset_dps)  # type: ignore[arg-type]
        data = base.model_dump(mode="json", exclude_none=True)
        data.update(name=f"{base.name}-ident-{axis}", duration_s=sweep.total_s + 0.5, excitation=sweep.model_dump(),
                    tracking={**data.get("tracking", {}), "enabled": False}, profile={"segments": []},
                    mqtt=base.mqtt)  # the object itself: its dump hides the password
        config = SessionConfig.model_validate(data)
    except ValidationError as exc:
        raise fail(one_line("ident", exc)) from None
    travel_deg = abs(offset_dps) * sweep.total_s
    if axis == "el" and travel_deg > MAX_EL_TRAVEL_DEG:
        raise fail(f"--offset-dps: the elevation axis would turn {travel_deg:.0f} deg during the sweep (at most "
                   f"{MAX_EL_TRAVEL_DEG:g}: near 90 deg the cross-elevation gyro loses the azimuth axis); lower "
                   "--offset-dps or --sweep-s, or identify --axis az")
    result = _run_session(config, out, loopback, clock, False)
    if result.status != "completed" or result.log_path is None:
        raise typer.Exit(result.exit_code or 1)
    try:
        frf, fit = identify_log(read_log(result.log_path), sweep)
    except ValueError as exc:
        raise fail(f"{result.log_path}: cannot identify: {exc}", code=1) from None
    png = bode_plot(frf, fit, out / f"bode-{axis}.png",
                    title=f"{config.name}: k_m = {fit.k_m_dps2_per_count:.5f} deg/s^2 per count")
    error_pct = 100.0 * (fit.k_m_dps2_per_count - K_M_DEFAULT) / K_M_DEFAULT
    report = {"log": str(result.log_path), "axis": axis, "sweep": sweep.model_dump(),
              "k_m_dps2_per_count": fit.k_m_dps2_per_count, "k_m_vs_default_pct": error_pct,
              "gyro_bandwidth_hz": fit.gyro_bandwidth_hz, "delay_ms": fit.delay_ms,
              "rms_error_db": fit.rms_error_db, "f_range_hz": list(fit.f_range_hz), "bins": fit.n_bins}
    (out / f"ident-{axis}.json").write_text(json.dumps(report, indent=2))
    console.print(f"[bold]{fit.describe()}[/]", highlight=False)
    console.print(f"k_m {fit.k_m_dps2_per_count:.5f} deg/s^2 per count: {error_pct:+.1f} % vs the controllers' "
                  f"default {K_M_DEFAULT} (set b0_dps2_per_count to the fitted value if it differs)", highlight=False)
    console.print(f"bode: {png}\nident: {out / f'ident-{axis}.json'}", highlight=False)


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Directory for the log.")] = Path("runs"),
) -> None:
    """The README's demo: a 10 s session, 1 deg / 1 Hz swing, ESO+KF, against the emulator (no setup needed)."""
    from hil.config import PROFILES

    config = _load_session(PROFILES / "sessions" / "demo.yaml")
    raise typer.Exit(run_session(config, out, True, None, False))


@app.command()
def report(
    log: Annotated[Path, typer.Argument(help="A session log (.h5), or a campaign directory.")],
    json_out: Annotated[bool, typer.Option("--json", help="Print the metrics as JSON.")] = False,
    settle_s: Annotated[float, typer.Option(min=0, help="Leave out the first seconds.")] = 1.0,
) -> None:
    """Metrics of a session log (rate error, miss distance, drive ripple, latency, link errors), or a
    campaign directory's report: Markdown and a self-contained HTML page with the paper's tables and plots."""
    import json

    from hil.log import LogError
    from hil.log.reader import NotASessionLog
    from hil.report import summarize_log

    finite("--settle-s", settle_s)
    if log.is_dir():
        _campaign_report(log)
        return
    check_input_file(log)
    try:
        s = summarize_log(log, settle_s)
    except NotASessionLog as exc:
        raise fail(str(exc)) from None
    except (LogError, OSError, KeyError) as exc:
        raise fail(f"{log}: not a readable session log ({exc}); if the session crashed: hil recover {log}") from None
    if json_out:
        console.print_json(json.dumps(s, default=str))
    else:
        _print_summary(s)


def _campaign_report(campaign_dir: Path) -> None:
    from hil.campaign import CampaignError
    from hil.campaign.report import write_report

    try:
        files = write_report(campaign_dir)
    except CampaignError as exc:
        raise fail(str(exc)) from None
    console.print(f"report: {files.markdown}\n        {files.html}  ({len(files.pngs)} plots)", highlight=False)


@app.command()
def campaign(  # noqa: PLR0917 (typer maps parameters to options)
    file: Annotated[Path, typer.Argument(help="Campaign YAML (see profiles/campaigns/).")],
    out: Annotated[Path | None, typer.Option(help="Campaign directory (default: runs/campaigns/NAME).")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Finish a campaign in --out, skipping done cells.")] = False,
    jobs: Annotated[int, typer.Option(min=1, max=64, help="Cells run at once (loopback only).")] = 1,
    hardware: Annotated[bool, typer.Option("--hardware", help="Run on the lab's ports, one cell at a time.")] = False,
    clock: Annotated[str, typer.Option(help="Loopback cells: sim (in-process, default) | lockstep (over ptys); "
                                            "the same logs either way.")] = "sim",
    report_too: Annotated[bool, typer.Option("--report/--no-report", help="Write the report at the end.")] = True,
) -> None:
    """Run a swing campaign: profiles x controllers x seeds, each cell a session with its own log; then the
    summary table, the acceptance verdict, and the report. Exit 1 if a threshold or an acceptance rule fails."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from hil.campaign import CampaignError, load_campaign, run_campaign
    from hil.campaign.runner import cell_sessions

    try:
        config = load_campaign(file)
    except CampaignError as exc:
        raise fail(str(exc)) from None
    out_dir = out or Path("runs") / "campaigns" / config.name
    check_out_dir(out_dir, "--out")
    if clock not in ("sim", "lockstep"):
        raise fail(f"--clock: {clock!r} is not sim or lockstep")
    try:  # every cell, before anything is written
        sessions = cell_sessions(config, out_dir, hardware, clock)
    except CampaignError as exc:
        raise fail(f"{file}: {exc}") from None
    n_cells = len(config.cells())
    with Progress(TextColumn(f"[bold]{config.name}[/]"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[last]}"), TimeElapsedColumn(), console=err_console,
                  transient=True) as bar:
        task = bar.add_task("cells", total=n_cells, last="")

        def on_cell(cell) -> None:  # type: ignore[no-untyped-def]
            mark = "ok" if cell.passed else "FAIL"
            bar.update(task, advance=1, last=f"{cell.cell_id} {mark}")

        try:
            result = run_campaign(config, out_dir, jobs=jobs, resume=resume, hardware=hardware, on_cell=on_cell,
                                  sessions=sessions)
        except CampaignError as exc:
            raise fail(str(exc)) from None
    _print_campaign(result)
    if report_too:
        _campaign_report(out_dir)
    console.print(f"campaign: {out_dir}", highlight=False)
    raise typer.Exit(0 if result.passed else 1)


def _print_campaign(result) -> None:  # type: ignore[no-untyped-def]
    from hil.campaign import METRICS

    cfg = result.config
    for profile in cfg.profiles:
        t = Table(title=f"{cfg.title}: {profile.label}", title_justify="left")
        t.add_column("controller")
        for m in cfg.metrics:
            t.add_column(f"{METRICS[m].label} ({METRICS[m].unit})", justify="right")
        t.add_column("cells ok", justify="right")
        for c in cfg.controllers:
            row = [c.label]
            for m in cfg.metrics:
                v = result.values(profile.label, c.label, m)
                row.append("-" if not v else f"{sum(v) / len(v):.3g}" + (f" [{min(v):.3g}..{max(v):.3g}]"
                                                                          if len(v) > 1 else ""))
            cells = [x for x in result.cells if x.profile == profile.label and x.controller == c.label]
            row.append(f"{sum(x.passed for x in cells)}/{len(cfg.seeds)}")
            t.add_row(*row)
        console.print(t)
    for cell in result.cells:
        for why in cell.failures:
            console.print(f"[red]FAIL[/] {cell.cell_id}: {why}", highlight=False)
    for rule in result.acceptance:
        colour = "green" if rule.passed else "red"
        console.print(f"[bold {colour}]{'PASS' if rule.passed else 'FAIL'}[/] {rule.rule}", highlight=False)
        for line in rule.details:
            console.print(f"    {line}", highlight=False)
    state = "complete" if result.complete else "PARTIAL"
    console.print(f"{len(result.cells)} cells, {state}, {result.wall_s:.1f} s wall with {result.jobs} job(s): "
                  f"[bold {'green' if result.passed else 'red'}]{'PASS' if result.passed else 'FAIL'}[/]",
                  highlight=False)


@app.command()
def export(
    log: Annotated[Path, typer.Argument(help="A session log (.h5).")],
    fmt: Annotated[str, typer.Option("--format", help="parquet | csv")] = "parquet",
    out: Annotated[Path | None, typer.Option(help="Output directory (default: beside the log).")] = None,
) -> None:
    """Export every group of a log to Parquet or CSV files (units kept)."""
    from hil.log import LogError, export_log

    if fmt not in ("parquet", "csv"):
        raise fail(f"--format: {fmt!r} is not parquet or csv")
    check_input_file(log)
    check_out_dir(out if out is not None else log.parent, "--out" if out is not None else "the log's directory")
    try:
        paths = export_log(log, fmt, out)  # type: ignore[arg-type]
    except LogError as exc:
        raise fail(str(exc)) from None
    for p in paths:
        console.print(str(p))


@app.command()
def recover(
    log: Annotated[Path, typer.Argument(help="A log left by a crashed session.")],
) -> None:
    """Make a log left by a crash (SIGKILL, power loss) open normally; the original is kept beside it."""
    from hil.log import LogError, recover_log

    check_input_file(log)
    try:
        result = recover_log(log)
    except LogError as exc:
        raise fail(str(exc)) from None
    console.print(str(result))


@app.command()
def watch(
    broker: Annotated[str, typer.Option(help="mqtt://host:port of the broker the bench publishes to.")] = (
        "mqtt://127.0.0.1:1883"),
    bench: Annotated[str, typer.Option(help="The bench id (mqtt.bench_id in the session).")] = "bench",
    seconds: Annotated[float | None, typer.Option(help="Stop after this long (default: until Ctrl-C).")] = None,
) -> None:
    """Live telemetry from the broker: latest value of every channel, session state, events."""
    import asyncio

    from pydantic import ValidationError

    from hil.config import one_line
    from hil.telemetry import MqttConfig
    from hil.telemetry import watch as watch_telemetry

    finite("--seconds", seconds)
    if seconds is not None and seconds <= 0:
        raise fail(f"--seconds: {seconds!r} is not above 0")
    try:
        config = MqttConfig.from_url(broker, bench_id=bench)
    except ValidationError as exc:
        raise fail(one_line("--broker", exc)) from None
    except ValueError as exc:
        raise fail(f"--broker: {exc}") from None
    raise typer.Exit(asyncio.run(watch_telemetry(config, seconds=seconds, console=console)))


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def emulate(  # noqa: PLR0917 (typer maps parameters to options)
    ctx: typer.Context,
    config: Annotated[Path | None, typer.Option(help="Emulator YAML (default profiles/emulator/default.yaml).")] = None,
    clock: Annotated[str | None, typer.Option(help="realtime | lockstep (overrides the config).")] = None,
    seed: Annotated[int | None, typer.Option(help="Seed of plant noise and link faults (overrides config).")] = None,
    ports_file: Annotated[Path | None, typer.Option(help="Also write the ports map (JSON) to this file.")] = None,
    fault_log: Annotated[Path | None, typer.Option(help="Write every injected fault and board event (JSONL).")] = None,
    seconds: Annotated[float | None, typer.Option(help="Stop after this much simulated time.")] = None,
) -> None:
    """Run the emulated lab (gimbal on a hexapod, four boards on ptys) until Ctrl-C: `python -m firmware_stub`."""
    import os

    args = [sys.executable, "-m", "firmware_stub"]
    for flag, value in (("--config", config), ("--clock", clock), ("--seed", seed), ("--ports-file", ports_file),
                        ("--fault-log", fault_log), ("--seconds", seconds)):
        if value is not None:
            args += [flag, str(value)]
    sys.stdout.flush()
    os.execv(sys.executable, args + list(ctx.args))  # the emulator gets our pid, so signals reach it directly


@protocol_app.command("docs")
def protocol_docs(
    write: Annotated[bool, typer.Option("--write", help="Rewrite the generated blocks of the file.")] = False,
    path: Annotated[Path | None, typer.Option(help="The protocol document (default: docs/protocol.md).")] = None,
) -> None:
    """Check (or with --write, regenerate) the catalogue tables in docs/protocol.md."""
    from hil.config import read_text_file
    from hil.protocol import docgen

    path = path or docgen.DOC_PATH
    try:
        old = read_text_file(path, 16 << 20)
    except ValueError as exc:
        raise fail(str(exc)) from None
    try:
        new = docgen.apply(old)
    except ValueError as exc:
        raise fail(str(exc)) from None
    if new == old:
        console.print(f"{path}: up to date with the catalogue")
        return
    if write:
        path.write_text(new)
        console.print(f"{path}: regenerated")
        return
    raise fail(f"{path} differs from the catalogue; run `hil protocol docs --write`", code=1)


@protocol_app.command("decode")
def protocol_decode(
    capture: Annotated[str, typer.Argument(help="A raw binary capture file, '-' for stdin, or hex text with --hex.")],
    hex_input: Annotated[bool, typer.Option("--hex", help="The input is hex text (spaces allowed).")] = False,
    limit: Annotated[int, typer.Option(min=0, help="Print at most this many frames.")] = 50,
    link: Annotated[
        str | None, typer.Option(help="Check addressing as on this board's link: servo, driver, image or hexapod.")
    ] = None,
    side: Annotated[
        str, typer.Option(help="With --link, the receiving end: host (the capture holds what the board sent) or board.")
    ] = "host",
) -> None:
    """Decode a capture of one link: frames, then the link counters. Streams: memory stays bounded."""
    import re
    from collections.abc import Iterator

    from hil.protocol import Decoder, Frame
    from hil.transport import board_of

    chunk_bytes = 1 << 16
    if link is None:
        decoder = Decoder()
    else:
        board = board_of(link)
        if board is None:
            raise fail(f"--link: {link!r} is not servo, driver, image or hexapod")
        if side not in ("host", "board"):
            raise fail(f"--side: {side!r} is not host or board")
        decoder = Decoder.for_link(board, "host" if side == "host" else "board")
    if capture == "-":
        source, where = sys.stdin.buffer, "stdin"
    elif hex_input:
        source, where = None, "the --hex text"
    else:
        p = Path(capture)
        if not p.is_file():
            raise fail(f"{capture}: no such file (pass --hex to decode hex text given on the command line)")
        try:
            source, where = p.open("rb"), capture
        except OSError as exc:
            raise fail(f"{capture}: cannot read: {exc.strerror}") from None

    def blocks() -> Iterator[bytes]:
        if source is None:
            yield capture.encode()
            return
        while block := source.read(chunk_bytes):
            yield block

    def hex_blocks() -> Iterator[bytes]:
        """Hex text to bytes, block by block; spaces, newlines and ':' between digits are ignored."""
        carry, offset = b"", 0
        for text in blocks():
            bad = re.search(rb"[^0-9a-fA-F \t\r\n:]", text)
            if bad:
                raise fail(f"{where}: not hex text: {bad[0].decode('latin-1')!r} at byte {offset + bad.start()}")
            offset += len(text)
            digits = carry + text.translate(None, b" \t\r\n:")
            cut = len(digits) & ~1
            carry = digits[cut:]
            yield bytes.fromhex(digits[:cut].decode("ascii"))
        if carry:
            raise fail(f"{where}: not hex text: an odd number of hex digits")

    shown: list[Frame] = []
    n_frames = 0
    try:
        for block in hex_blocks() if hex_input else blocks():
            frames = decoder.feed(block)
            n_frames += len(frames)
            if len(shown) < limit:
                shown += frames[: limit - len(shown)]
    except OSError as exc:
        raise fail(f"{where}: cannot read: {exc.strerror or exc}") from None
    finally:
        if source is not None and source is not sys.stdin.buffer:
            source.close()
    table = Table("#", "src", "dst", "seq", "message", title=f"{n_frames} frames")
    for i, fr in enumerate(shown):
        table.add_row(str(i), f"{fr.src:#04x}", f"{fr.dst:#04x}", str(fr.seq), repr(fr.message))
    console.print(table)
    if n_frames > limit:
        console.print(f"... {n_frames - limit} more (raise --limit)")
    counters = Table("counter", "value", title="link counters")
    for name, value in decoder.counters.as_dict().items():
        counters.add_row(name, str(value))
    counters.add_row("pending (incomplete frame)", str(decoder.pending))
    console.print(counters)


def main(argv: list[str] | None = None) -> int:
    """Console-script entry: bad usage is one line on stderr and exit code 2, never a traceback."""
    try:
        code = app(args=argv, prog_name="hil", standalone_mode=False)
    except typer.Abort:
        err_console.print("interrupted")
        return 130
    except Exception as exc:
        # click's UsageError contract (typer vendors click, so match the contract, not the class)
        if getattr(exc, "exit_code", None) != 2 or not hasattr(exc, "format_message"):
            raise
        if not exc.format_message():  # no arguments at all: the help was shown
            return 0
        ctx = getattr(exc, "ctx", None)
        where = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
        fail(f"{exc.format_message()}{where}")
        return 2
    return code if isinstance(code, int) else 0
