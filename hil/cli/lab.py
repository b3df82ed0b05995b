"""`hil watch`, `hil emulate` and `hil doctor`: the live telemetry viewer, the emulated lab on its own, and the
hardware check."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Annotated, Literal

import typer

from hil.cli._common import app, console, err_console, fail, finite, print_json


@app.command()
def watch(
    broker: Annotated[str, typer.Option(help="mqtt://host:port of the broker the bench publishes to.")] = (
        "mqtt://127.0.0.1:1883"),
    bench: Annotated[str, typer.Option(help="The bench id (mqtt.bench_id in the session).")] = "bench",
    seconds: Annotated[float | None, typer.Option(help="Stop after this long (default: until Ctrl-C).")] = None,
) -> None:
    """Live telemetry from the broker: latest value, unit and trend of every channel, session state, events."""
    import asyncio  # noqa: PLC0415  (loaded on first use: `hil --help` stays fast)

    from pydantic import ValidationError  # noqa: PLC0415  (loaded on first use: `hil --help` stays fast)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import MqttConfig, one_line  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    finite("--seconds", seconds)
    if seconds is not None and seconds <= 0:
        raise fail(f"--seconds: {seconds!r} is not above 0")
    try:
        config = MqttConfig.from_url(broker, bench_id=bench)
    except ValidationError as exc:
        raise fail(one_line("--broker", exc)) from None
    except ValueError as exc:
        raise fail(f"--broker: {exc}") from None
    raise typer.Exit(asyncio.run(api.watch(config, seconds=seconds, console=console, err_console=err_console)))


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def emulate(  # noqa: PLR0917 (typer maps parameters to options)
    ctx: typer.Context,
    config: Annotated[Path | None, typer.Option(help="Emulator YAML (default profiles/emulator/default.yaml).")] = None,
    clock: Annotated[Literal["realtime", "lockstep"] | None, typer.Option(
        help="The emulator's clock (overrides the config).")] = None,
    seed: Annotated[int | None, typer.Option(help="Seed of plant noise and link faults (overrides config).")] = None,
    ports_file: Annotated[Path | None, typer.Option(help="Also write the ports map (JSON) to this file.")] = None,
    fault_log: Annotated[Path | None, typer.Option(help="Write every injected fault and board event (JSONL).")] = None,
    seconds: Annotated[float | None, typer.Option(help="Stop after this much simulated time.")] = None,
) -> None:
    """Run the emulated lab (gimbal on a hexapod, four boards on ptys) until Ctrl-C: `python -m firmware_stub`."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    args = api.emulator_command(config=config, clock=clock, seed=seed, ports_file=ports_file, fault_log=fault_log,
                                seconds=seconds)
    sys.stdout.flush()
    os.execv(sys.executable, args + list(ctx.args))  # the emulator gets our pid, so signals reach it directly


@app.command()
def doctor(
    session: Annotated[Path | None, typer.Argument(
        help="A session file: check its ports at their baud rates, and ask its boards (default: every adapter in "
             "/dev/serial/by-id/, the ports alone).",
        exists=False)] = None,
    boards: Annotated[bool, typer.Option(
        "--boards/--no-boards", help="Ask the session's boards: IDENT and its catalogue fingerprint, and a 2 s listen "
                                     "to the servo stream (--no-boards: the ports alone, nothing sent).")] = True,
    json_out: Annotated[bool, typer.Option("--json", help="The findings as JSON on stdout.")] = False,
) -> None:
    """Is the hardware ready? Each port exists and is a serial port this user may open, no other bench holds it, a
    USB-serial adapter's latency timer is 1 ms, and the baud rate carries the link's periodic messages; with a
    session file, each board answers IDENT with the catalogue fingerprint this bench expects, and a 2 s listen to
    the servo stream reports its rate and jitter (the driver is never enabled, the hexapod never moved); and what the
    wire adds to every cycle at the session's rates, a warning over ports.wire_delay_budget_us. Exit 1 if a check
    fails, each failure saying what to do (a warning does not fail)."""
    from rich.table import Table  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        findings = api.doctor(session, boards=boards)
    except ConfigError as exc:
        raise fail(str(exc)) from None
    failed = [f for f in findings if not f.ok]
    if json_out:
        print_json({"ok": not failed, "findings": [vars(f) for f in findings]})
    elif not findings:
        console.print("no serial adapters in /dev/serial/by-id/; give the session file whose ports to check")
    else:
        table = Table("link", "check", "", "what was found", show_header=True, header_style="bold")
        for f in findings:
            mark = "[bold red]FAIL[/]" if not f.ok else "[yellow]warn[/]" if f.warning else "[green]ok[/]"
            table.add_row(f.link, f.check, mark, f.detail)
        console.print(table)
        console.print(f"{len(findings) - len(failed)} of {len(findings)} checks passed"
                      + ("" if not failed else "; fix what FAIL says, then run `hil doctor` again"))
    raise typer.Exit(1 if failed else 0)
