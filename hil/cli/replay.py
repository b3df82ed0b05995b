"""`hil replay`: a session log through another controller offline, or a capture back at a board (hil.replay)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer
from rich.table import Table

from hil.cli._common import app, check_out_dir, console, fail, finite, note, print_json

if TYPE_CHECKING:
    from collections.abc import Mapping

    from hil.api import PlaybackResult


@app.command()
def replay(  # noqa: PLR0917 (typer maps parameters to options)
    source: Annotated[Path, typer.Argument(
        help="A session log (.h5) to replay through a controller, or with --to-emulator a capture (.hilcap, or "
             "the directory holding one) to play back at the boards.")],
    controller: Annotated[str | None, typer.Option(
        help="Log: the controller to replay (a registry name; default: the logged one, or the YAML's).")] = None,
    params: Annotated[str | None, typer.Option(
        help="Log: its parameters, 'k=v,k=v' over the registry defaults, or a controller YAML (name and params). "
             "Default: the logged parameters when the controller is the logged one.")] = None,
    settle: Annotated[float, typer.Option(min=0.0, help="Log: seconds left out of the metrics at the start.")] = 1.0,
    to_emulator: Annotated[bool, typer.Option(
        "--to-emulator", help="Play a capture's host-side frames back at the boards (a fresh emulator unless "
                              "--ports-file or --port name them) with their timing.")] = False,
    ports_file: Annotated[Path | None, typer.Option(
        help="Capture: the boards' ports as JSON {link: path} (the emulator's --ports-file).")] = None,
    port: Annotated[list[str] | None, typer.Option(
        help="Capture: LINK=PATH, once per link (servo, driver, image, hexapod).")] = None,
    clock: Annotated[Literal["lockstep", "realtime"] | None, typer.Option(
        help="Capture, no ports given: the fresh emulator's clock (default: the captured emulator's).")] = None,
    seed: Annotated[int | None, typer.Option(
        min=0, help="Capture, no ports given: the fresh emulator's seed (default: the captured emulator's).")] = None,
    timing: Annotated[Literal["samples", "clock"], typer.Option(
        help="Capture: 'samples' times each write from the sample it followed in the capture; 'clock' from the "
             "first write. Either way the replay stops and disarms the boards when their stream stops.")] = "samples",
    out: Annotated[Path | None, typer.Option(
        help="Log: where the PNG and JSON go (default: beside the log). Capture: where the replay's own capture "
             "and JSON go (default: none written).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="The results as JSON on stdout.")] = False,
) -> None:
    """Replay a session log through an estimator/controller offline and compare it with the logged one; or, with
    --to-emulator, play a capture's frames back at a board or the emulator and count what came back."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    finite("--settle", settle)
    if out is not None:
        check_out_dir(out, "--out")
    if not source.exists():
        raise fail(f"{source}: no such file or directory")
    if to_emulator:
        if controller is not None or params is not None:
            raise fail("--controller/--params replay a log; --to-emulator plays a capture")
        _replay_capture(source, ports_file, port or [], clock=clock, seed=seed, timing=timing, out=out,
                        json_out=json_out)
        return
    if ports_file is not None or port or clock is not None or seed is not None:
        raise fail("--ports-file, --port, --clock and --seed go with --to-emulator (a capture)")
    if source.is_dir() or api.is_capture(source):
        raise fail(f"{source}: a capture; play it back with --to-emulator, or replay a session log (.h5)")
    _replay_log(source, controller, params, settle=settle, out=out, json_out=json_out)


# --- a log through a controller (hil.api.replay_log) ----------------------------------------------------------


def _replay_log(log: Path, controller: str | None, params: str | None, *, settle: float, out: Path | None,
                json_out: bool) -> None:
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        result = api.replay_log(log, controller, params, settle_s=settle)
    except ValueError as exc:  # bad input, one line: ConfigError (hil.api), ReplayError, ControllerConfigError
        raise fail(str(exc)) from None
    try:
        png, js = api.write_replay_outputs(result, out if out is not None else log.parent)
    except OSError as exc:
        raise fail(f"{out if out is not None else log.parent}: cannot write the plot and JSON: "
                   f"{exc.strerror or exc}") from None
    if json_out:
        print_json({**result.as_dict(), "plot": str(png), "json": str(js)})
        return
    t = Table(title=f"{log.name}: logged {result.logged.name} vs replayed {result.replayed.name} "
                    f"({result.window_s[0]:.1f}-{result.window_s[1]:.1f} s, {result.window_ticks} samples)")
    t.add_column("metric")
    t.add_column("axis")
    t.add_column("unit")
    t.add_column(f"logged {result.logged.name}", justify="right")
    t.add_column(f"replayed {result.replayed.name}", justify="right")
    for metric, axis, unit, logged, replayed in result.table():
        t.add_row(metric, axis, unit, "" if metric.startswith("drive minus") else _fmt(logged), _fmt(replayed))
    console.print(t)
    mismatches = sum(v for k, v in result.inputs.items() if k.startswith("command_mismatches"))
    note(f"replayed {result.ticks} of {result.rows} samples (up to {result.ended}); "
         f"commands rebuilt exactly except {mismatches}; gyro values beyond float32's exact range: "
         f"{result.inputs.get('gyro_inexact', 0)}")
    console.print(f"plot: {png}   json: {js}", highlight=False)


def _fmt(x: float) -> str:
    return "-" if x is None or math.isnan(x) else f"{x:.4g}"


# --- a capture back at the boards (hil.api.replay_capture) ------------------------------------------------------


def _replay_capture(source: Path, ports_file: Path | None, port: list[str], *,
                    clock: Literal["lockstep", "realtime"] | None, seed: int | None,
                    timing: Literal["samples", "clock"], out: Path | None, json_out: bool) -> None:
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        result = api.replay_capture(source, ports=port, ports_file=ports_file, clock=clock, seed=seed,
                                    timing=timing, record_dir=out)
    except ValueError as exc:  # bad input, one line: ConfigError (hil.api), ReplayError, CaptureError
        raise fail(str(exc)) from None
    if out is not None:
        try:
            api.write_playback_json(result, out)
        except OSError as exc:
            raise fail(f"{out}: cannot write the JSON: {exc.strerror or exc}") from None
    if json_out:  # the JSON alone on stdout
        print_json(result.as_dict())
    else:
        if result.emulator is not None:
            emu = result.emulator
            note(f"emulator: {emu['clock']}, seed {emu['seed']}, config {emu['config'] or 'the default'}")
        _print_playback(result)
    if result.stopped or result.answered < result.commands:
        raise typer.Exit(1)


def _print_playback(r: PlaybackResult) -> None:
    t = Table(title=f"{r.capture.name} played back ({r.timing} timing, {r.duration_s:.1f} s)")
    for col in ("link", "sent", "received", "in the capture (received)", "answered", "NACKs"):
        t.add_column(col)
    for name, lp in r.links.items():
        t.add_row(name, _counts(lp.sent), _counts(lp.received), _counts(lp.captured_rx),
                  f"{lp.acked + lp.nacked} ({lp.unanswered} unanswered)",
                  ", ".join(f"{k} x{v}" for k, v in lp.nacks.items()) or "0")
    console.print(t)
    lt = r.loop_timing
    lines = [f"frames sent: {r.frames_sent} of {r.frames_in_capture}; commands answered: {r.answered} of "
             f"{r.commands}",
             f"stream: {'started' if r.stream_started else 'never started'}, {r.samples} samples, "
             f"{r.samples_equal} of {r.samples_compared} equal to the capture's; board timing reports: "
             f"{lt['ticks_reported']} ticks, {lt['missing']} without a command, {lt['late_total']} late",
             f"writes late against their schedule: p50 {r.lateness_us['p50']:.0f} us, "
             f"p99 {r.lateness_us['p99']:.0f} us",
             f"stopped early: {r.stopped}" if r.stopped else "played to the end",
             *([f"left safe: sent {', '.join(r.safe_end)}"] if r.safe_end else []),
             *([f"replay capture: {r.record}"] if r.record else [])]
    for line in lines:
        console.print(line, highlight=False)


def _counts(counter: Mapping[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counter.items())) or "-"
