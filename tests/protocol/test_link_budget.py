"""The link budget's numbers (hil.protocol.budget) against the catalogue's rate texts and docs/protocol.md's table."""

from __future__ import annotations

import re

import pytest

from hil.protocol import BITS_PER_BYTE, CATALOGUE
from hil.protocol.budget import PERIODIC_HZ, periodic_load_bits_per_s, periodic_messages
from hil.protocol.docgen import DOC_PATH

RATE_TEXT = re.compile(r"(\d+(?:\.\d+)?) (k?Hz)")


def _budget_block() -> str:
    doc = DOC_PATH.read_text()
    return doc.split("<!-- BEGIN GENERATED: budget -->", 1)[1].split("<!-- END GENERATED: budget -->", 1)[0]


def test_each_periodic_rate_is_the_number_its_catalogue_text_names() -> None:
    for spec in CATALOGUE:
        found = RATE_TEXT.search(spec.rate)
        said = None if not found else float(found[1]) * (1000 if found[2] == "kHz" else 1)
        assert PERIODIC_HZ.get(spec.cls) == said, (spec.name, spec.rate)


def test_the_periodic_messages_are_the_docs_table() -> None:
    rows = re.findall(r"^\| (\w+) \| (\d+) \| (\d+(?:\.\d+)?) Hz \|", _budget_block(), re.M)
    assert rows, "docs/protocol.md has no link budget table"
    assert [(p.name, p.frame_bytes, p.rate_hz) for p in periodic_messages()] == [
        (name, int(size), float(hz)) for name, size, hz in rows]


def test_the_load_per_link_is_the_docs_list() -> None:
    listed = dict(re.findall(r"^- (\w+ → \w+): (\d+\.\d) kB/s", _budget_block(), re.M))
    load = periodic_load_bits_per_s()
    assert {d: f"{bps / BITS_PER_BYTE / 1e3:.1f}" for d, bps in load.items()} == listed


@pytest.mark.parametrize(("direction", "bits_per_s"), [
    ("servo → host", (39 * 1000 + 43 * 100) * 10),  # GYRO_SAMPLE at 1 kHz, LOOP_TIMING at 100 Hz
    ("host → driver", 19 * 1000 * 10),  # DRIVE_CMD at 1 kHz
    ("driver → host", 27 * 100 * 10),  # DRIVE_STATUS
    ("image → host", 28 * 100 * 10),  # MISS_DISTANCE
    ("hexapod → host", (39 * 100 + 18 * 10) * 10),  # POSE, HEXAPOD_STATUS
])
def test_the_load_per_link_in_bits_per_second(direction: str, bits_per_s: int) -> None:
    load = periodic_load_bits_per_s()
    assert len(load) == 5
    assert load[direction] == bits_per_s
