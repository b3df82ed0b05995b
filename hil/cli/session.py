"""`hil run`, `hil demo`, `hil ident`: bench sessions, through :mod:`hil.api`."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer
from rich.table import Table

from hil.cli._bench import bench_for, run_on_bench
from hil.cli._common import app, check_out_dir, console, err_console, fail, finite, no_progress, note, print_json

if TYPE_CHECKING:
    from hil.api import RunResult, SelftestReport
    from hil.config import SessionConfig, SweptSine

ClockOption = Literal["realtime", "lockstep", "sim"]


def load_session_or_exit(path: Path) -> SessionConfig:
    from hil.config import ConfigError, load_session  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        return load_session(path)
    except ConfigError as exc:
        raise fail(str(exc)) from None


def run_and_print(config: SessionConfig, out: Path | None, loopback: bool, clock: ClockOption | None, json_out: bool, *,
                  capture: Path | None = None, show: bool = True) -> RunResult:
    """Run one session through hil.api with a progress bar, print its summary (``show``), return the api's
    RunResult."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        config, clock_name, out_dir = api.prepare_run(config, loopback=loopback, clock=clock, out=out)
    except ConfigError as exc:
        raise fail(str(exc)) from None
    total = round(config.duration_s * 1000)
    label = f"[bold]{config.name}[/] {config.controller.name}" + (" (sim)" if clock_name == "sim" else "")
    with Progress(TextColumn(label), BarColumn(), TextColumn("{task.fields[sim]:.1f} / {task.fields[total_s]:.1f} s"),
                  TimeRemainingColumn(), console=err_console, transient=True, disable=no_progress(json_out)) as bar:
        task = bar.add_task("run", total=total, sim=0.0, total_s=config.duration_s)
        try:
            result = api.run(config, loopback=loopback, clock=clock_name if loopback else None,  # type: ignore[arg-type]
                             out=out_dir, capture=capture,
                             progress=lambda n, _t: bar.update(task, completed=n, sim=n / 1000))
        except (ConfigError, ValueError) as exc:
            raise fail(str(exc)) from None
    if show:
        print_result(result, json_out)
    return result


def print_result(result: RunResult, json_out: bool) -> None:
    summary = result.summary()
    if json_out:
        print_json(result.record(summary))
        return
    lost = result.log_loss()
    if lost:  # the log says only that no summary was written; the session knows why
        summary["incomplete"] = lost
    if summary:
        print_summary(summary)
    elif lost:
        console.print(f"[bold yellow]incomplete:[/] {lost}", highlight=False)
    colour = {"completed": "green", "interrupted": "yellow"}.get(result.status, "red")
    line = f"[bold {colour}]{result.status}[/]"
    if result.message:
        line += f": {result.message}"
    if result.log_path:
        line += f"   log: {result.log_path}"
    console.print(line, highlight=False)
    cap = result.capture
    if cap:
        trouble = f"; {cap['dropped']} records lost: {cap['error']}" if cap.get("dropped") or cap.get("error") else ""
        text = f"capture: {cap['path']} ({cap['records']} records, {cap['bytes']} bytes{trouble})"
        console.print(text, style="red" if trouble else None, markup=False, highlight=False)


def _fmt(x: float | None, digits: int = 3) -> str:
    return "-" if x is None or math.isnan(x) else f"{x:.{digits}f}"


def print_summary(s: dict[str, Any]) -> None:
    t = Table(title=f"{s.get('session', '')}  ({s.get('controller', '')}, {s['duration_s']:.1f} s, "
                    f"first {s['settle_s']:g} s of the run left out)")
    t.add_column("metric")
    t.add_column("value", justify="right")
    t.add_column("unit")
    if isinstance(pose := s.get("start_pose"), dict):
        t.add_row("start pose", f"{pose.get('outcome')} in {_fmt(pose.get('took_s'), 2)} s from az "
                  f"{_fmt(pose.get('from_az_deg'), 2)}, el {_fmt(pose.get('from_el_deg'), 2)}",
                  "s, deg; the run starts there")
    for axis in ("el", "az"):
        e = s[f"rate_error_{axis}_dps"]
        t.add_row(f"rate error {axis}: range +- / std", f"{_fmt(e['range_pm'])} / {_fmt(e['std'])}", "deg/s")
        t.add_row(f"drive ripple {axis} (std)", _fmt(s[f"drive_ripple_{axis}_counts"], 0), "counts")
        if (amps := s.get(f"motor_current_{axis}_a")) is not None:
            t.add_row(f"motor current {axis}: rms / peak", f"{_fmt(amps['rms'], 2)} / {_fmt(amps['peak'], 2)}",
                      "A, the driver's DRIVE_STATUS")
    if "miss_x_px" in s:
        for axis in ("x", "y"):
            m = s[f"miss_{axis}_px"]
            t.add_row(f"miss distance {axis}: range +- / std", f"{_fmt(m['range_pm'], 2)} / {_fmt(m['std'], 2)}", "px")
        t.add_row("frames tracked", f"{s['frames_valid']} / {s['frames']}", "")
    lat, board = s["latency_us"], s["board_latency_us"]
    t.add_row("bench latency p50 / p99", f"{_fmt(lat['p50'], 0)} / {_fmt(lat['p99'], 0)}",
              "us, sample in -> command out")
    if board.get("na_reason"):
        t.add_row("board-measured p50 / p99", "n/a", board["na_reason"])
    else:
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
    provenance = s.get("provenance") or {}
    if provenance:
        controller = provenance.get("controller") or {}
        params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in (controller.get("params") or {}).items())
        commit = provenance.get("git_commit")
        if commit:  # a full hash is in the log; twelve digits name it here
            commit = commit[:12] + ("-dirty" if commit.endswith("-dirty") else "")
        note(f"hil {provenance.get('hil_version', '?')}" + (f" ({commit})" if commit else "")
             + f", numpy {provenance.get('numpy', '?')}, h5py {provenance.get('h5py', '?')}"
             + (f", plant {provenance['plant'].get('path')} sha256 {provenance['plant'].get('sha256', '')[:12]}"
                if provenance.get("plant") else ""))
        if params:
            note(f"{controller.get('name', 'controller')}: {params}")
    if s.get("incomplete"):
        console.print(f"[bold yellow]incomplete:[/] {s['incomplete']}", highlight=False)
    gaps = s.get("swing_gaps") or []
    if gaps:
        spans = ", ".join(f"{g['from_s']:.2f}-{g['to_s']:.2f} s" if g.get("to_s") is not None else
                          f"from {g['from_s']:.2f} s to the end" for g in gaps)
        console.print(f"[yellow]the table did not swing for {s['swing_gap_s']:.2f} s ({spans}: {gaps[0]['reason']}); "
                      "those spans are left out of the figures above[/]", highlight=False)
    reasons = s.get("fault_reasons", [])
    if reasons:
        text = (f"{len(reasons)} fault{'s' if len(reasons) > 1 else ''}, the first: {reasons[0]}. The loop was "
                "disarmed while it recovered; the figures above include those windows.")
        if any(r.startswith("watchdog") for r in reasons):
            text += (" A watchdog trip is a gap in the servo board's samples; against the emulator on a busy or "
                     "virtual machine, the emulator not being scheduled (docs/performance.md).")
        console.print(f"[yellow]{text}[/]", highlight=False)


@app.command()
def run(  # noqa: PLR0917 (typer maps parameters to options)
    session: Annotated[Path, typer.Argument(help="Session YAML (see profiles/sessions/).")],
    loopback: Annotated[bool, typer.Option("--loopback", help="Run against the emulator (started here).")] = False,
    out: Annotated[Path | None, typer.Option(help="Directory for the log (default: the session's logging.dir)")] = None,
    clock: Annotated[ClockOption | None, typer.Option(
        help="Emulator clock with --loopback: realtime (paced 1 kHz over ptys), lockstep (full protocol over "
             "ptys, byte-reproducible), sim (boards and plant in this process; logs identical to lockstep).")] = None,
    capture: Annotated[Path | None, typer.Option(
        help="Record every link's raw bytes with timestamps in this directory (docs/capture.md).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON.")] = False,
    bench: Annotated[str | None, typer.Option(
        help="Run it on a `hil serve` service at this URL (default $HIL_BENCH unless --loopback): it waits its "
             "turn in the queue; the log comes back into --out.")] = None,
) -> None:
    """Run a bench session: connect, arm, swing, stabilize and track, log; print the summary."""
    url = bench_for(bench, loopback)
    if url is not None:
        if clock is not None or capture is not None:
            raise fail("--bench: the service runs on its own lab and clock; leave out --clock and --capture")
        if out is not None:
            check_out_dir(out, "--out")
        load_session_or_exit(session)
        result, _record = run_on_bench(url, session, out, json_out)
        print_result(result, json_out)
        raise typer.Exit(result.exit_code)
    if capture is not None:
        check_out_dir(capture, "--capture")
    result = run_and_print(load_session_or_exit(session), out, loopback, clock, json_out, capture=capture)
    raise typer.Exit(result.exit_code)


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Directory for the log.")] = Path("runs"),
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON.")] = False,
) -> None:
    """The README's demo: a 10 s session, 1 deg / 1 Hz swing, ESO+KF, against the emulator (no setup needed)."""
    from hil.config import PROFILES  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    config = load_session_or_exit(PROFILES / "sessions" / "demo.yaml")
    result = run_and_print(config, out, True, None, json_out)
    if not json_out:
        note("next, the same lab as a service, for a browser and other terminals (docs/service.md):\n"
             "  .venv/bin/hil serve --loopback        then open http://localhost:8765/\n"
             "  .venv/bin/hil queue start --bench http://localhost:8765     (every start leaves the queue stopped)\n"
             "  .venv/bin/hil run profiles/sessions/demo.yaml --bench http://localhost:8765")
    raise typer.Exit(result.exit_code)


@app.command()
def ident(  # noqa: PLR0917 (typer maps parameters to options)
    session: Annotated[Path, typer.Argument(help="Session YAML: ports, controller (see profiles/sessions/).")],
    loopback: Annotated[bool, typer.Option("--loopback", help="Identify the emulator (started here).")] = False,
    out: Annotated[Path, typer.Option(help="Directory for the log, bode-AXIS.png and ident.json.")] = Path(
        "runs/ident"),
    axis: Annotated[Literal["el", "az"], typer.Option(help="The gimbal axis to identify.")] = "el",
    f_start_hz: Annotated[float, typer.Option(min=0.01, help="Sweep start.")] = 1.0,
    f_stop_hz: Annotated[float, typer.Option(max=450, help="Sweep stop (below the 500 Hz Nyquist).")] = 450.0,
    sweep_s: Annotated[float, typer.Option(min=1, help="Length of the sweep.")] = 8.0,
    amplitude_dps: Annotated[float, typer.Option(
        min=0, help="Sweep amplitude on the rate command (where the levelling starts).")] = 1.5,
    offset_dps: Annotated[float, typer.Option(
        help="Constant rate under the sweep, above its amplitude, so Coulomb friction stays on one side "
        "(docs/ident.md); the axis turns offset x (sweep + 1 s) deg (where the levelling starts).")] = 3.0,
    level: Annotated[bool, typer.Option(
        "--level/--no-level", help="Level the sweep: up to 6 sweeps, the amplitude raised where the coherence "
        "fails and the drive has headroom, lowered where it saturates, the offset raised while the axis reverses "
        "(at most 60 deg of travel); each sweep turns the axis back (docs/ident.md, Levelling).")] = True,
    clock: Annotated[ClockOption | None, typer.Option(
        help="Emulator clock with --loopback (default: the session's).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the fit as JSON.")] = False,
    bench: Annotated[str | None, typer.Option(
        help="Identify on a `hil serve` service at this URL (default $HIL_BENCH unless --loopback).")] = None,
) -> None:
    """Frequency-sweep identification (seed 000 Figs. 8-9): a swept sine on the rate command of the closed rate
    loop, levelled by default (up to 6 sweeps: more amplitude where the coherence fails, less where the drive clips,
    the offset kept above the rate's swing), the plant's frequency response from the log (indirect closed-loop
    method), its coherent band, a Bode plot, and the fit on that band only of k_m (deg/s^2 per count), the gyro's
    bandwidth and the delay."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    base = load_session_or_exit(session)
    url = bench_for(bench, loopback)
    if url is not None:
        if clock is not None:
            raise fail("--bench: the service runs on its own lab and clock; leave out --clock")
        options = {"axis": axis, "f_start_hz": f_start_hz, "f_stop_hz": f_stop_hz, "sweep_s": sweep_s,
                   "amplitude_dps": amplitude_dps, "offset_dps": offset_dps, "level": level}
        result, record = run_on_bench(url, session, out, json_out, kind="ident", options=options)
        report = record["summary"].get("ident")
        if report and result.log_path is not None:
            report = {**report, "log": str(result.log_path), "log_on_service": report.get("log")}
        if json_out and report:
            print_json(report)
        else:
            print_result(result, json_out)
            if report:
                band = report.get("coherent_band_hz") or [math.nan, math.nan]
                lag = (f"gyro bandwidth {_fmt(report.get('gyro_bandwidth_hz'), 1)} Hz, delay "
                       f"{_fmt(report.get('delay_ms'), 2)} ms" if report.get("gyro_bandwidth_hz") is not None else
                       f"gyro bandwidth above {band[1]:.3g} Hz, loop delay {_fmt(report.get('loop_delay_ms'), 2)} ms")
                console.print(f"k_m {report['k_m_dps2_per_count']:.5f} deg/s^2 per count "
                              f"({report['k_m_vs_default_pct']:+.1f} % vs the controllers' default), {lag}; "
                              f"coherent {band[0]:.3g}-{band[1]:.3g} Hz (on the service; its Bode plot stays there)",
                              highlight=False)
        raise typer.Exit(result.exit_code if report or result.exit_code else 1)
    with Progress(TextColumn(f"[bold]{base.name}[/] swept sine on {axis}" + " {task.fields[sweep]}"), BarColumn(),
                  TextColumn("{task.fields[sim]:.1f} s"), TimeRemainingColumn(), console=err_console,
                  transient=True, disable=no_progress(json_out)) as bar:
        task = bar.add_task("ident", total=None, sim=0.0, sweep="")

        def on_pass(i: int, sweep: SweptSine) -> None:
            bar.update(task, completed=0, sweep=f"pass {i} (peak {sweep.amplitude_dps:.3g} deg/s, offset "
                       f"{sweep.offset_dps:+.3g} deg/s)")

        try:
            done = api.ident(base, axis=axis, loopback=loopback, clock=clock, out=out, f_start_hz=f_start_hz,
                             f_stop_hz=f_stop_hz, sweep_s=sweep_s, amplitude_dps=amplitude_dps,
                             offset_dps=offset_dps, level=level, on_pass=on_pass,
                             progress=lambda n, t: bar.update(task, completed=n, total=t, sim=n / 1000))
        except ConfigError as exc:
            raise fail(str(exc)) from None
        except ValueError as exc:  # the log could not be fitted
            raise fail(str(exc), code=1) from None
    result, fit = done.run, done.fit
    if fit is None:  # the session did not complete: say so, as `hil run` would
        print_result(result, json_out)
        raise typer.Exit(result.exit_code or 1)
    if json_out:
        print_json(done.report)
        return
    print_result(result, False)
    lo, hi = done.band_hz or fit.f_range_hz
    console.print(f"levelling: {done.report['levelling']}; coherent band {lo:.3g}-{hi:.3g} Hz (coherence >= 0.8), "
                  "the figures below from it only", highlight=False)
    if done.report.get("resonance_hz"):
        console.print(f"a resonance at {done.report['resonance_hz']:.0f} Hz over the rigid model (a structural mode?):"
                      f" the fit stops at half of it, {fit.f_range_hz[1]:.3g} Hz", highlight=False)
    console.print(f"[bold]{fit.describe()}[/]", highlight=False)
    console.print(f"k_m {fit.k_m_dps2_per_count:.5f} deg/s^2 per count: {done.report['k_m_vs_default_pct']:+.1f} % "
                  f"vs the controllers' default {api.K_M_DEFAULT} (set b0_dps2_per_count to the fitted value if it "
                  "differs)", highlight=False)
    console.print(f"bode: {done.bode_png}\nident: {done.json_path}", highlight=False)


@app.command()
def selftest(
    ticks: Annotated[int, typer.Option(min=100, max=3_600_000, help="GYRO_SAMPLEs to stream at 1 kHz.")] = 3000,
    seed: Annotated[int, typer.Option(help="Seed of the injected faults.")] = 1,
    garbage_rate: Annotated[float, typer.Option(min=0, max=1, help="Chance of a garbage burst per frame.")] = 0.01,
    flip_rate: Annotated[float, typer.Option(min=0, max=1, help="Chance of a flipped bit per frame.")] = 0.005,
    json_out: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False,
) -> None:
    """Protocol self-test: the bench against an emulated servo board on a pty, with injected faults."""

    finite("--garbage-rate", garbage_rate)
    finite("--flip-rate", flip_rate)

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    with Progress(TextColumn("[bold]selftest[/] GYRO_SAMPLE -> DRIVE_CMD"), BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), console=err_console, transient=True, disable=no_progress(json_out)) as bar:
        task = bar.add_task("frames", total=ticks)
        report = api.selftest(ticks=ticks, seed=seed, garbage_rate=garbage_rate, flip_rate=flip_rate,
                              progress=lambda n: bar.update(task, completed=n))
    if json_out:
        print_json(dataclasses.asdict(report) | {"passed": report.passed})
    else:
        _print_selftest(report)
    if not report.passed:
        raise typer.Exit(1)


def _print_selftest(report: SelftestReport) -> None:
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
