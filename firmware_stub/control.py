"""The emulator's control socket: JSON lines over a Unix socket, for tests and `hil` tools.

Requests (one JSON object per line; one JSON reply per request):

- ``{"cmd": "status"}``: tick, clock mode, per-link statistics, board summaries;
- ``{"cmd": "inject", "link": "servo", "kind": "stall", "duration_ms": 20}``: a one-off fault now
  (kinds as in :class:`firmware_stub.config.ScheduledFault`; ``n_bytes`` for garbage);
- ``{"cmd": "set_faults", "link": "servo", "bit_error_rate": 1e-5, ...}``: change a link's continuous
  faults (fields of :class:`firmware_stub.config.LinkFaults`; unspecified ones keep their values);
- ``{"cmd": "records", "since": 0}``: the fault and board-event records from index ``since``;
- ``{"cmd": "stop"}``: shut the emulator down as SIGTERM would.

Every request is validated by its command's pydantic model (:data:`REQUESTS`: unknown fields refused, NaN
and infinities refused, durations bounded) before the emulator sees it; a bad one is answered with
``{"error": "<cmd>: <field>: <reason>"}`` and the socket keeps serving. A line longer than
``MAX_LINE_BYTES`` is answered with an error and its client disconnected.
"""

from __future__ import annotations

import contextlib
import json
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from firmware_stub.config import FaultKind, LinkFaults, LinkName, describe_validation_error

Handler = Callable[[dict[str, Any]], dict[str, Any]]
MAX_LINE_BYTES = 64 * 1024  # one request
MAX_FAULT_MS = 600_000.0  # a stall, latency spike or disconnect injected here lasts at most 10 min


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class StatusRequest(_Request):
    cmd: Literal["status"]


class InjectRequest(_Request):
    cmd: Literal["inject"]
    link: LinkName
    kind: FaultKind
    duration_ms: float = Field(0.0, ge=0.0, le=MAX_FAULT_MS, description="stall / latency_spike / disconnect length")
    n_bytes: int = Field(64, ge=1, le=65536, description="garbage length")


class SetFaultsRequest(_Request):
    """``link`` and any fields of :class:`firmware_stub.config.LinkFaults` (checked as LinkFaults checks them)."""

    model_config = ConfigDict(extra="allow")
    cmd: Literal["set_faults"]
    link: LinkName

    @model_validator(mode="after")
    def _faults(self) -> SetFaultsRequest:
        fields = dict(self.model_extra or {})
        unknown = sorted(set(fields) - set(LinkFaults.model_fields))
        if unknown:
            raise ValueError(f"{unknown[0]}: not a LinkFaults field ({', '.join(LinkFaults.model_fields)})")
        try:
            LinkFaults.model_validate(fields)
        except ValidationError as exc:
            raise ValueError(describe_validation_error("faults", exc)) from None
        return self


class RecordsRequest(_Request):
    cmd: Literal["records"]
    since: int = Field(0, ge=0, le=2**62)


class StopRequest(_Request):
    cmd: Literal["stop"]


REQUESTS: dict[str, type[_Request]] = {"status": StatusRequest, "inject": InjectRequest,
                                       "set_faults": SetFaultsRequest, "records": RecordsRequest, "stop": StopRequest}


def validate_request(request: Any) -> dict[str, Any]:
    """The request as the emulator's handler takes it, validated; ValueError (one line) if it is not valid."""
    if not isinstance(request, dict):
        raise ValueError("expected a JSON object")
    cmd = request.get("cmd")
    model = REQUESTS.get(cmd) if isinstance(cmd, str) else None
    if model is None:
        raise ValueError(f"unknown command {request.get('cmd')!r} ({', '.join(REQUESTS)})")
    try:
        return model.model_validate(request).model_dump(mode="json")
    except ValidationError as exc:
        raise ValueError(describe_validation_error(str(request["cmd"]), exc)) from None


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
            def serve(_t: float, fd: int = fd) -> None:
                self._serve(fd)
            readers[fd] = serve
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
            self._reply(conn, self._answer(line))
        if len(buf) > MAX_LINE_BYTES:
            self._reply(conn, {"error": f"a request longer than {MAX_LINE_BYTES} bytes"})
            del self.clients[fd]
            conn.close()

    def _answer(self, line: bytes) -> dict[str, Any]:
        """The reply to one request line: the handler's, or an error; never raises (the socket keeps serving)."""
        if len(line) > MAX_LINE_BYTES:
            return {"error": f"a request longer than {MAX_LINE_BYTES} bytes"}
        try:
            request = validate_request(json.loads(line))
        except (ValueError, RecursionError) as exc:
            return {"error": " ".join(str(exc).split())}
        try:
            return self.handler(request)
        except Exception as exc:  # a handler failure is this request's error, not the emulator's end
            return {"error": f"{request['cmd']}: {type(exc).__name__}: {' '.join(str(exc).split())}"}

    @staticmethod
    def _reply(conn: socket.socket, reply: dict[str, Any]) -> None:
        try:
            text = json.dumps(reply)
        except (TypeError, ValueError) as exc:
            text = json.dumps({"error": f"the reply is not JSON: {exc}"})
        conn.setblocking(True)
        try:
            conn.sendall(text.encode() + b"\n")
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
