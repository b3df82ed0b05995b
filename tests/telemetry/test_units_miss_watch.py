"""Channel units from the log schema, the miss distance channel, the watch sparkline, and where watch's errors go."""

from __future__ import annotations

import asyncio
import io
import json
import math
import time

import pytest
from rich.console import Console

from hil.log.schema import group_by_name
from hil.telemetry import Telemetry, TelemetryProcess, schema_units, sparkline, watch
from tests.telemetry.broker import MqttBroker, free_port
from tests.telemetry.test_telemetry import Subscriber, config, run, until

# --- sparkline (pure) -------------------------------------------------------------------------


def test_sparkline_exact_strings() -> None:
    assert sparkline([0, 1, 2, 3, 4, 5, 6, 7]) == "▁▂▃▄▅▆▇█"  # min..max over the 8 blocks
    assert sparkline([7, 6, 5, 4, 3, 2, 1, 0]) == "█▇▆▅▄▃▂▁"
    assert sparkline([10.0, 20.0, 15.0]) == "▁█▅"  # 15 is 3.5 steps up: rounded to 4
    assert sparkline([-2.0, 2.0, 0.0, 1.0]) == "▁█▅▆"  # 1.0: 5.25 steps -> 5
    assert sparkline([0.25, 0.25, 0.25, 0.25]) == "▁▁▁▁"  # constant: a flat line
    assert sparkline([42.5]) == "▁"
    assert sparkline([]) == ""
    assert sparkline([1.0, None, 3.0, math.nan, "x", 2.0]) == "▁ █  ▅"  # gaps: not numbers, not scaled
    assert sparkline([None, None]) == "  "
    assert sparkline([False, True, True]) == "▁██"  # flags as 0 and 1
    assert sparkline(range(100), 5) == "▁▃▅▆█"  # the last 5 values (95..99), scaled among themselves
    assert sparkline([5, 0, 1], 0) == ""
    assert sparkline([-1e308, 1e308, 0.0]) == "▁█▅"  # a span beyond the float range still scales


# --- units from the log schema ----------------------------------------------------------------


def test_schema_units_are_the_log_schemas() -> None:
    loop, image = group_by_name()["loop"], group_by_name()["image"]
    units = schema_units()
    for channel in (*loop.channels, *image.channels):
        assert units[channel.name] == channel.unit
    assert units["gyro_y_dps"] == "deg/s" and units["drive_el_counts"] == "counts" and units["latency_us"] == "us"
    assert units["miss_x_px"] == "px" and units["miss_y_px"] == "px" and units["t_s"] == "s"


def test_miss_rides_on_due_samples_with_units_for_new_channels() -> None:
    """1 kHz samples decimated to 50 Hz, camera frames at 100 Hz: each due sample carries the latest frame."""

    async def main() -> None:
        tm = Telemetry(config(port=free_port(), telemetry_hz=50), "s-miss", units={"el_deg": "rad", "supply": "V"})
        tm.stats.connected = True  # pretend, to see what would be queued (start() is never called)
        for k in range(200):  # 0.2 s of board time
            if k % 10 == 3:  # frame f = k // 10 arrives 3 ms into its 10 ms
                f = k // 10
                tm.miss(0.5 * f, -0.25 * f, track_valid=f != 15)
            tm.sample(k / 1000, lambda k=k: {"gyro_y_dps": k / 100, "el_deg": 1.0, "supply": 28.0, "odd": 1})
        queued = list(tm._telemetry)
        assert [t for t, _ in queued] == [k / 1000 for k in range(0, 200, 20)]
        assert queued[0][1] == {"gyro_y_dps": 0.0, "el_deg": 1.0, "supply": 28.0, "odd": 1}  # no frame yet
        assert queued[1][1] == {"gyro_y_dps": 0.2, "el_deg": 1.0, "supply": 28.0, "odd": 1,
                                "miss_x_px": 0.5, "miss_y_px": -0.25}  # frame 1 (arrived at k=13)
        assert [(d["miss_x_px"], d["miss_y_px"]) for _, d in queued[2:8]] == [
            (1.5, -0.75), (2.5, -1.25), (3.5, -1.75), (4.5, -2.25), (5.5, -2.75), (6.5, -3.25)]
        t_s, data = queued[8]  # k=160: the latest frame is 15, with no valid target
        assert t_s == 0.16 and math.isnan(data["miss_x_px"]) and math.isnan(data["miss_y_px"])
        assert json.loads(tm._telemetry_payload(t_s, data) or "") == {
            "t_s": 0.16, "gyro_y_dps": 1.6, "el_deg": 1.0, "supply": 28.0, "odd": 1,
            "miss_x_px": None, "miss_y_px": None}
        assert (queued[9][1]["miss_x_px"], queued[9][1]["miss_y_px"]) == (8.5, -4.25)  # frame 17 valid again
        # the publisher looked the new channels up in the log schema; the given units win
        assert json.loads(tm._meta_payload())["units"] == {
            "el_deg": "rad", "supply": "V", "t_s": "s", "gyro_y_dps": "deg/s", "miss_x_px": "px", "miss_y_px": "px"}
        tm.miss("not a number", 1.0)  # never raises: sent as null
        assert tm._miss is not None and math.isnan(tm._miss[0])
        tm.stats.connected = False

    run(main())


def test_bench_publisher_sends_schema_units_and_miss_distance(mqtt_broker: MqttBroker) -> None:
    """TelemetryProcess, what a session uses, given no units: the meta carries the log schema's units of every
    channel it publishes, and each telemetry message the latest miss distance."""

    async def main() -> None:
        with Subscriber(mqtt_broker.port, "hil/rig-units/#") as sub:
            tm = TelemetryProcess(config(mqtt_broker, bench_id="rig-units", telemetry_hz=50), "s-units")
            await tm.start()
            await until(lambda: tm.stats.connected, 10, "the child connected")
            for k in range(300):  # 0.3 s of board time at 1 kHz: 15 due samples
                if k % 10 == 5:
                    tm.miss(1.25 + k / 1000, -2.5)
                tm.sample(k / 1000, lambda k=k: {"gyro_y_dps": 0.5, "drive_el_counts": -120, "latency_us": 85.5})
                await asyncio.sleep(0)

            def units() -> dict[str, str]:
                meta = sub.on("/meta")
                return meta[-1][0]["units"] if meta else {}

            await until(lambda: len(sub.on("/telemetry")) == 15 and "miss_y_px" in units(), 5, "15 samples, units")
            got = [p for p, _, _ in sub.on("/telemetry")]
            await tm.stop()
        assert units() == {"t_s": "s", "gyro_y_dps": "deg/s", "drive_el_counts": "counts", "latency_us": "us",
                           "miss_x_px": "px", "miss_y_px": "px"}
        assert got[0] == {"t_s": 0.0, "gyro_y_dps": 0.5, "drive_el_counts": -120, "latency_us": 85.5}
        assert got[1] == {"t_s": 0.02, "gyro_y_dps": 0.5, "drive_el_counts": -120, "latency_us": 85.5,
                          "miss_x_px": 1.25 + 15 / 1000, "miss_y_px": -2.5}  # the frame of k=15
        assert [m["miss_x_px"] for m in got[2:]] == [1.25 + (20 * i - 5) / 1000 for i in range(2, 15)]

    run(main(), timeout=30)


# --- hil watch --------------------------------------------------------------------------------


def test_watch_shows_units_miss_and_trend(mqtt_broker: MqttBroker) -> None:
    async def main() -> tuple[str, str]:
        cfg = config(mqtt_broker, bench_id="rig-trend")
        tm = Telemetry(cfg, "s-trend")  # no units given: the schema's
        await tm.start()
        await until(lambda: tm.stats.connected, 5, "connected")
        tm.miss(3.5, -1.25)

        async def drive() -> None:
            k = 0
            while True:
                tm.sample(k / 1000, lambda k=k: {"gyro_y_dps": math.sin(2 * math.pi * k / 1000), "latency_us": 80.0})
                k += 1
                await asyncio.sleep(0.001)

        driver = asyncio.create_task(drive())
        console = Console(record=True, width=120, force_terminal=False)
        errors = io.StringIO()
        rc = await watch(cfg, seconds=1.5, console=console, err_console=Console(file=errors, width=120))
        driver.cancel()
        await tm.stop()
        assert rc == 0
        return console.export_text(), errors.getvalue()

    text, errors = run(main())
    assert errors == ""
    rows = {line.split()[1]: line for line in text.splitlines() if line.startswith("│ ") and len(line.split()) > 3}
    assert "deg/s" in rows["gyro_y_dps"] and "us" in rows["latency_us"]
    assert "px" in rows["miss_x_px"] and " 3.5 " in rows["miss_x_px"] and " -1.25 " in rows["miss_y_px"]
    assert "miss x 3.5  y -1.25 px" in text
    trend = rows["gyro_y_dps"].split("│")[4].strip()
    assert len(trend) >= 10 and set(trend) <= set("▁▂▃▄▅▆▇█") and len(set(trend)) > 2  # a sine: varied blocks
    assert rows["latency_us"].split("│")[4].strip() == "▁" * len(trend)  # constant: flat


def test_watch_broker_error_goes_to_err_console_not_stdout() -> None:
    console, errors = Console(record=True, width=120), io.StringIO()
    port = free_port()
    rc = run(watch(config(port=port), seconds=1.0, console=console, err_console=Console(file=errors, width=40)))
    assert rc == 1
    assert console.export_text() == ""
    lines = errors.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: cannot reach the MQTT broker at 127.0.0.1:{port}: "), lines


def test_watch_broker_error_default_is_stderr(capsys: pytest.CaptureFixture[str]) -> None:
    out = io.StringIO()
    port = free_port()
    rc = run(watch(config(port=port), seconds=1.0, console=Console(file=out, width=120)))
    captured = capsys.readouterr()
    assert rc == 1 and out.getvalue() == "" and captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: cannot reach the MQTT broker at 127.0.0.1:{port}: ")


@pytest.mark.parametrize("terminal", [False, True], ids=["recorded", "terminal"])
def test_watch_lost_broker_warns_on_err_console(mqtt_broker: MqttBroker, terminal: bool) -> None:
    """One warning line on err_console when the broker goes; on terminals the live view restarts below it."""

    async def main() -> tuple[str, str]:
        cfg = config(mqtt_broker, bench_id="rig-lost")
        out, errors = io.StringIO(), io.StringIO()
        console = Console(file=out, width=120, force_terminal=terminal)
        err_console = Console(file=errors, width=120, force_terminal=terminal)
        loop = asyncio.get_running_loop()
        loop.call_later(0.5, mqtt_broker.kill)
        t0 = time.monotonic()
        assert await watch(cfg, seconds=1.5, console=console, err_console=err_console) == 0
        assert time.monotonic() - t0 < 3.0
        return out.getvalue(), errors.getvalue()

    try:
        text, errors = run(main())
    finally:
        mqtt_broker.restart()
    lines = errors.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"warning: lost the MQTT broker at 127.0.0.1:{mqtt_broker.port}: ")
    assert lines[0].endswith("; reconnecting")
    assert "warning" not in text and "disconnected" in text
