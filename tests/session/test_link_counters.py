"""Link counters and missed cycles, from the decoders to the log to `hil report`."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from hil.analysis import summarize_log
from hil.log import SCHEMA, SessionLog, read_log
from hil.log.schema import LINK_COUNTERS, Group, group_by_name
from hil.protocol import Board, Decoder, DriveStatus, Encoder, GyroSample
from hil.session import ControlLoop
from tests.factories import run_session, session_config

G = group_by_name(SCHEMA)
ATTRS = {"config": {}, "ident": {}, "seed": 0}


class Rows:
    """Stands in for the session log: keeps the rows appended per group."""

    def __init__(self) -> None:
        self.rows: dict[str, list[list[Any]]] = {}

    def append(self, group: str, row: Any) -> None:
        self.rows.setdefault(group, []).append(list(row))


def gyro(tick: int) -> GyroSample:
    return GyroSample(tick * 1000, tick, 0.0, 0.0, 0.0, 0.0, 0.0)


def test_log_links_writes_every_counter_of_every_link() -> None:
    servo = Decoder.for_link(Board.SERVO)
    enc = Encoder(Board.SERVO)
    frames = [enc.encode(gyro(k), Board.HOST) for k in range(6)]
    stray = Encoder(Board.DRIVER).encode(DriveStatus(0, 0, 0, 0, 0, 0, 0), Board.HOST)
    wrong = enc.encode(DriveStatus(0, 0, 0, 0, 0, 0, 0), Board.HOST)  # seq 6, on the wrong link
    # 0 1 1 (duplicate) 3 (gap of 1) 2 (reordered) 4, a stray driver frame, 5, then the board resets: 0
    servo.feed(b"".join([frames[0], frames[1], frames[1], frames[3], frames[2], frames[4], stray, frames[5], wrong,
                         Encoder(Board.SERVO).encode(gyro(0), Board.HOST)]))
    log = Rows()
    fake_loop = SimpleNamespace(decoders={"servo": servo}, log=log)
    ControlLoop._log_links(fake_loop, 123)  # type: ignore[arg-type]
    (row,) = log.rows["links"]
    names = [c.name for c in G["links"].channels]
    assert len(row) == len(names) == 1 + 4 * len(LINK_COUNTERS)
    got = dict(zip(names, row, strict=True))
    assert got["t_host_ns"] == 123
    assert {n: got[f"servo_{n}"] for n in LINK_COUNTERS} == {
        "frames_ok": 8, "crc_errors": 0, "bad_frames": 0, "bytes_discarded": 0, "frames_lost": 1,
        "duplicates": 1, "reordered": 1, "restarts": 1, "rejected": 2}
    assert all(got[f"{link}_{n}"] == 0 for link in ("driver", "image", "hexapod") for n in LINK_COUNTERS)


def test_a_gap_of_1000_ticks_is_logged_whole() -> None:
    log = Rows()
    loop = ControlLoop(session_config(), lambda tick, az, el: None, log=log, telemetry=None,  # type: ignore[arg-type]
                       duration_ticks=10**6, on_done=lambda: None)
    for tick in (7, 8, 1009, 1010):
        loop.on_sample(gyro(tick))
    gap_column = [c.name for c in G["loop"].channels].index("tick_gap")
    assert [r[gap_column] for r in log.rows["loop"]] == [0, 0, 1000, 0]
    assert loop.stats.missed == 1000


def write_log(path: Path, ticks: np.ndarray, gaps: np.ndarray, schema: tuple[Group, ...] = SCHEMA,
              links: dict[str, int] | None = None) -> None:
    loop_names = [c.name for c in G["loop"].channels]
    with SessionLog(path, attrs=ATTRS, schema=schema) as log:
        for tick, gap in zip(ticks, gaps, strict=True):
            row = dict.fromkeys(loop_names, 0)
            row.update(tick=int(tick), t_s=tick / 1000, t_host_ns=1 + int(tick), tick_gap=int(gap))
            log.append("loop", list(row.values()))
        if links is not None:
            row = dict.fromkeys((c.name for c in G["links"].channels), 0)
            log.append("links", list({**row, "t_host_ns": 1, **links}.values()))


def ticks_with_a_gap(gap: int) -> tuple[np.ndarray, np.ndarray]:
    ticks = np.concatenate([np.arange(0, 100), np.arange(100 + gap, 200 + gap)])
    return ticks, np.diff(ticks, prepend=0) - 1 * (np.arange(ticks.size) > 0)


def test_report_counts_a_gap_of_1000_ticks_as_1000_missed_cycles(tmp_path: Path) -> None:
    ticks, gaps = ticks_with_a_gap(1000)
    assert gaps.sum() == 1000
    write_log(tmp_path / "wide.h5", ticks, gaps)
    assert summarize_log(tmp_path / "wide.h5")["missed_cycles"] == 1000


def test_report_reads_the_true_gap_from_an_older_log_that_capped_it_at_255(tmp_path: Path) -> None:
    loop = G["loop"]
    narrow = tuple(c._replace(dtype="u1") if c.name == "tick_gap" else c for c in loop.channels)
    schema = tuple(g._replace(channels=narrow) if g.name == "loop" else g for g in SCHEMA)
    ticks, gaps = ticks_with_a_gap(1000)
    gaps = np.minimum(gaps, 255)
    gaps[150] = 3  # a gap below 255 is taken from the column as it is, not from the ticks
    write_log(tmp_path / "old.h5", ticks, gaps, schema=schema)
    assert read_log(tmp_path / "old.h5").groups["loop"]["tick_gap"].dtype == np.uint8
    assert summarize_log(tmp_path / "old.h5")["missed_cycles"] == 1000 + 3


def test_report_link_errors_count_losses_and_refusals_not_resends(tmp_path: Path) -> None:
    links = {"servo_crc_errors": 2, "servo_bad_frames": 3, "servo_frames_lost": 5, "servo_reordered": 7,
             "servo_rejected": 11, "servo_duplicates": 100, "servo_restarts": 1000, "servo_bytes_discarded": 99,
             "driver_frames_lost": 1}
    ticks, gaps = ticks_with_a_gap(0)
    write_log(tmp_path / "links.h5", ticks, gaps, links=links)
    assert summarize_log(tmp_path / "links.h5")["link_errors"] == {"servo": 28, "driver": 1, "image": 0, "hexapod": 0}


def test_a_clean_emulated_session_logs_zero_in_every_error_counter(tmp_path: Path) -> None:
    """The emulator's traffic is what each link is declared to carry: nothing refused, nothing lost."""
    run = run_session(session_config(duration_s=0.5, seed=4), tmp_path)
    assert run.result.status == "completed", run.result.message
    links = read_log(run.result.log_path).groups["links"]
    for link in ("servo", "driver", "image", "hexapod"):
        last = {n: int(links[f"{link}_{n}"][-1]) for n in LINK_COUNTERS}
        assert last["frames_ok"] > 10, (link, last)
        assert {n: v for n, v in last.items() if n != "frames_ok"} == dict.fromkeys(LINK_COUNTERS[1:], 0), link
    assert summarize_log(run.result.log_path)["link_errors"] == {"servo": 0, "driver": 0, "image": 0, "hexapod": 0}

