"""A real `hil serve --loopback` for the service's tests: its own process, state directory and free port, the
emulated lab on the realtime clock; stopped with SIGINT (the worker aborts a running item and lets go)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from hil.service import Bench, BenchError

READY_S = 180.0  # the worker starts the emulated lab and compiles nothing: minutes only on a machine under load


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Service:
    state_dir: Path
    port: int = field(default_factory=free_port)
    args: tuple[str, ...] = ("--loopback",)
    env: dict[str, str] = field(default_factory=dict)
    proc: subprocess.Popen[bytes] | None = None
    token: str | None = None
    host: str = "127.0.0.1"  # where clients reach it (give --host in args too)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self, wait: bool = True, start_queue: bool = True) -> Service:
        """Start `hil serve`; with ``wait``, until its worker is ready, and then (``start_queue``) start its queue,
        which every start of a service leaves stopped."""
        self.log = (self.state_dir.parent / f"serve-{self.port}.log").open("ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil", "serve", *self.args, "--port", str(self.port), "--state-dir",
             str(self.state_dir)], stdout=self.log, stderr=subprocess.STDOUT, env={**os.environ, **self.env},
            start_new_session=True)
        if wait:
            self.wait_ready()
            if start_queue:
                self.bench().start()
        return self

    def bench(self, user: str = "tester", token: str | None = None) -> Bench:
        return Bench(self.url, token=token if token is not None else self.token, user=user)

    def wait_ready(self, timeout_s: float = READY_S) -> dict:
        deadline = time.monotonic() + timeout_s
        last = None
        while time.monotonic() < deadline:
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise AssertionError(f"hil serve exited {self.proc.returncode}: {self.output()}")
            try:
                last = self.bench().status()
                if last["worker"]["state"] == "ready":
                    return last
            except BenchError:
                pass
            time.sleep(0.2)
        raise AssertionError(f"not ready in {timeout_s} s: {last}; {self.output()}")

    def output(self) -> str:
        path = self.state_dir.parent / f"serve-{self.port}.log"
        worker = self.state_dir / "worker.log"
        text = path.read_text(errors="replace")[-3000:] if path.exists() else ""
        return text + (worker.read_text(errors="replace")[-3000:] if worker.exists() else "")

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 60.0) -> int | None:
        if self.proc is None or self.proc.poll() is not None:
            return None if self.proc is None else self.proc.returncode
        os.killpg(self.proc.pid, sig) if sig == signal.SIGKILL else self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            return self.proc.wait(10)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """One loopback service shared by a module's tests (each test leaves the queue empty and running)."""
    svc = Service(tmp_path_factory.mktemp("serve") / "state").start()
    yield svc
    svc.stop()


def wait_for(predicate, timeout_s: float = 120.0, poll_s: float = 0.1):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise AssertionError(f"not within {timeout_s} s")
