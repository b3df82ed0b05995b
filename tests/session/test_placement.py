"""CPU placement (hil.session._host, host.loop_cpu, emulator.cpu): the loop and what it ping-pongs with share a CPU,
the helpers are kept off it, and the thread is given back when the session ends."""

from __future__ import annotations

import json
import os

import pytest

from hil.log import read_log
from hil.session import EmulatorProcess, Session
from hil.session import _host as host
from tests.factories import run_session, session_config
from tests.session.helpers import wait_cycles


def test_resolve_cpu_indexes_the_allowed_cpus_like_a_python_list() -> None:
    assert host.resolve_cpu(-1, [0, 2, 5]) == 5
    assert host.resolve_cpu(0, [0, 2, 5]) == 0
    assert host.resolve_cpu(-3, [0, 2, 5]) == 0
    with pytest.raises(ValueError, match=r"no CPU index 3: this process may use CPUs \[0, 2, 5\]"):
        host.resolve_cpu(3, [0, 2, 5])
    with pytest.raises(ValueError, match="nothing to keep the helpers off"):
        host.resolve_cpu(-1, [3])


def test_emulator_process_args_carry_the_cpu_only_when_set() -> None:
    cfg = session_config()
    assert cfg.emulator.process_args() == ["--rt-priority", "0"]
    cfg = session_config(emulator={"cpu": -1})
    assert cfg.emulator.process_args() == ["--rt-priority", "0", "--cpu", "-1"]


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="placement needs two CPUs")
def test_session_pins_loop_and_emulator_together_and_helpers_elsewhere(tmp_path) -> None:
    cpus = sorted(os.sched_getaffinity(0))
    before = os.sched_getaffinity(0)
    seen: dict[str, set[int]] = {}

    async def look(emulator: EmulatorProcess, session: Session) -> None:
        await wait_cycles(session, 200)
        assert emulator.proc is not None and session.log is not None
        seen["loop"] = os.sched_getaffinity(0)  # this thread runs the event loop, i.e. the 1 kHz loop
        seen["emulator"] = os.sched_getaffinity(emulator.proc.pid)
        seen["writer"] = os.sched_getaffinity(session.log.writer_pid)

    run = run_session(session_config(duration_s=1.0, host={"loop_cpu": -1}, emulator={"cpu": -1}), tmp_path,
                      during=look)
    assert run.result.status == "completed", run.result.message
    last = cpus[-1]
    assert seen == {"loop": {last}, "emulator": {last}, "writer": set(cpus) - {last}}
    assert os.sched_getaffinity(0) == before  # given back: the test process goes on unpinned
    events = read_log(run.result.log_path).groups["events"]
    info = [json.loads(d) for k, d in zip(events["kind"], events["detail"], strict=True) if str(k) == "info"]
    placed = [d for d in info if "loop_cpu" in d]
    assert placed and placed[0]["loop_cpu"] == last and placed[0]["helper_cpus"] == cpus[:-1]


def test_a_cpu_that_does_not_exist_is_logged_and_the_session_runs_unpinned(tmp_path) -> None:
    before = os.sched_getaffinity(0)
    run = run_session(session_config(duration_s=0.5, host={"loop_cpu": 1000}), tmp_path)
    assert run.result.status == "completed", run.result.message
    assert os.sched_getaffinity(0) == before
    events = read_log(run.result.log_path).groups["events"]
    details = [str(d) for k, d in zip(events["kind"], events["detail"], strict=True) if str(k) == "info"]
    assert any("host.loop_cpu 1000 not applied" in d and "no CPU index 1000" in d for d in details), details
