"""The emulator's control socket: JSON lines over a Unix socket, for tests and `hil` tools.

Requests (one JSON object per line; one JSON reply per request):

- ``{"cmd": "status"}``: tick, clock mode, per-link statistics, board summaries;
- ``{"cmd": "inject", "link": "servo", "kind": "stall", "duration_ms": 20}``: a one-off fault now
  (kinds as in :class:`firmware_stub.config.ScheduledFault`; ``n_bytes`` for garbage);
- ``{"cmd": "set_faults", "link": "servo", "bit_error_rate": 1e-5, ...}``: change a link's continuous
  faults (fields of :class:`firmware_stub.config.LinkFaults`; unspecified ones keep their values);
- ``{"cmd": "records", "since": 0}``: the fault and board-event records from index ``since``;
- ``{"cmd": "stop"}``: shut the emulator down as SIGTERM would.

Errors come back as ``{"error": "..."}``.
"""

from __future__ import annotations

import contextlib
import json
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

Handler = Callable[[dict[str, Any]], dict[str, Any]]


class ControlServer:
    """Non-blocking server; the emulator's loop calls ``on_readable`` when select says so."""

    def __init__(self, path: Path, handler: Handler) -> None:
        self.path = path
        self.handler = handler
        path.unlink(missing_ok=True)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.bind(str(path))
        self.sock.listen(4)
        self.sock.setblocking(False)
        self.clients: dict[int, tuple[socket.socket, bytearray]] = {}

    def fds(self) -> dict[int, Callable[[float], None]]:
        readers: dict[int, Callable[[float], None]] = {self.sock.fileno(): self._accept}
        for fd in self.clients:
            readers[fd] = lambda _t, fd=fd: self._serve(fd)
        return readers

    def _accept(self, _t: float) -> None:
        with contextlib.suppress(BlockingIOError):
            conn, _ = self.sock.accept()
            conn.setblocking(False)
            self.clients[conn.fileno()] = (conn, bytearray())

    def _serve(self, fd: int) -> None:
        conn, buf = self.clients[fd]
        try:
            data = conn.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            del self.clients[fd]
            conn.close()
            return
        buf += data
        while b"\n" in buf:
            line, _, rest = bytes(buf).partition(b"\n")
            buf[:] = rest
            try:
                request = json.loads(line)
                reply = self.handler(request) if isinstance(request, dict) else {"error": "expected a JSON object"}
            except (ValueError, KeyError, TypeError) as exc:
                reply = {"error": " ".join(str(exc).split())}
            conn.setblocking(True)
            try:
                conn.sendall(json.dumps(reply).encode() + b"\n")
            except OSError:
                pass
            finally:
                conn.setblocking(False)

    def close(self) -> None:
        for conn, _ in self.clients.values():
            conn.close()
        self.clients.clear()
        self.sock.close()
        self.path.unlink(missing_ok=True)


class ControlClient:
    """Blocking client: ``ControlClient(path).call("inject", link="servo", kind="stall", duration_ms=20)``."""

    def __init__(self, path: str | Path, timeout_s: float = 5.0) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout_s)
        self.sock.connect(str(path))
        self.buf = b""

    def call(self, cmd: str, **args: Any) -> dict[str, Any]:
        self.sock.sendall(json.dumps({"cmd": cmd, **args}).encode() + b"\n")
        while b"\n" not in self.buf:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("the emulator closed its control socket")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        reply = json.loads(line)
        if "error" in reply:
            raise RuntimeError(f"emulator: {reply['error']}")
        return reply

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
