"""A session with tracking on that never acquires the target, or loses it for longer than `tracking.max_lost_s`,
ends `lost_target` with exit code 4 and says which, not a bare `completed` (docs/service.md, "Items and their
outcome"); the summary event carries the frames judged."""

from __future__ import annotations

from pathlib import Path

import hil
from hil.session import EXIT_LOST_TARGET, TrackJudge
from tests.factories import session_config
from tests.session.helpers import logged_events


def test_a_target_lost_past_max_lost_s_ends_lost_target(tmp_path: Path) -> None:
    """A 1 px gate (TRACK_CMD): the image board calls the target lost as soon as the swing moves it one pixel."""
    config = session_config(duration_s=3.0, tracking={"gate_px": 1})
    result = hil.run(config, clock="sim", out=tmp_path)
    assert result.status == "lost_target" and result.exit_code == EXIT_LOST_TARGET == 4
    assert result.message.startswith("tracking: the target was lost for ")
    lost_s = float(result.message.split("lost for ")[1].split(" s")[0])
    assert 1.0 < lost_s <= 5.0 and "(tracking.max_lost_s 1)" in result.message  # the wind-down's frames too
    assert result.log_path is not None
    summary = next(detail for kind, detail in logged_events(result.log_path) if kind == "summary")
    assert summary["tracking"]["frames"] > 250 and summary["tracking"]["valid"] < 10
    assert summary["tracking"]["longest_lost_s"] == round(lost_s, 3) or abs(
        summary["tracking"]["longest_lost_s"] - lost_s) < 0.01


def test_the_same_run_allowed_to_lose_it_longer_completes(tmp_path: Path) -> None:
    config = session_config(duration_s=3.0, tracking={"gate_px": 1, "max_lost_s": 60.0})
    result = hil.run(config, clock="sim", out=tmp_path)
    assert result.status == "completed" and result.exit_code == 0


def test_a_shipped_session_tracks_from_its_first_frames(tmp_path: Path) -> None:
    result = hil.run(session_config(duration_s=2.0), clock="sim", out=tmp_path)
    assert result.status == "completed", result.message
    assert result.log_path is not None
    summary = next(detail for kind, detail in logged_events(result.log_path) if kind == "summary")
    assert summary["tracking"]["valid"] == summary["tracking"]["frames"] > 150
    assert summary["tracking"]["longest_lost_s"] == 0.0


def test_the_judge_says_never_acquired_and_lost_apart() -> None:
    never = TrackJudge(max_lost_s=1.0)
    for i in range(1114):
        never.on_frame(i * 0.01, False)
    assert never.verdict() == ("tracking: the target was never acquired (0 of 1114 frames valid): is it in the "
                               "camera's view at the start pose?")
    brief = TrackJudge(max_lost_s=1.0)
    for i in range(300):  # lost for 0.5 s in the middle: allowed
        brief.on_frame(i * 0.01, not 100 <= i < 150)
    assert brief.verdict() is None and brief.longest_lost_s == 0.5
    long = TrackJudge(max_lost_s=1.0)
    for i in range(400):  # lost for 2 s at the end, never regained
        long.on_frame(i * 0.01, i < 200)
    verdict = long.verdict()
    assert verdict is not None and verdict.startswith("tracking: the target was lost for 2.00 s")


def test_frames_while_the_loop_is_disarmed_are_not_judged() -> None:
    """A recovery disarms the loop for a while: the target drifts off with nothing driving the gimbal; the stretch
    is counted anew once the loop is armed again."""
    judge = TrackJudge(max_lost_s=1.0)
    for i in range(600):  # 6 s: valid, 3 s disarmed (lost), then 0.5 s to reacquire, then valid
        t = i * 0.01
        armed = not 200 <= i < 500
        judge.on_frame(t, valid=i < 200 or i >= 550, armed=armed)
    assert judge.verdict() is None and abs(judge.longest_lost_s - 0.49) < 1e-9
    assert judge.frames == 300 and judge.valid == 250
