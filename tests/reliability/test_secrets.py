"""No secrets in logs: the MQTT password never appears in a dump of the session config (what the session log's
`config` attribute holds), in repr, or in an error line; the broker still gets it, from the file, an environment
variable or a password file."""

from __future__ import annotations

import json
import os
import pickle
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from hil.config import SessionConfig, load_session
from hil.log import read_log
from hil.telemetry import MqttConfig, Telemetry
from hil.telemetry import _publisher as telemetry  # the publisher module itself: its aiomqtt is patched
from tests.factories import session_data, write_yaml
from tests.reliability.helpers import bad_input

SECRET = "hunter2-s3cret"


def every_dump(config: SessionConfig) -> str:
    """Every way the bench writes a session config out, as text."""
    return "\n".join([json.dumps(config.model_dump(mode="json")),  # the session log's `config` attribute
                      str(config.model_dump()), config.model_dump_json(), repr(config), str(config)])


def client_kwargs(config: MqttConfig, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """What the telemetry publisher hands the MQTT client."""
    seen: dict[str, Any] = {}

    def fake_client(*args: Any, **kwargs: Any) -> None:
        seen.update(kwargs)

    monkeypatch.setattr(telemetry.aiomqtt, "Client", fake_client)
    Telemetry(config, "s1")._client()
    return seen


@pytest.mark.parametrize("how", ["password", "password_env", "password_file"])
def test_the_password_is_in_no_dump_and_reaches_the_broker(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, how: str,
) -> None:
    monkeypatch.setenv("HIL_TEST_MQTT_PASSWORD", SECRET)
    (tmp_path / "mqtt.pw").write_text(SECRET + "\n")
    where = {"password": SECRET, "password_env": "HIL_TEST_MQTT_PASSWORD", "password_file": "mqtt.pw"}[how]
    session = write_yaml(tmp_path / "s.yaml", session_data(mqtt={"host": "broker", "username": "bench", how: where}))
    config = load_session(session)
    assert config.mqtt is not None and config.mqtt.password_value == SECRET
    assert SECRET not in every_dump(config)
    if how == "password":
        assert config.model_dump(mode="json")["mqtt"]["password"] == "**********"
    kwargs = client_kwargs(config.mqtt, monkeypatch)
    assert kwargs["password"] == SECRET and kwargs["username"] == "bench"
    # the publisher child gets the config as a pickled python dump and validates it again
    child = MqttConfig.model_validate(pickle.loads(pickle.dumps(config.mqtt.model_dump())))
    assert child.password_value == SECRET


def test_a_session_built_from_a_dump_keeps_working_and_keeps_the_secret(tmp_path: Path) -> None:
    config = load_session(write_yaml(tmp_path / "s.yaml", session_data(mqtt={"host": "h", "password": SECRET})))
    again = SessionConfig.model_validate(config.model_dump())  # the test helpers and `hil ident` do this
    assert again.mqtt is not None and again.mqtt.password_value == SECRET and SECRET not in every_dump(again)


@pytest.mark.parametrize(("mqtt", "needle"), [
    ({"host": "h", "password_env": "HIL_TEST_NOT_SET_ANYWHERE"}, "the environment variable HIL_TEST_NOT_SET_ANYWHERE "
                                                                 "is not set"),
    ({"host": "h", "password_file": "absent.pw"}, "absent.pw: no such file"),
    ({"host": "h", "password_file": "/dev/zero"}, "/dev/zero: a character device, not a regular file"),
    ({"host": "h", "password": SECRET, "password_env": "X"}, "password_env: give the password one way only"),
    ({"host": "h", "password": SECRET * 5000}, "mqtt.password: Value should have at most 65535 items"),
    ({"host": "h", "password_env": "1; rm -rf"}, "mqtt.password_env: String should match pattern"),
])
def test_a_bad_password_setting_is_one_line_without_the_secret(
    *, capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
    monkeypatch: pytest.MonkeyPatch, mqtt: dict[str, Any], needle: str,
) -> None:
    monkeypatch.delenv("HIL_TEST_NOT_SET_ANYWHERE", raising=False)
    session = write_yaml(tmp_path / "s.yaml", session_data(mqtt=mqtt))
    line = bad_input(capsys, ["run", session, "--loopback", "--out", tmp_path / "out"], str(session), needle)
    assert SECRET not in line


def test_a_broker_url_with_a_password_is_not_echoed(capsys: pytest.CaptureFixture[str]) -> None:
    for url, needle in ((f"mqtt://bench:{SECRET}@h:99999", "Port out of range"),
                        (f"mqtts://bench:{SECRET}@h:1", "scheme must be mqtt://"),
                        (f"mqtt://bench:{SECRET}@h:1?telemetry_hz=nan", "telemetry_hz: Input should be a finite")):
        line = bad_input(capsys, ["watch", "--broker", url], "--broker", needle)
        assert SECRET not in line


def test_a_real_session_log_holds_no_password(tmp_path: Path) -> None:
    """`hil run` as a user runs it, telemetry configured with a password (no broker listening): the log file, its
    stdout and stderr hold no trace of the password, and the log records the masked value."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    data = session_data(duration_s=0.5, mqtt={"host": "127.0.0.1", "port": port, "password": SECRET})
    session = write_yaml(tmp_path / "s.yaml", data)
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", str(session), "--loopback", "--json", "--out", str(out)],
                          capture_output=True, text=True, timeout=120, check=False,
                          env={**os.environ, "TMPDIR": str(tmp_path)})
    assert proc.returncode == 0, proc.stderr
    (log,) = out.glob("*.h5")
    assert SECRET.encode() not in log.read_bytes()
    assert SECRET not in proc.stdout + proc.stderr
    assert read_log(log).attrs["config"]["mqtt"]["password"] == "**********"
