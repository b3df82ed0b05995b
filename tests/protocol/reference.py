"""Independent reference implementations the protocol tests check the codec against."""

from __future__ import annotations


def crc16_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), bit by bit: the C loop of docs/protocol.md.

    Independent of binascii.crc_hqx, which the codec uses.
    """
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc
