"""The emulated lab as a child process (`python -m firmware_stub`), for `hil run --loopback`, `hil demo` and tests."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from hil.transport import LinkError


def _die_with_parent() -> None:
    """Linux: SIGTERM the emulator if the bench dies (even by SIGKILL), so no orphan keeps the ptys."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class EmulatorProcess:
    """Start with ``with EmulatorProcess(config, clock=..., seed=...) as emu: emu.ports ...``."""

    def __init__(self, config: Path | None = None, *, clock: str = "lockstep", seed: int = 0,
                 extra_args: list[str] | None = None) -> None:
        self.args = [sys.executable, "-m", "firmware_stub", "--clock", clock, "--seed", str(seed)]
        if config is not None:
            self.args += ["--config", str(config)]
        self.args += extra_args or []
        self.proc: subprocess.Popen[str] | None = None
        self.ports: dict[str, str] = {}
        self.summary: dict[str, Any] = {}

    def start(self) -> dict[str, str]:
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     preexec_fn=_die_with_parent)  # noqa: PLW1509 (before any thread)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read().strip() if self.proc.stderr else ""
            self.proc.wait(5)
            raise LinkError(f"the emulator did not start: {err.splitlines()[-1] if err else 'no output'}")
        self.ports = json.loads(line)
        return self.ports

    def stop(self) -> dict[str, Any]:
        if self.proc is None:
            return {}
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        lines = [ln for ln in out.strip().splitlines() if ln.startswith("{")]
        self.summary = json.loads(lines[-1]) if lines else {}
        self.proc = None
        return self.summary

    def __enter__(self) -> EmulatorProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
