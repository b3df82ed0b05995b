"""Controller parameters: every one has a documented valid range, derived quantities are checked, and a controller
that validates runs its 1 kHz step without overflow (gains of 1e300 or inf used to raise in every callback)."""

from __future__ import annotations

import math
import random
import re
from pathlib import Path

import annotated_types as at
import pytest

from hil.control.loops import DAC_MAX_COUNTS
from hil.control.registry import REGISTRY, ControllerConfigError, build_controller, controller_params

DOC = Path(__file__).resolve().parents[2] / "docs" / "reliability.md"
NUMERIC = [(name, field) for name, kind in REGISTRY.items() for field, info in kind.params.model_fields.items()
           if info.annotation in (float, int)]


def documented_range(params: type, field: str) -> str:
    """The field's bounds as docs/reliability.md writes them: ``[0, 100000]``, ``(0, 32767]``."""
    lo = hi = None
    for m in params.model_fields[field].metadata:
        if isinstance(m, at.Ge | at.Gt):
            lo = ("[" if isinstance(m, at.Ge) else "(") + f"{getattr(m, 'ge', getattr(m, 'gt', None)):g}"
        if isinstance(m, at.Le | at.Lt):
            hi = f"{getattr(m, 'le', getattr(m, 'lt', None)):g}" + ("]" if isinstance(m, at.Le) else ")")
    assert lo is not None and hi is not None, f"{params.__name__}.{field} has no range"
    return f"{lo}, {hi}"


@pytest.mark.parametrize(("name", "field"), NUMERIC)
def test_every_numeric_parameter_has_a_range_and_the_docs_give_it(name: str, field: str) -> None:
    rng = documented_range(REGISTRY[name].params, field)
    rows = [line for line in DOC.read_text().splitlines() if line.startswith(f"| `{field}` |")]
    assert len(rows) == 1, f"docs/reliability.md: no single row for {field}"
    assert rng in rows[0], (rng, rows[0])


@pytest.mark.parametrize(("name", "field"), [(n, f) for n, f in NUMERIC
                                             if REGISTRY[n].params.model_fields[f].annotation is float])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nan_and_infinities_are_refused_with_the_parameter_named(name: str, field: str, value: float) -> None:
    with pytest.raises(ControllerConfigError, match=rf"^controller '{name}': parameter '{field}': Input should be a "
                                                    r"finite number"):
        controller_params(name, {field: value})


@pytest.mark.parametrize(("name", "params", "message"), [
    ("eso", {"kp_counts_per_dps": 1e300}, "'kp_counts_per_dps': Input should be less than or equal to 100000"),
    ("eso", {"kp_counts_per_dps": 43479.0}, "kp * b0 * dt_s = 1, need < 1"),
    ("eso_kf", {"omega_o_rad_s": 3200.0}, "omega_o * dt_s = 3.2 is above pi"),
    ("eso", {"omega_o_rad_s": 1000.0, "dt_s": 0.005}, "omega_o * dt_s = 5 is above pi"),
    ("pi_lpf", {"ki_counts_per_deg": 8.1e6}, "need ki * dt_s <= kp (8000)"),
    ("pi_lpf", {"kp_counts_per_dps": 0.0}, "need ki * dt_s <= kp (0)"),
    ("pi_lpf", {"cutoff_hz": 500.0, "order": 2}, "cutoff_hz: 500 Hz is not below the Nyquist frequency 500 Hz"),
    ("eso_kf_ukf_ff", {"ukf_dt_s": 0.0105}, "ukf_dt_s: 0.0105 s is not a whole number of dt_s"),
    ("eso_kf_ukf_ff", {"ukf_dt_s": 0.0015, "dt_s": 5e-4}, "not a whole number of the bench's 1 ms tick"),
    ("eso_kf_ukf_ff", {"ff_limit_counts": 1e6}, "less than or equal to 32767"),
    ("eso", {"dt_s": 0.0}, "greater than or equal to 0.0001"),
    ("eso_kf", {"r_dps2": 1e5}, "less than or equal to 10000"),
    ("lqr", {}, "unknown controller 'lqr'"),
    ("eso", {"omega_o": 1.0}, "unknown parameter 'omega_o'"),
])
def test_out_of_range_and_derived_checks(name: str, params: dict[str, float], message: str) -> None:
    with pytest.raises(ControllerConfigError) as exc:
        controller_params(name, params)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_the_edges_of_the_ranges_are_accepted() -> None:
    controller_params("eso_kf", {"omega_o_rad_s": 3141.0})  # omega_o h just below pi
    controller_params("eso", {"kp_counts_per_dps": 43000.0})  # kp b0 h = 0.989
    controller_params("pi_lpf", {"cutoff_hz": 499.0, "order": 2})
    controller_params("pi_lpf", {"ki_counts_per_deg": 8e6})  # ki h = kp
    controller_params("eso_kf_ukf_ff", {"ukf_dt_s": 0.002, "ff_limit_counts": DAC_MAX_COUNTS})


CORNERS = {  # the largest gains each controller accepts
    "pi_lpf": {"kp_counts_per_dps": 1e5, "ki_counts_per_deg": 1e7, "cutoff_hz": 499.0, "order": 2},
    "eso": {"kp_counts_per_dps": 43000.0, "ki_counts_per_deg": 4.3e7 * 1e-3, "omega_o_rad_s": 3141.0,
            "b0_dps2_per_count": 1e-5},
    "eso_nonlinear": {"kp_counts_per_dps": 43000.0, "omega_o_rad_s": 3141.0, "alpha": 1e-3, "delta_dps": 1e-6},
    "eso_kf": {"kp_counts_per_dps": 43000.0, "omega_o_rad_s": 3141.0, "q_dps2": 1e4, "r_dps2": 1e-300},
    "eso_kf_high_gain": {"kp_counts_per_dps": 43000.0, "omega_o_rad_s": 3141.0, "s_dps2": 1e4, "r_dps2": 1e4},
    "eso_kf_ukf_ff": {"kp_counts_per_dps": 43000.0, "omega_o_rad_s": 3141.0, "ff_limit_counts": 32767.0},
}


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_a_controller_at_its_largest_valid_gains_steps_without_overflow(name: str) -> None:
    """Wild gyro input (+-2000 deg/s, and a run stuck at full scale) for 2000 ticks: every drive is an int in the
    DAC's range, every estimate finite."""
    ctrl = build_controller(name, CORNERS[name])
    rnd = random.Random(5)
    for k in range(2000):
        gyro = 2000.0 if 500 <= k < 1000 else rnd.uniform(-2000.0, 2000.0)
        u = ctrl.step(rnd.uniform(-1000.0, 1000.0), gyro, rnd.uniform(-3e4, 3e4))
        assert isinstance(u, int) and -DAC_MAX_COUNTS <= u <= DAC_MAX_COUNTS
        assert math.isfinite(ctrl.rate_fb_dps) and math.isfinite(ctrl.disturbance_counts)


def test_the_range_table_lists_only_real_parameters() -> None:
    fields = {f for kind in REGISTRY.values() for f in kind.params.model_fields}
    section = DOC.read_text().split("## Controller parameter ranges", 1)[1].split("\n## ", 1)[0]
    named = set(re.findall(r"^\| `(\w+)` \|", section, flags=re.MULTILINE))
    assert named == fields
