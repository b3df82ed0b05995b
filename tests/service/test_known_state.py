"""Every item starts from the boards' rest state, measured (docs/service.md, "Between items"): the item after an
abort or a fault waits for the hexapod's stop ramp instead of being refused by it, and the status says what the
boards reported, not what they should be."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from hil.log import read_log
from hil.service._worker import Outbox, Worker
from tests.factories import short_session
from tests.service.conftest import Service, wait_for


@pytest.mark.slow
def test_the_item_after_an_abort_waits_for_the_stop_ramp_and_runs(service: Service, tmp_path: Path) -> None:
    bench = service.bench(user="kim")
    rest = bench.status()["worker"]["rest"]
    assert rest["ok"] is True and rest["boards"] == {"servo": "stream idle", "driver": "disabled",
                                                     "hexapod": "IDLE at home"}
    swinging = bench.add(short_session(tmp_path, 30.0, name="swinging"))
    wait_for(lambda: bench.item(swinging["uid"]).get("cycles", 0) > 2000, timeout_s=180)  # the table well off home
    bench.abort("test: the next item at once")
    bench.start()  # at once: the hexapod is still ramping home
    after = bench.run(short_session(tmp_path, 1.0, name="after"), out=tmp_path / "out")
    assert after.status == "completed", after.message  # it used to end "PROFILE_LOAD refused: BAD_STATE"
    aborted = bench.item(swinging["uid"])
    assert aborted["status"] == "aborted"
    started = bench.history(2)
    assert [r["name"] for r in started] == ["after", "swinging"]
    assert started[0]["started_at"] > started[1]["ended_at"]
    status = wait_for(lambda: (s := bench.status())["worker"]["rest"] and s, timeout_s=60)  # measured after it
    rest = status["worker"]["rest"]
    assert rest["ok"] is True and rest["boards"] == {"servo": "stream idle", "driver": "disabled",
                                                     "hexapod": "LOADED at home"}  # its profile still loaded
    assert status["worker"]["safe"] == rest["summary"]


class _Lines:
    """The worker's outbox stream, kept as parsed lines."""

    def __init__(self) -> None:
        self.lines: list[dict[str, object]] = []

    def write(self, text: str) -> None:
        self.lines.extend(json.loads(line) for line in text.splitlines() if line)

    def flush(self) -> None:
        pass


@pytest.mark.parametrize("how", ["stop", "abort"])
def test_an_end_asked_while_the_item_waits_for_the_boards_is_kept_and_nothing_runs(tmp_path: Path,
                                                                                  how: str) -> None:
    """A stop or an abort that reaches the worker after the item did but before its boards were at rest (the rest
    check of the item before still running) ends the item there: it used to be dropped, and the item ran whole."""
    stream = _Lines()
    outbox = Outbox(stream)
    worker = Worker(state_dir=tmp_path, loopback=True, lab_session=None, emulator=None, seed=0, outbox=outbox)
    sessions_run: list[str] = []
    worker._run_session = lambda running, *args: sessions_run.append(running.uid) or {}  # type: ignore[method-assign]

    async def scenario() -> None:
        at_rest = asyncio.Event()

        async def check_rest(timeout_s: float = 0.0) -> dict[str, object]:
            await at_rest.wait()
            return {"ok": True, "boards": {}, "summary": "at rest", "at": 0.0}

        worker.check_rest = check_rest  # type: ignore[method-assign]
        path = short_session(tmp_path, 1.0, name="waits")
        worker.run({"uid": "u1", "kind": "session", "file_name": path.name, "body": path.read_text()})
        await asyncio.sleep(0.05)  # the item waits for the boards
        worker.end(how, f"{how} by kim: changed my mind")
        at_rest.set()
        assert worker.item_task is not None
        await worker.item_task

    asyncio.run(scenario())
    outbox.close()
    done = [line for line in stream.lines if line["ev"] == "done"]
    assert sessions_run == [] and [line["ev"] for line in stream.lines].count("started") == 0
    assert len(done) == 1 and done[0]["status"] == ("stopped" if how == "stop" else "aborted"), done
    assert done[0]["exit_code"] == (3 if how == "stop" else 130)
    assert "changed my mind" in str(done[0]["message"]) and "nothing was armed" in str(done[0]["message"])


def _last_el_deg(log: Path) -> float:
    return float(read_log(log).groups["loop"]["el_deg"][-1])


@pytest.mark.slow
def test_a_tracked_session_after_an_ident_starts_from_its_start_pose_and_tracks(service: Service,
                                                                               tmp_path: Path) -> None:
    """The ident's sweep turns the elevation well away from the target (27 deg by default) and leaves it there; the
    next item, a tracked session, used to start there and track 0 frames, recorded completed. Its start pose phase
    now brings the gimbal back to the pose first (logged as a phase), and it tracks."""
    bench = service.bench(user="kim")
    ident, _ = bench.run_item(short_session(tmp_path, 2.0, name="ident"), out=tmp_path / "ident", kind="ident",
                              options={"sweep_s": 4.0, "f_start_hz": 2.0, "f_stop_hz": 40.0, "level": False})
    assert ident.log_path is not None, ident.message
    passes = sorted((tmp_path / "ident").glob("*.h5"), key=lambda p: read_log(p).attrs.get("start_time_utc", ""))
    left_el_deg = _last_el_deg(passes[-1])  # where its one sweep (4 s at a 3 deg/s offset) left it
    assert abs(left_el_deg) > 5.0, left_el_deg  # far outside the camera's field (+-1.0 deg in elevation)
    tracked = bench.run(short_session(tmp_path, 3.0, name="tracked"), out=tmp_path / "tracked")
    assert tracked.status == "completed" and tracked.exit_code == 0, tracked.message
    summary = tracked.summary()
    pose = summary["start_pose"]
    assert pose["outcome"] == "reached" and abs(pose["from_el_deg"] - left_el_deg) < 1.0, (pose, left_el_deg)
    assert pose["error_deg"] <= 0.05
    assert summary["frames_valid"] > 0.9 * 3.0 * 100 * (1 - 1.0 / 3.0), summary  # 100 Hz, after the 1 s settle
