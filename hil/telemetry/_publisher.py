"""Live MQTT telemetry of a bench session (docs/telemetry.md); `hil watch` is in hil.telemetry._watch, the topics,
units and JSON both speak in hil.telemetry._wire.

The control loop calls `Telemetry.sample()` on every 1 kHz cycle, in the event loop's thread.
The rule of this module is that telemetry never blocks, slows down or crashes that loop:

- `sample()` decimates by board time (`t_s`) to `telemetry_hz`; a call that is not due is two
  attribute loads and a compare (~0.1 us). A due call copies the values into a bounded deque
  and wakes the publisher task; it never waits, never raises.
- One background task owns the MQTT connection (aiomqtt, which does not reconnect by itself):
  it connects, publishes, and on `aiomqtt.MqttError` waits an exponential backoff between
  `reconnect_min_s` and `reconnect_max_s` and connects again, for as long as the session runs.
- Everything queued is bounded. Telemetry is accepted only while connected and while fewer
  than `queue_size` samples wait; otherwise the *newest* sample is dropped and counted
  (`stats.dropped`): a live view wants fresh data, not a backlog replayed after an outage.
  Events (and state changes, which are also events) are kept while disconnected, up to
  `queue_size` of them, and sent after the reconnection; past that the newest is dropped and
  counted, and a warning is logged. Nothing is dropped without being counted.
- `stop()` publishes the retained ``offline`` status and disconnects cleanly, in at most 2 s
  even with no broker; whatever could not be sent by then is counted as dropped.
- Units: the retained ``meta`` message gives the unit of every channel the telemetry carries. A
  channel named like a session-log channel gets the log schema's unit (hil.log.schema, the one
  source of channel units), found by the publisher when a channel first appears, never in `sample()`.
- Slow channels: `miss()` holds the image board's latest miss distance (camera rate); every due
  sample carries it as ``miss_x_px``/``miss_y_px``, so it is published at the telemetry rate.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import logging
import math
import os
import secrets
import signal
import subprocess
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Self

import aiomqtt
import paho.mqtt.client as paho

from hil.config import MqttConfig, check_topic_name
from hil.log import ipc
from hil.telemetry._wire import (
    MISS_X,
    MISS_Y,
    dumps,
    meta_topic,
    schema_units,
    session_topic,
    status_topic,
)

if TYPE_CHECKING:
    pass

__all__ = [
    "MqttConfig",
    "Telemetry",
    "TelemetryProcess",
    "TelemetryStats",
    "meta_topic",
    "schema_units",
    "session_topic",
    "status_topic",
]

log = logging.getLogger(__name__)
# paho's and aiomqtt's log: WARNING and above, as aiomqtt's own logger (paho logs every packet at DEBUG)
mqtt_log = logging.getLogger(f"{__name__}.mqtt")
mqtt_log.setLevel(logging.WARNING)
# paho's lines for a connection the broker dropped ("failed to receive on socket: [Errno 104] Connection reset by
# peer"); the publisher reports the lost broker itself, in one warning
_PAHO_CONNECTION_LOST = ("failed to receive on socket: ", "timeout on socket: ")


class _ConnectionLost(logging.Filter):
    """Keeps paho's error for a dropped connection off stderr: the one line of a lost broker is the publisher's
    own warning (``telemetry: lost the broker ...; reconnecting``); paho's line goes to the DEBUG log."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str) and record.msg.startswith(_PAHO_CONNECTION_LOST):
            log.debug("telemetry: paho: %s", record.getMessage())
            return False
        return True


mqtt_log.addFilter(_ConnectionLost())

STOP_TIMEOUT_S = 2.0  # stop() returns within this, broker or not
FIRST_REPORT_TIMEOUT_S = 5.0  # TelemetryProcess.start() waits this long at most for the first connection attempt
EVENT_QOS = 1  # status, meta, state and events: rare and worth an acknowledgement
_CHILD_NICE = 5  # the publisher child must not preempt the 1 kHz loop or the log writer
_BURST = 25  # telemetry messages handed to paho per loop step when a backlog has built up


@dataclass
class TelemetryStats:
    """Counters of one Telemetry; read them any time (they are plain attributes)."""

    published: int = 0  # telemetry, event and state messages handed to the broker connection
    dropped: int = 0  # samples and events not published: not connected, queue full, or unsent at stop()
    reconnects: int = 0  # successful connections after a lost one
    connected: bool = False
    last_error: str | None = None


def _safe_dumps(body: dict[str, Any], detail: dict[str, Any]) -> str:
    """``body`` plus ``"detail": detail`` as JSON; never raises (an unencodable detail becomes its repr)."""
    try:
        return dumps(body | {"detail": detail})
    except Exception:  # e.g. non-string dict keys deep inside detail
        return dumps(body | {"detail": {"repr": repr(detail)[:2000]}})


# --- the publisher ----------------------------------------------------------------------------


class Telemetry:
    """Publishes one session's telemetry, state and events; see the module docstring and docs/telemetry.md.

    Use from the event loop's thread only (sample/event/state are not thread-safe); the exception is
    :class:`TelemetryProcess`, whose ``sample`` the realtime loop thread calls while the event loop sends
    events and state (each message is one atomic pipe write; the decimation state is the loop thread's).
    """

    TASK_NAME: ClassVar[str] = "hil-telemetry"

    def __init__(self, config: MqttConfig, session_id: str, *, units: Mapping[str, str] | None = None) -> None:
        self.config = config
        self.session_id = check_topic_name("session_id", session_id)
        self.stats = TelemetryStats()
        self._units: dict[str, str] = dict(units or {})
        self._described: set[str] = set()  # channels whose unit has been looked up (by the publisher)
        self._miss: tuple[float, float] | None = None  # latest miss distance (x, y) px, set by miss()
        self._period = 1.0 / config.telemetry_hz
        self._eps = self._period * 1e-6  # absorbs float error in t_s = k * 0.001
        self._due = -math.inf  # exact board time the next sample is due
        self._next_due = -math.inf  # _due - _eps: what the fast path compares against
        self._last_due = -math.inf  # board time of the last due sample (t_s going back resets)
        self._telemetry: deque[tuple[float, dict[str, float]]] = deque()
        self._events: deque[str] = deque()  # JSON payloads for the events topic
        self._state_payload: str | None = None  # latest state, retained; republished at every connect
        self._state_dirty = False
        self._meta_dirty = False
        self._event_seq = 0
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        self._client_id = f"hil-{config.bench_id}-{session_id}-{secrets.token_hex(3)}"
        self.topic_status = status_topic(config.bench_id)
        self.topic_state = session_topic(config.bench_id, session_id, "state")
        self.topic_meta = session_topic(config.bench_id, session_id, "meta")
        self.topic_telemetry = session_topic(config.bench_id, session_id, "telemetry")
        self.topic_events = session_topic(config.bench_id, session_id, "events")

    # -- called from the control loop ------------------------------------------------------

    def sample(self, t_s: float, values: dict[str, float] | Callable[[], dict[str, float]]) -> None:
        """Offer one cycle's values at board time ``t_s``; published at most at ``telemetry_hz``.

        Call it every cycle. When no sample is due this returns after one compare; pass a
        callable to build the dict only when a sample is due. Never raises; a sample that cannot
        be queued (not connected, queue full, the callable failed) is counted in ``stats.dropped``.
        """
        if self._last_due <= t_s < self._next_due:
            return
        self._sample_due(t_s, values)

    def _sample_due(self, t_s: float, values: dict[str, float] | Callable[[], dict[str, float]]) -> None:
        if math.isnan(t_s):  # NaN board time: never due (it would otherwise be due on every call)
            self.stats.dropped += 1
            return
        due = self._due + self._period
        if not (t_s < due <= t_s + self._period):  # first sample, a gap of over a period, or t_s went back
            due = t_s + self._period
        self._due = due
        self._next_due = due - self._eps
        self._last_due = t_s
        if not self.stats.connected or len(self._telemetry) >= self.config.queue_size:
            self.stats.dropped += 1
            return
        try:
            data = dict(values() if callable(values) else values)  # a snapshot: callers may reuse their dict
        except Exception as exc:
            self.stats.dropped += 1
            self.stats.last_error = f"sample(): {type(exc).__name__}: {exc}"
            return
        miss = self._miss  # one read: miss() replaces the tuple whole, from any thread
        if miss is not None:
            data[MISS_X], data[MISS_Y] = miss
        self._enqueue_sample(t_s, data)

    def _enqueue_sample(self, t_s: float, data: dict[str, float]) -> None:
        self._telemetry.append((t_s, data))
        if not self._wake.is_set():
            self._wake.set()

    def miss(self, x_px: float, y_px: float, track_valid: bool = True) -> None:
        """The image board's latest miss distance (px), at camera rate; published with every due sample.

        Every telemetry message from the next due sample on carries ``miss_x_px`` and ``miss_y_px``, the
        values of the latest call (held until the next frame), so the miss distance goes out at the telemetry
        rate whatever the camera rate. ``track_valid=False`` (no target: the values are meaningless) sends
        both as null. Costs one tuple assignment; safe to call from another thread than ``sample()``'s.
        Never raises (a value that is not a number is sent as null).
        """
        try:
            self._miss = (float(x_px), float(y_px)) if track_valid else (math.nan, math.nan)
        except (TypeError, ValueError):
            self._miss = (math.nan, math.nan)

    def event(self, kind: str, /, **detail: Any) -> None:
        """Publish an event (QoS 1, not retained). Queued while disconnected; a drop is counted and logged."""
        self._event_seq += 1
        body = {"kind": str(kind), "seq": self._event_seq, "t": time.time(), "session": self.session_id}
        self._push_event(_safe_dumps(body, detail), str(kind))

    def state(self, state: str, /, **detail: Any) -> None:
        """Set the session state: retained on ``.../state`` (latest wins) and also sent as a ``state`` event."""
        body = {"state": str(state), "t": time.time(), "session": self.session_id}
        self._set_state_payload(_safe_dumps(body, detail))
        self.event("state", **{**detail, "state": str(state)})

    def _set_state_payload(self, payload: str) -> None:
        self._state_payload = payload
        self._state_dirty = True
        if not self._wake.is_set():
            self._wake.set()

    def set_units(self, units: Mapping[str, str]) -> None:
        """Channel -> unit, published retained on ``.../meta`` (again now if connected); wins over the schema's."""
        self._units.update(units)
        self._meta_dirty = True
        if not self._wake.is_set():
            self._wake.set()

    def _push_event(self, payload: str, kind: str) -> None:
        if len(self._events) >= self.config.queue_size:
            self.stats.dropped += 1
            log.warning("telemetry: event queue full (%d), dropped event %r", len(self._events), kind)
            return
        self._events.append(payload)
        if not self._wake.is_set():
            self._wake.set()

    # -- lifecycle -------------------------------------------------------------------------

    async def start(self) -> None:
        """Start the background publisher; returns at once (it connects, and reconnects, on its own)."""
        if self._task is not None and not self._task.done():
            return
        self._stopping = False
        self._wake = asyncio.Event()  # bound to the running loop
        if self._events or self._state_dirty:
            self._wake.set()
        self._task = asyncio.get_running_loop().create_task(self._run(), name=self.TASK_NAME)

    async def stop(self) -> None:
        """Publish the retained offline status, disconnect; returns within 2 s, broker or not."""
        task, self._task = self._task, None
        if task is None:
            return
        t_end = time.monotonic() + STOP_TIMEOUT_S - 0.1
        self._stopping = True
        self._wake.set()
        if not self.stats.connected:
            task.cancel()  # in a backoff sleep or a connection attempt: nothing to flush
        else:
            await asyncio.wait({task}, timeout=max(0.0, t_end - 0.3 - time.monotonic()))
        for _ in range(3):  # cancel again if a cleanup await swallowed the first cancellation
            if task.done():
                break
            task.cancel()
            await asyncio.wait({task}, timeout=max(0.01, (t_end - time.monotonic()) / 2))
        if task.done() and not task.cancelled() and task.exception() is not None:
            self.stats.last_error = f"publisher: {task.exception()!r}"
        unsent = len(self._telemetry) + len(self._events)
        if unsent:
            self.stats.dropped += unsent
            log.warning("telemetry: %d messages not sent at stop (counted as dropped)", unsent)
        self._telemetry.clear()
        self._events.clear()
        self.stats.connected = False

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # -- the background task ---------------------------------------------------------------

    def _status_payload(self, status: str, reason: str | None = None, t: float | None = None) -> str:
        body: dict[str, Any] = {
            "status": status,
            "bench": self.config.bench_id,
            "session": self.session_id,
            "t": time.time() if t is None else t,
        }
        if reason:
            body["reason"] = reason
        return dumps(body)

    def _meta_payload(self) -> str:
        return dumps(
            {
                "session": self.session_id,
                "bench": self.config.bench_id,
                "telemetry_hz": self.config.telemetry_hz,
                "qos": self.config.qos,
                "units": self._units,
                "t": time.time(),
            }
        )

    def _client(self) -> aiomqtt.Client:
        cfg = self.config
        # The will is registered at connect: its "t" is that connection's start, which is the
        # best the broker can tell (it does not stamp wills). See docs/telemetry.md.
        will = aiomqtt.Will(
            self.topic_status,
            self._status_payload("offline", reason="connection lost"),
            qos=EVENT_QOS,
            retain=True,
        )
        return aiomqtt.Client(
            cfg.host,
            cfg.port,
            identifier=self._client_id,
            username=cfg.username,
            password=cfg.password_value,
            will=will,
            keepalive=cfg.keepalive_s,
            timeout=float(max(2, cfg.keepalive_s)),
            clean_session=True,
            max_queued_outgoing_messages=cfg.queue_size,
            max_queued_incoming_messages=16,  # we subscribe to nothing
            logger=mqtt_log,
        )

    async def _run(self) -> None:
        cfg = self.config
        delay = cfg.reconnect_min_s
        ever_connected = False
        while not self._stopping:
            connected_now = False
            try:
                async with self._client() as client:
                    connected_now = True
                    self._on_connected(ever_connected)
                    ever_connected = True
                    delay = cfg.reconnect_min_s
                    await self._connected_session(client)
                    if self._stopping:
                        await client.publish(
                            self.topic_status, self._status_payload("offline", reason="stopped"), EVENT_QOS, True
                        )
            except aiomqtt.MqttError as exc:
                self._on_error(exc, connected_now)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # a bug here must not take the bench down: log it and retry
                log.exception("telemetry publisher failed; retrying")
                self._on_error(exc, connected_now)
            finally:
                self._on_disconnected()
            if self._stopping:
                return
            await asyncio.sleep(delay)
            delay = min(delay * 2.0, cfg.reconnect_max_s)

    def _on_connected(self, is_reconnect: bool) -> None:
        self.stats.connected = True
        if is_reconnect:
            self.stats.reconnects += 1
        log.info("telemetry: connected to %s as %s", self.config.url, self._client_id)

    def _on_error(self, exc: BaseException, was_connected: bool) -> None:
        self.stats.last_error = f"{type(exc).__name__}: {exc}"
        if was_connected:
            log.warning("telemetry: lost the broker %s (%s); reconnecting", self.config.url, exc)
        else:
            log.debug("telemetry: cannot connect to %s (%s)", self.config.url, exc)

    def _on_disconnected(self) -> None:
        self.stats.connected = False
        if self._telemetry:  # stale by the time we are back: drop them (counted); events stay queued
            self.stats.dropped += len(self._telemetry)
            self._telemetry.clear()

    async def _connected_session(self, client: aiomqtt.Client) -> None:
        """Announce, then publish until the connection drops (MqttError) or stop() drains the queues."""
        await client.publish(self.topic_status, self._status_payload("online"), EVENT_QOS, True)
        await client.publish(self.topic_meta, self._meta_payload(), EVENT_QOS, True)
        self._meta_dirty = False
        if self._state_payload is not None:  # the broker may have restarted and lost the retained state
            self._state_dirty = False
            await client.publish(self.topic_state, self._state_payload, EVENT_QOS, True)
            self.stats.published += 1  # counted as the pump counts it: a state set while connecting goes out here
        loop = asyncio.get_running_loop()
        pump = loop.create_task(self._pump(client), name=f"{self.TASK_NAME}-pump")
        watchdog = loop.create_task(self._wait_lost(client), name=f"{self.TASK_NAME}-watchdog")
        try:
            done, _ = await asyncio.wait({pump, watchdog}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in (pump, watchdog):
                t.cancel()
            await asyncio.gather(pump, watchdog, return_exceptions=True)
        for t in done:
            t.result()  # re-raises the MqttError that ended the connection

    @staticmethod
    async def _wait_lost(client: aiomqtt.Client) -> None:
        """Raises MqttError as soon as the connection drops, even while nothing is being published."""
        async for _ in client.messages:  # we subscribe to nothing: this only ends on a disconnection
            pass

    async def _pump(self, client: aiomqtt.Client) -> None:
        stats, qos = self.stats, self.config.qos
        telemetry, events = self._telemetry, self._events
        fast = _paho_of(client) if qos == 0 else None
        backlog: deque[paho.MQTTMessageInfo] = deque()  # fast path: handed to paho, not yet on the socket
        while True:
            if self._state_dirty and self._state_payload is not None:
                self._state_dirty = False
                await client.publish(self.topic_state, self._state_payload, EVENT_QOS, True)
                stats.published += 1
            elif self._meta_dirty:
                self._meta_dirty = False
                await client.publish(self.topic_meta, self._meta_payload(), EVENT_QOS, True)
            elif events:
                await client.publish(self.topic_events, events[0], EVENT_QOS, False)
                events.popleft()  # only once sent: an event in flight when the link drops is sent again
                stats.published += 1
            elif telemetry:
                if fast is not None:
                    self._publish_telemetry_now(fast, backlog)
                    if telemetry:
                        await asyncio.sleep(0)  # a backlog goes out in bursts, letting the loop run between
                    continue
                payload = self._telemetry_payload(*telemetry.popleft())
                if payload is None:
                    continue
                try:
                    await client.publish(self.topic_telemetry, payload, qos, False)
                except BaseException:
                    stats.dropped += 1
                    raise
                stats.published += 1
            elif self._stopping:
                return
            else:
                self._wake.clear()
                await self._wake.wait()

    def _describe(self, data: dict[str, Any]) -> None:
        """Units of channels seen for the first time: from the log schema unless given; meta again if any."""
        known: Mapping[str, str] = {}
        if any(isinstance(n, str) and n not in self._units for n in ("t_s", *data)):  # the session gives them all
            try:
                known = schema_units()
            except Exception as exc:  # the units are a convenience: telemetry goes on without them
                self.stats.last_error = f"units from the log schema: {type(exc).__name__}: {exc}"
        for name in ("t_s", *data):
            if name in self._described:
                continue
            self._described.add(name)
            unit = known.get(name) if isinstance(name, str) else None
            if unit is not None and name not in self._units:
                self._units[name] = unit
                self._meta_dirty = True
        if self._meta_dirty and not self._wake.is_set():
            self._wake.set()

    def _telemetry_payload(self, t_s: float, data: dict[str, Any]) -> str | None:
        if not self._described.issuperset(data):  # a new channel (the first sample, a slow channel's start)
            self._describe(data)
        body: dict[str, Any] = {"t_s": t_s}
        body.update(data)
        try:
            return dumps(body)
        except Exception as exc:  # e.g. a non-string channel name: count it, keep the connection
            self.stats.dropped += 1
            self.stats.last_error = f"telemetry payload: {type(exc).__name__}: {exc}"
            return None

    def _publish_telemetry_now(self, pc: paho.Client, backlog: deque[paho.MQTTMessageInfo]) -> None:
        """QoS 0 fast path: hand up to a burst of samples to paho without awaiting each one.

        aiomqtt's awaitable publish() costs an Event, a wait_for task and three extra loop
        callbacks per message only to learn that a QoS 0 packet reached the socket. Here the
        packet is queued in paho (aiomqtt's socket callbacks still do the writing) and paho's
        MQTTMessageInfo tells what is still unwritten, which keeps paho's own queue bounded.
        """
        telemetry, stats, limit = self._telemetry, self.stats, self.config.queue_size
        while backlog and backlog[0].is_published():
            backlog.popleft()
        for _ in range(min(len(telemetry), _BURST)):
            t_s, data = telemetry.popleft()
            if len(backlog) >= limit:  # the socket is not draining: drop the newest, counted
                stats.dropped += 1
                continue
            payload = self._telemetry_payload(t_s, data)
            if payload is None:
                continue
            info = pc.publish(self.topic_telemetry, payload, 0, False)
            if info.rc != paho.MQTT_ERR_SUCCESS:
                stats.dropped += 1
                raise aiomqtt.MqttCodeError(info.rc, "Could not publish message")
            backlog.append(info)
            stats.published += 1


class TelemetryProcess(Telemetry):
    """A Telemetry whose MQTT client runs in a child process: what the bench session uses.

    The decimation and the snapshot of a due sample happen here, in the loop's thread, as in
    :class:`Telemetry`; the JSON encoding, paho, aiomqtt, the socket and the reconnections run in
    a child process (a plain :class:`Telemetry` there). The loop's share of a published sample is
    one pickle of ~10 floats and one non-blocking write to a pipe (a few us); in the loop's own
    thread, a publish cost ~0.4 ms of event-loop time and delayed one cycle in twenty
    (docs/performance.md). Nothing blocks: a message the pipe cannot take at once (the child is
    behind) is dropped and counted; ``stats`` is the child's, reported a few times a second and at
    stop, plus the drops counted here. If the bench dies the child sees EOF, publishes the
    retained ``offline`` status and exits (the broker's last will covers a lost child).
    """

    STATS_PERIOD_S: ClassVar[float] = 0.25

    def __init__(self, config: MqttConfig, session_id: str, *, units: Mapping[str, str] | None = None) -> None:
        super().__init__(config, session_id, units=units)
        self._proc: subprocess.Popen[bytes] | None = None
        self._wfd = self._rfd = -1
        self._frames = ipc.FrameBuffer()
        self._child_dropped = 0  # the child's own count, last reported
        self._final: asyncio.Future[None] | None = None
        self._pending: list[Any] = []  # events and state before start(), sent by start()
        self._first_report: asyncio.Future[None] | None = None

    @property
    def pid(self) -> int | None:
        """The publishing child process (None before start())."""
        return self._proc.pid if self._proc is not None else None

    async def start(self) -> None:
        """Start the child process (it connects, and reconnects, on its own); returns at once."""
        if self._proc is not None:
            return
        self._proc = ipc.spawn_helper(ipc.helper_argv("hil.telemetry._publisher:_child_main"))
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._wfd, self._rfd = self._proc.stdin.fileno(), self._proc.stdout.fileno()
        ipc.send(self._wfd, ("open", self.config.model_dump(), self.session_id, self._units, self._client_id))
        os.set_blocking(self._wfd, False)
        os.set_blocking(self._rfd, False)
        loop = asyncio.get_running_loop()
        self._final = loop.create_future()
        self._first_report = loop.create_future()
        loop.add_reader(self._rfd, self._on_child_output)
        pending, self._pending = self._pending, []
        for msg in pending:
            self._post(msg)
        # the child reports after its first connection attempt (~0.5 s: it imports aiomqtt first)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(self._first_report), FIRST_REPORT_TIMEOUT_S)

    def _on_child_output(self) -> None:
        messages = self._frames.read(self._rfd)
        if messages is None:  # the child is gone
            asyncio.get_running_loop().remove_reader(self._rfd)
            self.stats.connected = False
            _settle(self._first_report)
            _settle(self._final)
            return
        for kind, child in messages:
            _settle(self._first_report)
            self.stats.published = child["published"]
            self.stats.reconnects = child["reconnects"]
            self.stats.connected = child["connected"]
            self.stats.last_error = child["last_error"] or self.stats.last_error
            self.stats.dropped += child["dropped"] - self._child_dropped
            self._child_dropped = child["dropped"]
            if kind == "final":
                _settle(self._final)

    def _post(self, msg: Any) -> bool:
        """One message to the child, now or never (counted as dropped)."""
        if self._wfd < 0:
            if self._proc is None and msg[0] != "sample" and len(self._pending) < self.config.queue_size:
                self._pending.append(msg)  # not started yet: kept, as Telemetry keeps events
                return True
            self.stats.dropped += 1
            return False
        data = ipc.frame(msg)
        try:
            if len(data) > ipc.ATOMIC_BYTES:  # could be written in part: it would break the framing
                raise ValueError(f"message of {len(data)} bytes")
            os.write(self._wfd, data)
        except (OSError, ValueError) as exc:  # BlockingIOError: the child is behind
            self.stats.dropped += 1
            if not isinstance(exc, BlockingIOError):
                self.stats.last_error = f"telemetry child: {type(exc).__name__}: {exc}"
            return False
        return True

    def _enqueue_sample(self, t_s: float, data: dict[str, float]) -> None:
        self._post(("sample", t_s, data))

    def _push_event(self, payload: str, kind: str) -> None:
        self._post(("event", payload, kind))

    def _set_state_payload(self, payload: str) -> None:
        self._state_payload = payload
        self._post(("state", payload))

    def set_units(self, units: Mapping[str, str]) -> None:
        self._units.update(units)
        self._post(("units", dict(units)))

    async def stop(self) -> None:
        """The child publishes the retained offline status and disconnects; returns within ~2 s."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        self._post(("stop",))
        if self._final is not None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._final), STOP_TIMEOUT_S + 0.5)
        with contextlib.suppress(Exception):
            asyncio.get_running_loop().remove_reader(self._rfd)
        for f in (proc.stdin, proc.stdout):
            if f is not None:
                f.close()
        self._wfd = self._rfd = -1
        try:
            await asyncio.to_thread(proc.wait, 2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            await asyncio.to_thread(proc.wait)
        self.stats.connected = False


def _settle(future: asyncio.Future[None] | None) -> None:
    if future is not None and not future.done():
        future.set_result(None)


def _child_main() -> None:
    """The telemetry child: messages in on stdin, stats out on the original stdout."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the process group: the bench stops us
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # we stop at EOF on stdin, after the offline status
    with contextlib.suppress(OSError):
        os.nice(_CHILD_NICE)
    out_fd = os.dup(1)
    os.dup2(2, 1)  # a stray print must not corrupt the stats
    msg = ipc.recv(0)
    if msg is None or msg[0] != "open":
        return
    _, config, session_id, units, client_id = msg
    asyncio.run(_child_run(MqttConfig.model_validate(config), session_id, units, client_id, out_fd))


async def _child_run(config: MqttConfig, session_id: str, units: dict[str, str], client_id: str,
                     out_fd: int) -> None:
    tm = Telemetry(config, session_id, units=units)
    tm._client_id = client_id  # the name the bench reported
    loop = asyncio.get_running_loop()
    done = loop.create_future()
    frames = ipc.FrameBuffer()

    def on_input() -> None:
        messages = frames.read(0)
        if messages is None:  # the bench is gone
            _settle(done)
            return
        for m in messages:
            kind = m[0]
            if kind == "sample":
                tm._sample_due(m[1], m[2])
            elif kind == "event":
                tm._push_event(m[1], m[2])
            elif kind == "state":
                tm._set_state_payload(m[1])
            elif kind == "units":
                tm.set_units(m[1])
            elif kind == "stop":
                _settle(done)

    def report(kind: str) -> None:
        with contextlib.suppress(OSError):
            ipc.send(out_fd, (kind, dataclasses.asdict(tm.stats)))

    on_connected, on_disconnected, on_error = tm._on_connected, tm._on_disconnected, tm._on_error

    def error(exc: BaseException, was_connected: bool) -> None:
        on_error(exc, was_connected)
        report("stats")

    def connected(is_reconnect: bool) -> None:  # tell the bench at once: it only sends samples while connected
        on_connected(is_reconnect)
        report("stats")

    def disconnected() -> None:
        on_disconnected()
        report("stats")

    tm._on_connected, tm._on_disconnected, tm._on_error = connected, disconnected, error  # type: ignore[method-assign]
    loop.set_exception_handler(_child_loop_error)
    os.set_blocking(0, False)
    await tm.start()
    # without units from the session, the schema's import (~0.1 s, numpy) overlaps the first connection
    warm = loop.run_in_executor(None, schema_units) if not units else None
    loop.add_reader(0, on_input)
    try:
        while not done.done():
            await asyncio.wait({done}, timeout=TelemetryProcess.STATS_PERIOD_S)
            report("stats")
    finally:
        loop.remove_reader(0)
        await tm.stop()
        report("final")
        if warm is not None:
            with contextlib.suppress(Exception):
                await warm


def _child_loop_error(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
    """The child's loop errors: aiomqtt registering the socket writer of a connection the broker has just dropped
    (``add_writer``, EBADF) is part of the lost broker the publisher reports in one warning, so DEBUG only; any
    other error as asyncio reports it."""
    exc = context.get("exception")
    if isinstance(exc, OSError) and exc.errno == errno.EBADF and "add_writer" in str(context.get("message", "")):
        log.debug("telemetry: %s: %r", context.get("message"), exc)
        return
    loop.default_exception_handler(context)


def _paho_of(client: aiomqtt.Client) -> paho.Client | None:
    """The paho client inside an aiomqtt Client (a private attribute: None if a release renames it)."""
    pc = getattr(client, "_client", None)
    return pc if isinstance(pc, paho.Client) else None


# --- hil watch --------------------------------------------------------------------------------
