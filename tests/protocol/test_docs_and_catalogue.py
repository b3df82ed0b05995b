"""docs/protocol.md and the catalogue must agree; fingerprints must track layout changes.

(No `from __future__ import annotations` here: the probe messages annotate with local variables.)
"""


import zlib
from enum import IntEnum
from typing import Annotated, NamedTuple

import pytest

from hil.protocol import CATALOGUE, MAX_PAYLOAD, docgen
from hil.protocol.wire import Catalogue, i16, i32, u8, u32


def test_protocol_document_matches_the_catalogue():
    doc = docgen.DOC_PATH.read_text()
    assert docgen.apply(doc) == doc, "docs/protocol.md is stale: run `hil protocol docs --write`"


def test_document_lists_every_message_with_its_id_and_fingerprint():
    doc = docgen.DOC_PATH.read_text()
    assert len(CATALOGUE) >= 20
    for spec in CATALOGUE:
        assert f"| `{spec.msg_id:#04x}` | {spec.name} |" in doc
        assert f"`{spec.fingerprint:#010x}`" in doc
    assert f"**`{CATALOGUE.fingerprint:#010x}`**" in doc


def test_every_payload_fits_and_ids_are_unique_bytes():
    assert all(0 <= s.payload_size <= MAX_PAYLOAD for s in CATALOGUE)
    assert len({s.msg_id for s in CATALOGUE}) == len(CATALOGUE)


def test_catalogue_has_the_messages_each_board_needs():
    names = {s.name for s in CATALOGUE}
    assert {"IDENT_REQ", "IDENT", "HEARTBEAT", "ACK", "NACK"} <= names
    assert {"GYRO_SAMPLE", "SERVO_CONFIG", "SERVO_MODE", "LOOP_TIMING"} <= names
    assert {"DRIVE_CMD", "DRIVE_ENABLE", "DRIVE_DISABLE", "DRIVE_STATUS"} <= names
    assert {"MISS_DISTANCE", "TRACK_CMD"} <= names
    assert {"PROFILE_LOAD", "HEXAPOD_START", "HEXAPOD_STOP", "POSE", "HEXAPOD_STATUS"} <= names


def test_fingerprint_is_crc32_of_the_documented_layout_text():
    assert zlib.crc32(b"123456789") == 0xCBF43926  # CRC-32/ISO-HDLC, as the document says
    assert CATALOGUE.fingerprint == zlib.crc32(CATALOGUE.layout_text().encode())
    gyro = CATALOGUE.by_id[0x10]
    assert gyro.layout() == (
        "0x10 GYRO_SAMPLE t_us:u32*1[us];tick:u32*1[];rate_x_dps:i32*1e-06[deg/s];"
        "rate_y_dps:i32*1e-06[deg/s];rate_z_dps:i32*1e-06[deg/s];az_deg:i32*1e-06[deg];el_deg:i32*1e-06[deg]"
    )
    assert CATALOGUE.layout_text().splitlines()[0] == "HIL stabilized-platform bench protocol v1"


class _Mode(IntEnum):
    A = 0


def _one_message_catalogue(field_type) -> Catalogue:
    cat = Catalogue(1, "test")

    @cat.message(0x10, sender=None, receiver=None, rate="1 kHz")
    class Probe(NamedTuple):
        tick: Annotated[int, u32()]
        value: Annotated[float, field_type]

    return cat


@pytest.mark.parametrize(
    "changed",
    [i16("deg", scale=1e-6), i32("rad", scale=1e-6), i32("deg", scale=1e-5), u32("deg"), u8("deg", enum=_Mode)],
    ids=["type", "unit", "scale", "signedness", "kind"],
)
def test_any_layout_change_changes_the_fingerprint(changed):
    base = _one_message_catalogue(i32("deg", scale=1e-6))
    assert _one_message_catalogue(i32("deg", "other words", scale=1e-6)).fingerprint == base.fingerprint
    assert _one_message_catalogue(changed).fingerprint != base.fingerprint


def test_an_empty_payload_line_ends_with_one_space_as_the_doc_says() -> None:
    lines = CATALOGUE.layout_text().split("\n")
    ident_req = next(line for line in lines if " IDENT_REQ" in line)
    assert ident_req == "0x01 IDENT_REQ "  # one trailing space, no field list
    doc = docgen.DOC_PATH.read_text()
    assert "`0x01 IDENT_REQ `" in doc
    spelled = "30 78 30 31 20 49 44 45 4E 54 5F 52 45 51 20"
    assert spelled in doc and bytes.fromhex(spelled).decode() == ident_req
    # the space is part of the fingerprint's input: without it the catalogue's fingerprint changes
    without = "\n".join(line.rstrip() for line in lines)
    assert zlib.crc32(without.encode()) != CATALOGUE.fingerprint == zlib.crc32("\n".join(lines).encode())
