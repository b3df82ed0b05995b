"""Golden vectors: the example frames of docs/protocol.md section 9, written out by hand here.

If one of these fails, the wire format changed: that breaks every deployed firmware, so it
must be a deliberate protocol-version bump, not a side effect.
"""

from __future__ import annotations

import pytest

from hil.protocol import (
    CATALOGUE,
    Board,
    Decoder,
    DriveCmd,
    ErrorCode,
    GyroSample,
    HexapodStart,
    HexAxis,
    MissDistance,
    Nack,
    crc16,
    encode_frame,
)
from hil.protocol.docgen import DOC_PATH
from tests.protocol.reference import crc16_bitwise

GOLDEN = [
    (
        GyroSample(t_us=1_000_000, tick=1000, rate_x_dps=0.5, rate_y_dps=-0.25, rate_z_dps=12.0, az_deg=30.0,
                   el_deg=-5.5),
        Board.SERVO, Board.HOST, 258,
        "eb 90 01 10 01 10 02 01 1c 40 42 0f 00 e8 03 00 00 20 a1 07 00 70 2f fc ff 00 1b b7 00 80 c3 c9 01"
        " a0 13 ac ff 4c 1c",
    ),
    (
        DriveCmd(tick=1000, az_counts=1200, el_counts=-350),
        Board.HOST, Board.DRIVER, 7,
        "eb 90 01 01 20 20 07 00 08 e8 03 00 00 b0 04 a2 fe 69 36",
    ),
    (
        MissDistance(frame=42, t_exposure_us=1_234_567, miss_x_px=3.25, miss_y_px=-1.5, track_valid=True),
        Board.IMAGE, Board.HOST, 42,
        "eb 90 01 30 01 30 2a 00 11 2a 00 00 00 87 d6 12 00 b2 0c 00 00 24 fa ff ff 01 fc 09",
    ),
    (
        Nack(msg_id=0x40, seq=2, error=ErrorCode.ENVELOPE_POSITION, axis=HexAxis.PITCH, value=12.5, limit=10.0),
        Board.HEXAPOD, Board.HOST, 3,
        "eb 90 01 40 01 05 03 00 0d 40 02 00 06 04 00 00 48 41 00 00 20 41 c4 15",
    ),
    (HexapodStart(), Board.HOST, Board.HEXAPOD, 0, "eb 90 01 01 40 41 00 00 00 4f 05"),
]


def test_crc_is_ccitt_false_with_its_catalogue_check_value():
    assert crc16(b"123456789") == 0x29B1
    assert crc16_bitwise(b"123456789") == 0x29B1


@pytest.mark.parametrize(("message", "src", "dst", "seq", "hex_frame"), GOLDEN, ids=lambda v: type(v).__name__)
def test_encoder_produces_the_golden_frame(message, src, dst, seq, hex_frame):
    assert encode_frame(message, src=src, dst=dst, seq=seq).hex(" ") == hex_frame


@pytest.mark.parametrize(("message", "src", "dst", "seq", "hex_frame"), GOLDEN, ids=lambda v: type(v).__name__)
def test_decoder_reads_the_golden_frame(message, src, dst, seq, hex_frame):
    raw = bytes.fromhex(hex_frame)
    assert int.from_bytes(raw[-2:], "little") == crc16_bitwise(raw[2:-2])
    frames = Decoder().feed(raw)
    assert [(f.src, f.dst, f.seq, f.message) for f in frames] == [(src, dst, seq, message)]


def test_golden_frames_are_the_ones_the_document_shows():
    doc = DOC_PATH.read_text()
    for *_, hex_frame in GOLDEN:
        assert f"\n{hex_frame}\n" in doc


def test_gyro_sample_field_offsets_match_the_spec_table():
    """Offsets a C struct would use: header 9 bytes, then t_us, tick, 3 rates, az, el."""
    spec = CATALOGUE.by_id[0x10]
    assert [(f.name, f.offset, f.wire.type_label) for f in spec.fields] == [
        ("t_us", 0, "u32"), ("tick", 4, "u32"), ("rate_x_dps", 8, "i32"), ("rate_y_dps", 12, "i32"),
        ("rate_z_dps", 16, "i32"), ("az_deg", 20, "i32"), ("el_deg", 24, "i32"),
    ]
    assert spec.payload_size == 28
