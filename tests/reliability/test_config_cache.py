"""The readers remember parsed config files by their text: an edited file is read afresh, a caller's changes to what it
got never reach the next caller, and a bad file is refused every time (exceptions are not remembered)."""

from __future__ import annotations

from pathlib import Path

import pytest

from firmware_stub.config import ConfigError
from firmware_stub.config import read_yaml_mapping as read_emulator_yaml
from hil.config import read_yaml_mapping as read_bench_yaml
from hil.protocol import HexAxis
from hil.protocol.swing import Envelope, Segment, check_envelope


@pytest.mark.parametrize("read", [read_emulator_yaml, read_bench_yaml], ids=["firmware_stub", "hil.config"])
def test_an_edited_file_is_read_afresh_and_a_callers_changes_stay_its_own(read, tmp_path: Path) -> None:
    path = tmp_path / "plant.yaml"
    path.write_text("motor_az: {inertia_kg_m2: 0.02}\nnotes: [a, b]\n")
    first = read(path)
    first["motor_az"]["inertia_kg_m2"] = 99.0  # the caller's own copy
    first["notes"].append("c")
    again = read(path)
    assert again == {"motor_az": {"inertia_kg_m2": 0.02}, "notes": ["a", "b"]}
    path.write_text("motor_az: {inertia_kg_m2: 0.05}\nnotes: [a, b]\n")
    assert read(path)["motor_az"]["inertia_kg_m2"] == 0.05
    path.write_text("motor_az: {inertia_kg_m2: [0.05\n")  # unclosed: refused, and again
    for _ in range(2):
        with pytest.raises((ConfigError, ValueError), match=r"plant\.yaml"):
            read(path)


def test_the_envelope_check_answers_by_its_arguments() -> None:
    wide = Envelope((50.0,) * 6, (100.0,) * 6, (1000.0,) * 6)
    narrow = wide._replace(position=(50.0, 50.0, 50.0, 0.5, 0.5, 0.5))
    swing = [Segment(HexAxis.PITCH, 0.0, 2.0, 1.0, 1.0)]
    assert check_envelope(swing, wide) is None
    violation = check_envelope(swing, narrow)
    assert violation is not None and violation.axis == HexAxis.PITCH and violation.limit == 0.5
    assert check_envelope(list(swing), wide) is None  # a list or a tuple: the same answer
    assert check_envelope([swing[0]._replace(amplitude=0.4)], narrow) is None
