"""Rate and tracking loops on simulated plants with known answers."""

from __future__ import annotations

import pytest

from hil.control.loops import DAC_MAX_COUNTS, RateLoop, TrackingLoop

H = 1e-3
K_M = 0.023  # deg/s^2 per count, seed 000 eq 38


def simulate_rate_loop(loop: RateLoop, *, rate_cmd_dps, d_counts: float, d_known: bool, seconds: float):
    """Plant d(rate)/dt = k_m (u + d), integrated exactly over each 1 ms hold."""
    rate = 0.0
    history = []
    for k in range(int(seconds / H)):
        u = loop.step(rate_cmd_dps(k * H), rate, d_counts if d_known else 0.0)
        rate += K_M * (u + d_counts) * H
        history.append((rate, u))
    return history


def test_perfect_disturbance_compensation_cancels_a_constant_disturbance_with_p_only():
    loop = RateLoop(kp_counts_per_dps=2000.0, dt_s=H)  # bandwidth 46 rad/s
    hist = simulate_rate_loop(loop, rate_cmd_dps=lambda t: 1.0, d_counts=-500.0, d_known=True, seconds=0.5)
    # the DAC is integer: the loop settles within half a count, |e| <= 0.5 / kp
    assert abs(hist[-1][0] - 1.0) <= 0.5 / 2000.0
    assert hist[-1][1] == 500
    # without compensation a P loop keeps the static error d / kp
    loop = RateLoop(kp_counts_per_dps=2000.0, dt_s=H)
    hist = simulate_rate_loop(loop, rate_cmd_dps=lambda t: 1.0, d_counts=-500.0, d_known=False, seconds=0.5)
    assert hist[-1][0] == pytest.approx(1.0 - 500.0 / 2000.0, abs=2e-3)


def test_integral_action_removes_the_static_error_of_an_unknown_disturbance():
    loop = RateLoop(kp_counts_per_dps=2000.0, ki_counts_per_deg=40000.0, dt_s=H)
    hist = simulate_rate_loop(loop, rate_cmd_dps=lambda t: 1.0, d_counts=-500.0, d_known=False, seconds=2.0)
    assert hist[-1][0] == pytest.approx(1.0, abs=1e-3)


def test_output_is_rounded_and_saturated_to_the_dac_range():
    loop = RateLoop(kp_counts_per_dps=1e6, dt_s=H)
    assert loop.step(10.0, 0.0) == DAC_MAX_COUNTS
    assert loop.step(-10.0, 0.0) == -DAC_MAX_COUNTS
    assert isinstance(loop.step(1e-5, 0.0), int)


def test_anti_windup_keeps_the_integral_bounded_while_saturated():
    loop = RateLoop(kp_counts_per_dps=500.0, ki_counts_per_deg=20000.0, u_max_counts=1000, dt_s=H)
    # an unreachable command: saturated for 2 s
    hist = simulate_rate_loop(loop, rate_cmd_dps=lambda t: 1e3, d_counts=0.0, d_known=True, seconds=2.0)
    assert all(u == 1000 for _, u in hist[100:])
    # saturated from the first sample with the error pushing further: nothing integrated
    # (a free integrator would hold 20000 * 1e3 * 2 s = 4e7 counts here)
    assert loop.integral_counts == 0.0
    frozen = loop.integral_counts
    loop.step(1e3, 0.0)
    assert loop.integral_counts == frozen
    # an error back out of saturation integrates again
    loop.step(-1.0, 0.0)
    assert loop.integral_counts == pytest.approx(frozen - 20.0)


def make_tracker(**kw) -> TrackingLoop:
    return TrackingLoop(kp_per_s=20.0, ki_per_s2=0.0, ifov_deg_per_px=0.01, **kw)


def test_tracking_command_is_held_between_frames_and_dropped_when_stale():
    t = make_tracker(stale_s=0.05)
    t.on_frame(frame=1, miss_px=10.0, track_valid=True, t_exposure_s=0.0, now_s=0.01)
    assert t.rate_cmd_dps(0.011) == pytest.approx(20.0 * 0.1)
    assert t.rate_cmd_dps(0.049) == pytest.approx(2.0)
    assert t.rate_cmd_dps(0.051) == 0.0
    assert t.counters.frames_used == 1


def test_tracking_ignores_late_out_of_order_and_invalid_frames():
    t = make_tracker(stale_s=0.05)
    t.on_frame(frame=5, miss_px=10.0, track_valid=True, t_exposure_s=1.0, now_s=1.01)
    t.on_frame(frame=4, miss_px=-50.0, track_valid=True, t_exposure_s=1.0, now_s=1.02)  # out of order
    t.on_frame(frame=6, miss_px=-50.0, track_valid=True, t_exposure_s=0.9, now_s=1.02)  # 120 ms old: late
    assert t.rate_cmd_dps(1.02) == pytest.approx(2.0)
    t.on_frame(frame=7, miss_px=3.0, track_valid=False, t_exposure_s=1.02, now_s=1.03)
    assert t.rate_cmd_dps(1.03) == 0.0
    c = t.counters
    assert (c.frames_used, c.frames_out_of_order, c.frames_late, c.frames_invalid) == (1, 1, 1, 1)


def test_tracking_closes_the_loop_on_a_fixed_target_with_camera_latency():
    """LOS angle integrates the rate command; camera at 100 Hz with one frame of latency."""
    t = TrackingLoop(kp_per_s=15.0, ki_per_s2=20.0, ifov_deg_per_px=0.01)
    target_deg, los_deg = 0.5, 0.0
    pending = None
    frame = 0
    for k in range(3000):
        now = k * H
        if k % 10 == 0:
            if pending is not None:
                t.on_frame(now_s=now, **pending)
            frame += 1
            pending = {"frame": frame, "miss_px": (target_deg - los_deg) / 0.01, "track_valid": True,
                       "t_exposure_s": now}
        los_deg += t.rate_cmd_dps(now) * H
    assert abs(target_deg - los_deg) / 0.01 < 0.5  # within half a pixel after 3 s
    assert t.counters.frames_used == 299
