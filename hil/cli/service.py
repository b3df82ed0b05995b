"""`hil serve`, `hil queue ...`, `hil bench ...`, and the `--bench URL` of `hil run`, `hil ident` and
`hil campaign`: the lab service and its clients, through :mod:`hil.service` (docs/service.md)."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from hil.cli._bench import call, client, duration
from hil.cli._common import CONTEXT, app, console, err_console, fail, note, print_json

queue_app = typer.Typer(help="The service's queue: list, add, remove, move, clear, start, stop.",
                        no_args_is_help=True, context_settings=CONTEXT, rich_markup_mode="markdown")
bench_app = typer.Typer(help="The service's bench: status, the lease, stop or abort the running item.",
                        no_args_is_help=True, context_settings=CONTEXT, rich_markup_mode="markdown")
app.add_typer(queue_app, name="queue")
app.add_typer(bench_app, name="bench")

BenchOption = Annotated[str | None, typer.Option(
    "--bench", envvar="HIL_BENCH", show_envvar=True, help="The service's URL, e.g. http://bench-pc:8765.")]
JsonOption = Annotated[bool, typer.Option("--json", help="Print the answer as JSON.")]


@app.command()
def serve(  # noqa: PLR0917 (typer maps parameters to options)
    loopback: Annotated[bool, typer.Option("--loopback", help="Serve the emulated lab (realtime clock).")] = False,
    lab: Annotated[Path | None, typer.Option(
        help="Without --loopback: a session file whose ports: are the lab's (the service holds them).")] = None,
    host: Annotated[str, typer.Option(help="Address to listen on; beyond localhost needs --token-file.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535, help="TCP port.")] = 8765,
    state_dir: Annotated[Path, typer.Option(help="The queue, the history (SQLite) and the runs' logs.")] = Path(
        "runs/service"),
    token_file: Annotated[Path | None, typer.Option(
        help="YAML: tokens with their user and role (viewer | operator); docs/service.md.")] = None,
    emulator: Annotated[Path | None, typer.Option(
        help="With --loopback: the emulated lab's config (default the shipped one).")] = None,
    seed: Annotated[int, typer.Option(help="With --loopback: the emulated lab's seed.")] = 0,
    emulator_cpu: Annotated[int, typer.Option(
        help="With --loopback: pin the emulated lab to this CPU (-1: the last, where the shipped sessions put the "
             "loop and the emulator).")] = -1,
    mqtt: Annotated[Path | None, typer.Option(
        help="The service's MQTT broker: a YAML file with a session's mqtt: section (host, port, username, and "
             "the password inline, or password_env / password_file read here). Every session and ident item "
             "publishes its telemetry there; a submitted item never carries the broker's secret.")] = None,
    max_rate: Annotated[float, typer.Option(
        min=1.0, help="Each client's requests a second (bursts of twice that); past it, 429 with Retry-After.")] = 50.0,
    allow_host: Annotated[list[str] | None, typer.Option(
        "--allow-host", help="A further host name the service answers to (its DNS name on the lab's network); "
                             "repeatable. Requests naming any other Host are refused (docs/service.md, \"Same "
                             "origin\").")] = None,
) -> None:
    """Serve the bench to the lab: the queue, the history, the lease, a live page at http://HOST:PORT/, and a
    worker that owns the boards' ports and runs one item at a time as `hil run` does. Ctrl-C stops it (a running
    item is aborted, the driver disabled first)."""
    import uvicorn  # noqa: PLC0415  (the web server: loaded only when serving)

    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.service import Gate, ServiceOptions, build_app, is_loopback_host, load_tokens  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    if loopback == (lab is not None):
        raise fail("--loopback or --lab SESSION.yaml: serve the emulated lab, or the lab whose ports a session names")
    if lab is not None and not lab.is_file():
        raise fail(f"--lab {lab}: no such file")
    tokens = None
    if token_file is not None:
        try:
            tokens = load_tokens(token_file)
        except ConfigError as exc:
            raise fail(str(exc)) from None
    elif not is_loopback_host(host):
        raise fail(f"--host {host}: serving beyond this machine needs --token-file FILE (tokens with roles; "
                   "docs/service.md)")
    if mqtt is not None:
        from hil.config import MqttConfig, load_model  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

        try:
            load_model(MqttConfig, mqtt)
        except ConfigError as exc:
            raise fail(f"--mqtt: {exc}") from None
    check_free_port(host, port)
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise fail(f"--state-dir {state_dir}: {exc.strerror or exc}") from None
    options = ServiceOptions(state_dir=state_dir.absolute(), loopback=loopback, lab=lab.absolute() if lab else None,
                             emulator=emulator.absolute() if emulator else None, seed=seed, host=host, port=port,
                             emulator_cpu=emulator_cpu, allow_hosts=tuple(allow_host or ()),
                             mqtt=mqtt.absolute() if mqtt else None, max_rate_per_s=max_rate)
    shown = "localhost" if host in ("127.0.0.1", "::1") else host
    url = f"http://{shown}:{port}/"

    def ready(_manager: Any) -> None:
        what = "the emulated lab" if loopback else f"the lab of {lab}"
        err_console.print(f"[bold]hil serve[/]: {what} at {url} (state in {state_dir}); Ctrl-C stops it",
                          highlight=False)
        ports = ", ".join(f"{k} {v}" for k, v in _manager.worker_info.get("ports", {}).items())
        note(f"the worker holds the lab's ports: {ports}")
        note(f"the queue is stopped ({_manager.queue_stopped}): nothing runs until an operator starts it, "
             "`hil queue start` or Start on the page")

    fatal: list[str] = []

    def cannot_serve(message: str) -> None:  # the worker could not take the lab (a port held by another bench)
        fatal.append(message)
        server.should_exit = True

    app_ = build_app(options, Gate(tokens), on_ready=ready, on_fatal=cannot_serve)
    config = uvicorn.Config(app_, host=host, port=port, log_level="warning", access_log=False, lifespan="on",
                            ws_max_size=1 << 20)
    server = uvicorn.Server(config)
    server.run()
    if fatal:
        raise fail(f"hil serve: cannot serve the lab: {fatal[0]}")


def check_free_port(host: str, port: int) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise fail(f"--port {port}: cannot listen on {host}:{port}: {exc.strerror or exc}") from None


def show(data: Any, json_out: bool, text: str | None = None) -> None:
    if json_out:
        print_json(data)
    elif text is not None:
        console.print(text, highlight=False)


# --- hil queue -------------------------------------------------------------------------------------


@queue_app.command("list")
def queue_list(bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """The queue in order (the running item first) and whether it runs."""
    data = call(client(bench).queue)
    if json_out:
        print_json(data)
        return
    t = Table(title=f"queue ({'running' if data['running'] else 'stopped: ' + str(data.get('stopped') or '')})")
    for col in ("#", "uid", "kind", "name", "user", "submitted", "state"):
        t.add_column(col)
    for i, item in enumerate(data["items"]):
        t.add_row(str(i), item["uid"][:12], item["kind"], item["name"], item["user"], item["submitted_at"],
                  "running" if item["started_at"] else "waiting")
    console.print(t)


@queue_app.command("add")
def queue_add(  # noqa: PLR0917 (typer maps parameters to options)
    file: Annotated[Path, typer.Argument(help="A session, ident or campaign YAML.")],
    kind: Annotated[str, typer.Option(help="session | ident | campaign")] = "session",
    axis: Annotated[str | None, typer.Option(help="ident: the axis (el | az).")] = None,
    position: Annotated[int | None, typer.Option(min=0, help="Place in the queue (0 first; default last).")] = None,
    bench: BenchOption = None, json_out: JsonOption = False,
) -> None:
    """Submit a file; it is checked here and by the service (exit 2 with its one line if it does not load)."""
    item = call(client(bench).add, file, kind=kind, options={"axis": axis} if axis else {}, position=position)
    show(item, json_out, f"queued {item['uid']} ({item['kind']} {item['name']}, user {item['user']})")


UidArgument = Annotated[str, typer.Argument(
    help="The item's uid, or its first characters (at least 6; `hil queue list` shows 12).")]


@queue_app.command("remove")
def queue_remove(uid: UidArgument, bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Take a waiting item off the queue."""
    item = call(client(bench).remove, uid)
    show(item, json_out, f"removed {item['uid'][:12]} ({item['kind']} {item['name']}, user {item['user']})")


@queue_app.command("move")
def queue_move(uid: UidArgument, position: Annotated[int, typer.Argument(min=0, help="New place (0 first).")],
               bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Move a waiting item."""
    item = call(client(bench).move, uid, position)
    show(item, json_out, f"moved {item['uid'][:12]} ({item['name']}) to {position}")


@queue_app.command("clear")
def queue_clear(bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Take every waiting item off the queue."""
    data = call(client(bench).clear)
    show(data, json_out, f"removed {data['removed']} items")


@queue_app.command("start")
def queue_start(stop_on_failure: Annotated[bool, typer.Option(
        "--stop-on-failure", help="Stop the queue after an item that did not complete.")] = False,
        bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Run the queue's items one after another."""
    data = call(client(bench).start, stop_on_failure)
    show(data, json_out, "the queue runs" + (f" (it was stopped: {data['was_stopped']})" if data.get("was_stopped")
                                             else ""))


@queue_app.command("stop")
def queue_stop(bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Start no further item (the running one goes on: `hil bench stop` ends it)."""
    show(call(client(bench).stop_queue), json_out, "the queue is stopped; the running item (if any) goes on")


# --- hil bench -------------------------------------------------------------------------------------


@bench_app.command("status")
def bench_status(bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """The service, its worker and boards, the running item, the queue and the lease."""
    s = call(client(bench).status)
    if json_out:
        print_json(s)
        return
    w, q, lease, running = s["worker"], s["queue"], s["lease"], s["running"]
    console.print(f"[bold]{s['service']['lab']}[/]  worker {w['state']}" + (f": {w['error']}" if w.get("error")
                                                                           else ""), highlight=False)
    doctor = w.get("doctor")
    for line in board_lines(w, running is not None):
        console.print(f"  {line}", highlight=False, markup=False, soft_wrap=True)
    rest = w.get("rest") or {}
    if running is None and rest.get("at"):
        ago = duration(max(0.0, time.time() - float(rest["at"])))
        if rest.get("ok"):
            console.print(f"  between items: at rest (measured {ago} ago, after {rest.get('waited_s', 0):.1f} s)",
                          highlight=False, soft_wrap=True)
        else:
            console.print(f"  [bold red]between items: NOT AT REST[/] (measured {ago} ago): "
                          f"{escape(str(rest.get('summary', '')))}", highlight=False, soft_wrap=True)
        for sent in rest.get("made_safe") or []:
            console.print(f"    made safe: {sent}", highlight=False, markup=False, soft_wrap=True)
    elif running is None and w.get("state") == "ready":
        console.print("  between items: measuring the boards' rest state (an item just ended)", highlight=False)
    if doctor:
        bad = [f for f in doctor["findings"] if not f["ok"]]
        console.print(f"  hardware checks: {len(doctor['findings']) - len(bad)} of {len(doctor['findings'])} passed"
                      + "".join(f"\n    [red]{f['link']} {f['check']}[/]: {f['detail']}" for f in bad),
                      highlight=False)
    if running:
        total = running.get("total") or 0
        done = f"{running.get('cycles', 0) / total:.0%}" if total else "starting"
        console.print(f"running: {running['name']} ({running['kind']}, {running['user']}) {done}", highlight=False)
    console.print(f"queue: {'running' if q['running'] else 'stopped (' + str(q.get('stopped')) + ')'}, "
                  f"{q['waiting']} waiting", highlight=False)
    console.print("lease: " + (f"{lease['holder']}, {lease['remaining_s']:.0f} s left" if lease else "none"),
                  highlight=False)


def board_lines(worker: dict[str, Any], running: bool) -> list[str]:
    """One line a board: its port, whether it was identified (its firmware and serial number from the hardware
    checks), and its state: between items the rest state measured (``driver disabled``, ``hexapod IDLE at home``),
    while an item runs ``armed`` or ``in use``."""
    idents = {f["link"]: f for f in ((worker.get("doctor") or {}).get("findings") or []) if f["check"] == "ident"}
    rest = ((worker.get("rest") or {}).get("boards") or {}) if not running else {}
    boards = worker.get("boards") or {}
    width = max((len(str(b.get("port", ""))) for b in boards.values()), default=0)
    lines = []
    for name, board in boards.items():
        finding = idents.get(name)
        values = (finding or {}).get("values") or {}
        if board.get("identified"):
            ident = "identified" + (f" (firmware {values['firmware_version']}, serial {values['serial_number']})"
                                    if finding and finding["ok"] and "firmware_version" in values else "")
        else:
            ident = "NOT identified" + (": its check failed (below)" if finding and not finding["ok"] else "")
        if running:
            state = "armed" if board.get("armed") else "in use by the item" if board.get("connected") else ""
        else:
            state = f"at rest: {rest[name]}" if name in rest else ""
        lines.append(f"{name:8s} {board.get('port', '')!s:{width}s}  {ident}" + (f"; {state}" if state else ""))
    return lines


@bench_app.command("doctor")
def bench_doctor(bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Run `hil doctor`'s checks on the service's ports (between items): ports, each board's IDENT, the stream."""
    bench_ = client(bench)
    before = (call(bench_.status)["worker"].get("doctor") or {}).get("at")
    call(bench_.doctor)
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        doctor = call(bench_.status)["worker"].get("doctor") or {}
        if doctor.get("at") != before:
            break
        time.sleep(0.3)
    else:
        raise fail("the checks did not report within 30 s; see the service's worker.log", code=1)
    if json_out:
        print_json(doctor)
    else:
        t = Table(title=f"hardware checks on {bench_.url}")
        for col in ("link", "check", "ok", "detail"):
            t.add_column(col)
        for f in doctor["findings"]:
            t.add_row(f["link"], f["check"], "[green]ok[/]" if f["ok"] else "[red]FAIL[/]", f["detail"])
        console.print(t)
    raise typer.Exit(0 if doctor.get("ok") else 1)


@bench_app.command("lease")
def bench_lease(ttl: Annotated[float, typer.Option(min=5, help="Seconds until it lapses unless renewed.")] = 300.0,
                bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Take (or renew) the lease: only your items run while you hold it."""
    lease = call(client(bench).lease, ttl)
    show(lease, json_out, f"leased to {lease['holder']} for {lease['ttl_s']:g} s (renew before it lapses)")


@bench_app.command("release")
def bench_release(bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Release your lease."""
    show(call(client(bench).release), json_out, "lease released")


@bench_app.command("break")
def bench_break(reason: Annotated[str, typer.Option(help="Why (it goes into the lease history).")],
                bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Break another operator's lease."""
    data = call(client(bench).break_lease, reason)
    show(data, json_out, f"broke {data['broken']['holder']}'s lease")


ItemOption = Annotated[str | None, typer.Option(
    "--item", help="Only if the running item is this one: its uid, or its first characters (at least 6).")]


@bench_app.command("stop")
def bench_stop(reason: Annotated[str, typer.Option(help="Why (it goes into the log).")] = "",
               item: ItemOption = None, bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Stop the running item the normal way: the swing stopped while stabilizing, then the driver disabled."""
    data = call(client(bench).stop, reason, uid=item)
    show(data, json_out, f"stopping the running item ({data['uid'][:12]})")


@bench_app.command("abort")
def bench_abort(reason: Annotated[str, typer.Option(help="Why (it goes into the log).")] = "",
                item: ItemOption = None, bench: BenchOption = None, json_out: JsonOption = False) -> None:
    """Abort the running item: the driver disabled first."""
    data = call(client(bench).abort, reason, uid=item)
    show(data, json_out, f"aborting the running item ({data['uid'][:12]})")
