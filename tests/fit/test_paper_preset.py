"""Seed 000's premises on the paper preset (profiles/plant/paper-000.yaml, docs/emulator.md, paper-000).

The preset and the controller parameters the same fit chose (profiles/controllers/*-paper-000.yaml, or the
registry's defaults where the fit kept them) run the measuring cells of profiles/targets/seed-000.yaml in this
process on the sim clock, three seeds, each campaign's full duration (about a minute). A premise that no plausible
plant reached in the search is an expected failure (strict: it fails the suite once it holds, so the docs get
updated), with the measured numbers in its reason; what does hold is asserted beside it.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from hil.fit.targets import TABLE_STDS, Measured, load_targets, measure, paper_figures

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
TARGETS = ROOT / "profiles" / "targets" / "seed-000.yaml"
PRESET = ROOT / "profiles" / "plant" / "paper-000.yaml"
CONTROLLERS = ROOT / "profiles" / "controllers"
SEEDS = (1, 2, 3)
PAPER_STD = {k: paper_figures(load_targets(TARGETS))[k] for k in TABLE_STDS}  # the targets file's figures


def _controller_values() -> dict[str, float]:
    """The searched controller parameters as the preset ships them (the targets file's defaults otherwise)."""
    config = load_targets(TARGETS)
    values = {p.name: p.default for p in config.search.controller_params}
    for p in config.search.controller_params:
        for name in p.controllers:
            path = CONTROLLERS / f"{name}-paper-000.yaml"
            if path.is_file():
                params = yaml.safe_load(path.read_text())["params"]
                if p.fields[0] in params:
                    values[p.name] = float(params[p.fields[0]])
    return values


@pytest.fixture(scope="module")
def measured() -> Measured:
    config = load_targets(TARGETS)
    ids = [*PAPER_STD, "eso-high-gain"]
    return measure(config, PRESET, _controller_values(), seeds=SEEDS, full=True, ids=ids)


def _seeds(m: Measured, key: str) -> list[float]:
    xs = m.per_seed[key]
    assert len(xs) == len(SEEDS) and all(math.isfinite(x) for x in xs), (key, xs, m.unstable)
    return xs


def test_the_preset_is_stable_for_every_paper_controller(measured: Measured) -> None:
    assert not {k: v for k, v in measured.unstable.items() if k != "eso-high-gain"}


def test_a_gyro_noise_limits_the_observer_gain(measured: Measured) -> None:
    """At the high-gain omega_o, plain ESO is unstable or >= 20 % worse than ESO+KF at that gain (every seed)."""
    if "eso-high-gain" in measured.unstable:
        return
    eso, kf = measured.per_seed["eso-high-gain"], _seeds(measured, "table1-hg-std")
    assert all(e >= 1.2 * k for e, k in zip(eso, kf, strict=True)), (eso, kf)


def test_b_table1_ordering_on_every_seed(measured: Measured) -> None:
    eso, kf, hg = (_seeds(measured, k) for k in ("table1-eso-std", "table1-esokf-std", "table1-hg-std"))
    for e, k, h in zip(eso, kf, hg, strict=True):
        assert k < e, (eso, kf)
        assert h < k and h < e, (kf, hg)


MISS_GROWTH = ("not reached: ESO miss std 9.68 px at 3 deg / 6.95 at 1 deg = 1.39 on seeds 1-3 (paper 2.59); "
               "29 of the search's 248 trials reached 1.5, none with every Table 1-3 std within 1.5x "
               "(docs/emulator.md, paper-000)")
D_FAILS = {
    "table3-eso-std": "not reached: ESO miss std at 3 deg 9.68 px, 0.62x the paper's 15.60 "
                      "(docs/emulator.md, paper-000)",
    "table3-hg-std": "not reached: high-gain ESO+KF miss std at 3 deg 10.45 px, 1.70x the paper's 6.15; no trial of "
                     "the search had every Table 1-3 std within 1.5x (best worst factor 1.69, "
                     "docs/emulator.md, paper-000)",
}


@pytest.mark.xfail(strict=True, reason=MISS_GROWTH)
def test_c_miss_grows_with_the_swing_amplitude(measured: Measured) -> None:
    one, three = _seeds(measured, "table2-eso-std"), _seeds(measured, "table3-eso-std")
    assert sum(three) / sum(one) >= 1.5, (one, three)


def test_c_what_holds_the_miss_grows_with_the_swing(measured: Measured) -> None:
    """The torque limit makes the 3 deg swing's miss larger on every seed (1.39x), short of the premise's 1.5x."""
    one, three = _seeds(measured, "table2-eso-std"), _seeds(measured, "table3-eso-std")
    assert all(t >= 1.3 * o for o, t in zip(one, three, strict=True)), (one, three)


@pytest.mark.parametrize("key", [pytest.param(k, marks=pytest.mark.xfail(strict=True, reason=D_FAILS[k]))
                                 if k in D_FAILS else k for k in PAPER_STD])
def test_d_each_table_std_within_a_factor_1_5(measured: Measured, key: str) -> None:
    x = measured.value(key)
    assert 1 / 1.5 <= x / PAPER_STD[key] <= 1.5, (key, x, PAPER_STD[key])
