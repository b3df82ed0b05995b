"""`hil watch`: the terminal view of a bench's MQTT topics (docs/telemetry.md).

It subscribes to ``hil/<bench>/#``, keeps the latest status, state and events of each session and a sparkline of
every channel, and redraws with rich at a few Hz. It only reads: nothing it does reaches a bench."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import secrets
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import aiomqtt

from hil.config import MqttConfig, check_topic_name
from hil.telemetry._wire import MISS_X, MISS_Y, TOPIC_ROOT, dumps, status_topic

if TYPE_CHECKING:
    from rich.console import Console, RenderableType


SPARK_BLOCKS = "▁▂▃▄▅▆▇█"
SPARK_POINTS = 50  # values kept per channel for the sparkline (1 s at 50 Hz); fewer on a narrow terminal


def sparkline(values: Iterable[Any], width: int | None = None) -> str:
    """One block character per value (the last ``width`` of them), scaled to their own min..max.

    The minimum is ``▁``, the maximum ``█``, the others in 8 steps between (rounded). A constant window is a
    flat line of ``▁``. A value that is not a finite number (null, NaN, a string) is a space and takes no part
    in the scaling; booleans count as 0 and 1. ``sparkline([0, 1, 2, 3, 4, 5, 6, 7]) == "▁▂▃▄▅▆▇█"``.
    """
    window = list(values)
    if width is not None:
        window = window[-width:] if width > 0 else []
    nums = [float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None for v in window]
    finite = [v for v in nums if v is not None]
    if not finite:
        return " " * len(nums)
    lo = min(finite) / 2  # halves: hi - lo stays finite for any two floats
    span = max(finite) / 2 - lo
    top = len(SPARK_BLOCKS) - 1
    if not span > 0:
        return "".join(" " if v is None else SPARK_BLOCKS[0] for v in nums)
    return "".join(" " if v is None else SPARK_BLOCKS[min(top, int((v / 2 - lo) / span * top + 0.5))] for v in nums)


@dataclass
class _SessionView:
    values: dict[str, Any]
    units: dict[str, str]
    history: dict[str, deque[Any]]  # channel -> its last SPARK_POINTS values, for the sparkline
    arrivals: deque[float]
    events: deque[dict[str, Any]]
    t_s: float | None = None
    state: dict[str, Any] | None = None
    count: int = 0
    last_seen: float = 0.0

    @classmethod
    def new(cls) -> _SessionView:
        return cls(values={}, units={}, history={}, arrivals=deque(maxlen=2000), events=deque(maxlen=5))


class _WatchView:
    """What `hil watch` knows, updated from messages and rendered as rich tables."""

    RATE_WINDOW_S = 2.0

    def __init__(self, config: MqttConfig, session: str | None, spark_width: int = SPARK_POINTS) -> None:
        self.config = config
        self.pinned = session
        self.status: dict[str, Any] | None = None
        self.sessions: dict[str, _SessionView] = {}
        self.connected = False
        self.note = ""
        self.bad = 0
        self.spark_width = max(1, min(SPARK_POINTS, spark_width))
        self._prefix = f"{TOPIC_ROOT}/{config.bench_id}/"

    def followed(self) -> str | None:
        if self.pinned:
            return self.pinned
        if self.status and isinstance(self.status.get("session"), str):
            return self.status["session"]
        live = [(v.last_seen, k) for k, v in self.sessions.items() if v.last_seen]
        return max(live)[1] if live else None

    def handle(self, topic: str, payload: bytes, now: float) -> None:
        if not topic.startswith(self._prefix):
            return
        try:
            body = json.loads(payload) if payload else None
        except ValueError:
            self.bad += 1
            return
        rest = topic[len(self._prefix) :].split("/")
        if rest == ["status"]:
            self.status = body if isinstance(body, dict) else None
            return
        if len(rest) != 3 or rest[0] != "session" or not isinstance(body, dict):
            return
        view = self.sessions.setdefault(rest[1], _SessionView.new())
        leaf = rest[2]
        if leaf == "telemetry":
            view.t_s = body.pop("t_s", None)
            view.values.update(body)
            history = view.history
            for name, value in body.items():
                trend = history.get(name)
                if trend is None:
                    trend = history[name] = deque(maxlen=SPARK_POINTS)
                trend.append(value)
            view.arrivals.append(now)
            view.count += 1
            view.last_seen = now
        elif leaf == "meta":
            units = body.get("units")
            if isinstance(units, dict):
                view.units.update({str(k): str(v) for k, v in units.items()})
        elif leaf == "state":
            view.state = body
        elif leaf == "events":
            view.events.append(body)
            view.last_seen = now

    def rate_hz(self, view: _SessionView, now: float) -> float:
        arr = view.arrivals
        while arr and now - arr[0] > self.RATE_WINDOW_S:
            arr.popleft()
        if len(arr) < 2 or arr[-1] <= arr[0]:
            return 0.0
        return (len(arr) - 1) / (arr[-1] - arr[0])

    def render(self, now: float) -> RenderableType:
        from rich.console import Group  # noqa: PLC0415  (the terminal UI: loaded only when it draws)
        from rich.table import Table  # noqa: PLC0415  (the terminal UI: loaded only when it draws)
        from rich.text import Text  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

        bench = self.config.bench_id
        status = (self.status or {}).get("status", "unknown")
        style = {"online": "bold green", "offline": "bold red"}.get(status, "yellow")
        head = Text.assemble(
            ("bench ", "bold"),
            (bench, "bold"),
            ": ",
            (str(status), style),
            f"  broker {self.config.host}:{self.config.port} ",
            ("connected", "green") if self.connected else ("disconnected", "red"),
        )
        if self.note:
            head.append(f"  ({self.note})", style="dim")
        sid = self.followed()
        view = self.sessions.get(sid) if sid else None
        if view is None:
            return Group(head, Text(f"session: {sid or '-'}   (no telemetry yet)"))
        state = (view.state or {}).get("state", "-")
        rate = self.rate_hz(view, now)
        age = now - view.last_seen if view.last_seen else math.inf
        info = Text.assemble(
            ("session ", "bold"),
            (sid or "-", "cyan"),
            "  state ",
            (str(state), "bold"),
            f"  rate {rate:.1f} Hz",
            f"  t_s {view.t_s:.3f}" if isinstance(view.t_s, (int, float)) else "",
            f"  messages {view.count}",
            ("  (stale)", "yellow") if age > 2.0 and view.count else "",
        )
        parts: list[RenderableType] = [head, info]
        if MISS_X in view.values or MISS_Y in view.values:  # the image board's, latest frame (null: no target)
            parts.append(Text.assemble(
                ("miss ", "bold"), "x ", _fmt(view.values.get(MISS_X)), "  y ", _fmt(view.values.get(MISS_Y)),
                f" {view.units.get(MISS_X, 'px')}",
            ))
        table = Table(title=None, expand=False)
        table.add_column("channel")
        table.add_column("value", justify="right")
        table.add_column("unit")
        table.add_column("trend", no_wrap=True, overflow="crop")
        for name in sorted(view.values):
            trend = sparkline(view.history.get(name, ()), self.spark_width)
            table.add_row(name, _fmt(view.values[name]), view.units.get(name, ""), trend)
        parts.append(table)
        if view.events:
            ev = Table(title="last events", expand=False)
            ev.add_column("time")
            ev.add_column("kind")
            ev.add_column("detail")
            for e in reversed(view.events):
                t = e.get("t")
                when = time.strftime("%H:%M:%S", time.localtime(t)) if isinstance(t, (int, float)) else "-"
                ev.add_row(when, str(e.get("kind", "?")), dumps(e.get("detail", {}))[:80])
            parts.append(ev)
        return Group(*parts)


def _fmt(v: Any) -> str:
    if v is None:  # null: NaN on the bench, or a miss distance with no valid target
        return "-"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, (int, float)):
        return f"{v:.6g}"
    return str(v)[:40]


async def watch(
    config: MqttConfig,
    *,
    seconds: float | None,
    console: Console,
    session: str | None = None,
    err_console: Console | None = None,
) -> int:
    """Show the bench's live telemetry from the broker (until ``seconds`` elapse, or forever).

    The live view goes to ``console``; errors and warnings go to ``err_console`` (default: a Console on
    stderr). Returns 0; or 1 after printing one error line if the broker cannot be reached at the start. A
    broker lost later is one warning line, shown as disconnected and reconnected to with backoff.
    """
    from rich.console import Console as RichConsole  # noqa: PLC0415  (the terminal UI: loaded only when it draws)
    from rich.live import Live  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    if err_console is None:
        err_console = RichConsole(stderr=True)
    if session is not None:
        check_topic_name("session", session)
    loop = asyncio.get_running_loop()
    deadline = None if seconds is None else loop.time() + seconds
    view = _WatchView(config, session, spark_width=console.width - 48)  # room for channel, value, unit
    prefix = f"{TOPIC_ROOT}/{config.bench_id}"
    topics = [f"{prefix}/#"] if session is None else [status_topic(config.bench_id), f"{prefix}/session/{session}/#"]
    where = f"{config.host}:{config.port}"

    def complain(text: str) -> None:
        err_console.print(text, highlight=False, markup=False, soft_wrap=True)

    def make_client() -> aiomqtt.Client:
        return aiomqtt.Client(
            config.host,
            config.port,
            identifier=f"hil-watch-{secrets.token_hex(4)}",
            username=config.username,
            password=config.password_value,
            keepalive=config.keepalive_s,
            timeout=float(max(2, config.keepalive_s)),
            max_queued_incoming_messages=10_000,
        )

    client = make_client()
    try:
        await client.__aenter__()
    except aiomqtt.MqttError as exc:
        complain(f"error: cannot reach the MQTT broker at {where}: {_one_line(exc)}")
        return 1

    async def consume(c: aiomqtt.Client) -> None:
        for topic in topics:
            await c.subscribe(topic, qos=1)
        view.connected, view.note = True, ""
        async for m in c.messages:
            payload = m.payload if isinstance(m.payload, bytes) else str(m.payload).encode()
            view.handle(str(m.topic), payload, loop.time())

    def new_live() -> Live:
        # redirect_stderr=False: the Live would otherwise catch what err_console writes and print it on console
        live = Live(view.render(loop.time()), console=console, auto_refresh=False, transient=False,
                    redirect_stderr=False)
        live.start(refresh=True)
        return live

    live = new_live()

    def warn(text: str) -> None:
        nonlocal live
        if console.is_terminal and err_console.is_terminal:  # one screen, most likely: keep the view whole
            live.stop()  # the view so far stays above the warning; a new one starts below it
            complain(text)
            live = new_live()
        else:
            complain(text)

    async def repaint() -> None:
        while True:
            live.update(view.render(loop.time()), refresh=True)
            await asyncio.sleep(0.25)

    painter = loop.create_task(repaint())
    delay = config.reconnect_min_s
    try:
        async with asyncio.timeout_at(deadline):
            while True:
                try:
                    try:
                        await consume(client)
                    finally:
                        with contextlib.suppress(aiomqtt.MqttError):
                            await client.__aexit__(None, None, None)
                except aiomqtt.MqttError as exc:
                    view.connected, view.note = False, f"lost: {exc}; reconnecting"
                    warn(f"warning: lost the MQTT broker at {where}: {_one_line(exc)}; reconnecting")
                while True:
                    await asyncio.sleep(delay)
                    delay = min(delay * 2, config.reconnect_max_s)
                    client = make_client()
                    try:
                        await client.__aenter__()
                    except aiomqtt.MqttError as exc:
                        view.note = f"cannot reconnect: {exc}"
                        continue
                    delay = config.reconnect_min_s
                    break
    except TimeoutError:
        pass
    finally:
        painter.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await painter
        live.update(view.render(loop.time()), refresh=True)
        live.stop()
    return 0


def _one_line(exc: BaseException) -> str:
    return str(exc).replace("\n", " ") or type(exc).__name__
