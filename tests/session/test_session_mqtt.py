"""Sessions with live telemetry against a real MQTT broker that the test starts on a free port."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path

import aiomqtt
import pytest

from hil.telemetry import MqttConfig
from tests.factories import run_session, session_config
from tests.session.helpers import wait_cycles
from tests.telemetry.broker import MqttBroker


class Subscriber:
    """Collects every message under hil/# in a background thread with its own event loop."""

    def __init__(self, broker: MqttBroker) -> None:
        self.broker = broker
        self.messages: list[tuple[str, dict]] = []  # type: ignore[type-arg]
        self.ready = threading.Event()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self.thread.start()
        assert self.ready.wait(10), "subscriber did not connect"

    async def _run(self) -> None:
        try:
            async with aiomqtt.Client(self.broker.host, self.broker.port) as client:
                await client.subscribe("hil/#", qos=1)
                self.ready.set()
                async for msg in client.messages:
                    self.messages.append((str(msg.topic), json.loads(msg.payload)))
                    if self.stop.is_set():
                        return
        except aiomqtt.MqttError:  # the broker went away (a later test kills it): we are done
            return

    def topics(self, suffix: str) -> list[dict]:  # type: ignore[type-arg]
        return [p for t, p in self.messages if t.endswith(suffix)]


def mqtt_session(broker: MqttBroker, duration_s: float):  # type: ignore[no-untyped-def]
    mqtt = MqttConfig(host=broker.host, port=broker.port, bench_id="testbench", telemetry_hz=50)
    return session_config(duration_s=duration_s, mqtt=mqtt.model_dump())


@pytest.mark.slow
def test_session_publishes_telemetry_state_and_status(mqtt_broker: MqttBroker, tmp_path: Path) -> None:
    sub = Subscriber(mqtt_broker)
    run = run_session(mqtt_session(mqtt_broker, 3.0), tmp_path)
    time.sleep(0.3)
    sub.stop.set()
    assert run.result.status == "completed", run.result.message
    telemetry = sub.topics("/telemetry")
    assert 0.8 * 150 <= len(telemetry) <= 1.2 * 150 + 60  # 50 Hz over 3 s (+ the wind-down)
    assert {"gyro_y_dps", "drive_el_counts", "t_s"} <= set(telemetry[10])
    assert all(abs(m["gyro_y_dps"]) < 10 for m in telemetry)
    states = [m.get("state") for m in sub.topics("/state")]
    assert "running" in states and states[-1] == "stopped"
    status = sub.topics("hil/testbench/status")
    assert status[-1]["status"] == "offline"
    kinds = [m["kind"] for m in sub.topics("/events")]
    assert "summary" in kinds


def test_broker_killed_mid_session_the_session_completes(mqtt_broker: MqttBroker, tmp_path: Path) -> None:
    async def kill_broker(emu, session) -> None:  # type: ignore[no-untyped-def]
        await wait_cycles(session, 800)
        await asyncio.to_thread(mqtt_broker.kill)

    try:
        run = run_session(mqtt_session(mqtt_broker, 3.0), tmp_path, during=kill_broker)
    finally:
        mqtt_broker.restart()
    assert run.result.status == "completed", run.result.message
    assert run.result.stats.cycles >= 3000 and run.result.stats.faults == []
    assert run.telemetry["dropped"] > 50  # ~2 s of board time at 50 Hz with no broker
    assert run.telemetry["published"] > 10
