"""A real MQTT broker on a free local port, for tests: mosquitto where installed, else amqtt.

Reusable from any test package::

    from tests.telemetry.broker import mqtt_broker  # noqa: F401  (the fixture)

or directly::

    with MqttBroker.start_new(tmp_path) as broker:
        ...  # broker.host, broker.port, broker.kill(), broker.restart()

Which broker: ``mosquitto`` if ``shutil.which("mosquitto")`` or ``/usr/sbin/mosquitto`` exists,
otherwise amqtt (pure Python, installed with the ``test`` extra) in its own process. The
environment variable ``HIL_TEST_BROKER=amqtt`` (or ``mosquitto``) forces one.

Both run without persistence, so a broker killed and restarted has no retained messages left.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

HOST = "127.0.0.1"
START_TIMEOUT_S = 15.0  # amqtt imports a lot on a cold cache; mosquitto is up in ~10 ms


def free_port() -> int:
    """A TCP port nothing listens on right now (the kernel's choice)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def port_open(host: str, port: int, timeout: float = 0.2) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def mosquitto_path() -> str | None:
    found = shutil.which("mosquitto")
    if found:
        return found
    return "/usr/sbin/mosquitto" if os.access("/usr/sbin/mosquitto", os.X_OK) else None


def broker_kind() -> str:
    """``"mosquitto"`` or ``"amqtt"``: the broker the tests will start here."""
    forced = os.environ.get("HIL_TEST_BROKER", "").strip().lower()
    if forced in ("mosquitto", "amqtt"):
        return forced
    return "mosquitto" if mosquitto_path() else "amqtt"


class MqttBroker:
    """One broker process on ``host:port``; ``kill()`` it (SIGKILL) and ``restart()`` it on the same port."""

    def __init__(self, workdir: Path, *, port: int | None = None, kind: str | None = None) -> None:
        self.host = HOST
        self.port = port or free_port()
        self.kind = kind or broker_kind()
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.log_path = self.workdir / f"{self.kind}-{self.port}.log"
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def _command(self) -> list[str]:
        if self.kind == "mosquitto":
            exe = mosquitto_path()
            if exe is None:
                raise RuntimeError("HIL_TEST_BROKER=mosquitto but mosquitto is not installed")
            conf = self.workdir / f"mosquitto-{self.port}.conf"
            conf.write_text(
                f"listener {self.port} {self.host}\n"
                "allow_anonymous true\n"
                "persistence false\n"
                "log_dest stderr\n"
                "log_type error\nlog_type warning\nlog_type notice\n"
            )
            return [exe, "-c", str(conf)]
        conf = self.workdir / f"amqtt-{self.port}.yaml"
        conf.write_text(
            "listeners:\n"
            "  default:\n"
            "    type: tcp\n"
            f"    bind: {self.host}:{self.port}\n"
            "plugins:\n"
            "  amqtt.plugins.authentication.AnonymousAuthPlugin:\n"
            "    allow_anonymous: true\n"
        )
        return [sys.executable, "-m", "amqtt.scripts.broker_script", "-c", str(conf)]

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def start(self) -> MqttBroker:
        """Start the process and wait until the port accepts connections."""
        if self.running:
            return self
        log = self.log_path.open("ab")
        try:
            self._proc = subprocess.Popen(
                self._command(), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=self.workdir
            )
        finally:
            log.close()
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                raise RuntimeError(f"{self.kind} exited with {self._proc.returncode} at start:\n{self.log_tail()}")
            if port_open(self.host, self.port):
                return self
            time.sleep(0.01)
        self.kill()
        raise RuntimeError(f"{self.kind} did not listen on {self.host}:{self.port} within {START_TIMEOUT_S} s")

    def kill(self) -> None:
        """SIGKILL the broker (no clean shutdown: its clients see the connection drop)."""
        if self._proc is not None and self._proc.poll() is None:
            self._proc.send_signal(signal.SIGKILL)
            self._proc.wait(timeout=10)
        deadline = time.monotonic() + 5
        while port_open(self.host, self.port, timeout=0.05) and time.monotonic() < deadline:
            time.sleep(0.01)

    def restart(self) -> MqttBroker:
        """Start again on the same port (after kill() or stop())."""
        self.kill()
        return self.start()

    def stop(self) -> None:
        """Terminate cleanly (SIGTERM, then SIGKILL after 5 s)."""
        if self._proc is None or self._proc.poll() is not None:
            return
        self._proc.terminate()
        try:
            self._proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.kill()

    def log_tail(self, n: int = 20) -> str:
        with contextlib.suppress(OSError):
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        return ""

    def __enter__(self) -> MqttBroker:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"MqttBroker({self.kind} on {self.host}:{self.port}, running={self.running})"

    @classmethod
    def start_new(cls, workdir: Path | None = None, attempts: int = 3) -> MqttBroker:
        """Start a broker on a fresh free port, trying another port if the chosen one was taken meanwhile."""
        workdir = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="hil-mqtt-"))
        error: Exception | None = None
        for _ in range(attempts):
            broker = cls(workdir)
            try:
                return broker.start()
            except RuntimeError as exc:  # port race or a broker start failure: try once more
                broker.kill()
                error = exc
        raise RuntimeError(f"could not start an MQTT broker: {error}")


@pytest.fixture
def mqtt_broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MqttBroker]:
    """A running broker on a free port of 127.0.0.1, stopped at teardown."""
    broker = MqttBroker.start_new(tmp_path_factory.mktemp("mqtt-broker"))
    try:
        yield broker
    finally:
        broker.stop()
