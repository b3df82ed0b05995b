"""Framing for the pipes between the bench process and its helper processes (the log writer, the
telemetry publisher): a 4-byte little-endian length, then a pickle.

Helpers run in their own processes so that their CPU work never holds the 1 kHz loop's GIL
(docs/performance.md: a log flush in a thread paused the loop by ~0.5 ms, an MQTT publish in the
loop's thread by ~0.4 ms).
"""

from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

LEN = struct.Struct("<I")
ATOMIC_BYTES = 4096  # POSIX PIPE_BUF on Linux: a write this small to a pipe is all or nothing


def frame(obj: Any) -> bytes:
    """One message as bytes on the wire."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    return LEN.pack(len(data)) + data


def send_bytes(fd: int, data: bytes) -> None:
    """Write one length-prefixed message body (blocking: loops over partial writes)."""
    view = memoryview(LEN.pack(len(data)) + data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def send(fd: int, obj: Any) -> None:
    send_bytes(fd, pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))


def read_exactly(fd: int, n: int) -> bytes | None:
    parts = []
    while n:
        chunk = os.read(fd, n)
        if not chunk:
            return None
        parts.append(chunk)
        n -= len(chunk)
    return b"".join(parts)


def recv(fd: int) -> Any:
    """The next message, or None at EOF (the other side is gone or closed its end)."""
    head = read_exactly(fd, LEN.size)
    if head is None:
        return None
    body = read_exactly(fd, LEN.unpack(head)[0])
    return None if body is None else pickle.loads(body)


class FrameBuffer:
    """Splits a byte stream read in arbitrary pieces (a non-blocking reader) into messages."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def read(self, fd: int) -> list[Any] | None:
        """Read what a non-blocking ``fd`` has and return the messages it completes; None at EOF (or a read
        error: the other side is gone)."""
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            return []
        except OSError:
            return None
        return self.feed(data) if data else None

    def feed(self, data: bytes) -> list[Any]:
        buf = self._buf
        buf += data
        out = []
        while len(buf) >= LEN.size:
            (n,) = LEN.unpack_from(buf)
            if len(buf) < LEN.size + n:
                break
            out.append(pickle.loads(bytes(buf[LEN.size:LEN.size + n])))
            del buf[: LEN.size + n]
        return out


def helper_argv(entry: str) -> list[str]:
    """``python -c "from MODULE import FUNC; FUNC()"`` for ``entry`` = ``"MODULE:FUNC"``."""
    module, func = entry.split(":")
    return [sys.executable, "-c", f"from {module} import {func}; {func}()"]


def spawn_helper(argv: list[str]) -> subprocess.Popen[bytes]:
    """Start a helper process with pipes on its stdin and stdout and this checkout on PYTHONPATH
    (raises OSError if it cannot start)."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    return subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0, env=env,
                            close_fds=True)
