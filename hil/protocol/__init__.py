"""The framed binary protocol the bench and its boards speak (docs/protocol.md).

Import messages and the codec from here::

    from hil.protocol import Decoder, Encoder, GyroSample, Board
"""

from hil.protocol import messages
from hil.protocol._text import frame_json, hex_bytes, message_json
from hil.protocol.framing import (
    BITS_PER_BYTE,
    CRC_INIT,
    HEADER_SIZE,
    LINE_RATE_BAUD,
    MAX_FRAME,
    MAX_PAYLOAD,
    SYNC,
    Decoder,
    Encoder,
    Frame,
    LinkCounters,
    crc16,
    encode_frame,
    frame_size,
    wire_time_s,
)
from hil.protocol.messages import *  # noqa: F403  (the catalogue is the public vocabulary)
from hil.protocol.wire import Catalogue, EncodeError, MessageSpec

__all__ = [  # noqa: PLE0604
    *messages.__all__,
    "BITS_PER_BYTE",
    "CRC_INIT",
    "HEADER_SIZE",
    "MAX_FRAME",
    "MAX_PAYLOAD",
    "SYNC",
    "Catalogue",
    "Decoder",
    "EncodeError",
    "Encoder",
    "Frame",
    "LinkCounters",
    "MessageSpec",
    "crc16",
    "encode_frame",
    "frame_json",
    "frame_size",
    "hex_bytes",
    "message_json",
    "LINE_RATE_BAUD",
    "wire_time_s",
]
