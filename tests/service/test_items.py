"""What a client submits is checked by its kind's own loader, with the command line's one-line error naming the
submitted file (hil.service.check_item; docs/service.md, "Items"), and stands on its own: it reads no file and no
environment variable of the service's, and no refusal quotes one (docs/service.md, "A submitted item stands on its
own")."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from hil.config import load_session
from hil.service import IDENT_OPTIONS, MAX_ITEM_BYTES, ItemError, check_item, item_text
from hil.service._worker import Running, Worker, campaign_on_ports

REPO = Path(__file__).resolve().parents[2]
SESSION = REPO / "profiles" / "sessions" / "swing-1deg-1hz-eso.yaml"
CAMPAIGN = REPO / "profiles" / "campaigns" / "swing-rate-error.yaml"
RULE = "outside the submitted item"


def as_submitted(**changes: Any) -> dict[str, Any]:
    """The session as `hil run --bench` sends it: loaded, its includes inline, without its ports and emulator."""
    data = yaml.safe_load(item_text(SESSION, "session")[1])
    data.update(changes)
    return data


def refusal(kind: str, body: str, file_name: str = "item.yaml", **kwargs: Any) -> str:
    with pytest.raises(ItemError) as exc:
        check_item(kind, file_name, body, **kwargs)
    message = str(exc.value)
    assert "\n" not in message and "hil-item-" not in message, message  # one line, never a path of the service's
    return message


def first_line(path: str) -> str:
    try:
        return Path(path).read_text().splitlines()[0]
    except (OSError, IndexError):
        pytest.skip(f"{path} is not readable here")


def test_a_session_as_loaded_stands_on_its_own() -> None:
    item = check_item("session", "swing.yaml", yaml.safe_dump(as_submitted()))
    assert (item.kind, item.name, item.options) == ("session", "swing-1deg-1hz-eso", {})
    assert item.config.profile == load_session(SESSION).profile
    assert item.config.controller == load_session(SESSION).controller


def test_a_bad_field_is_the_command_line_s_one_line_naming_the_submitted_file() -> None:
    message = refusal("session", yaml.safe_dump(as_submitted(duration_s=-1)), "swing.yaml")
    assert message.startswith("swing.yaml: duration_s:")


def test_a_file_that_leans_on_the_client_s_other_files_is_refused_by_name() -> None:
    text = SESSION.read_text()  # its controller, profile and limits are paths relative to it
    message = refusal("session", text, "swing.yaml")
    assert message.startswith("swing.yaml: ") and "controllers/eso.yaml" in message, message


@pytest.mark.parametrize(("kind", "name", "body", "message"), [
    ("plot", "a.yaml", "", r"^kind='plot': not session, ident, campaign$"),
    ("session", "a.txt", "", r"^a.txt: not a YAML file \(.yaml or .yml\)$"),
    ("session", "a.yaml", "x" * (1 << 20 + 1), r"^a.yaml: 2097152 bytes, more than the 1048576 an item may have$"),
    ("campaign", "c.yaml", "name: [", r"^c.yaml: "),
    ("session", "a\x00b.yaml", "name: a", r"^file_name 'a\\x00b.yaml': not a plain file name"),
    ("session", "é" * 250 + ".yaml", "name: a", r"^file_name 'é+\.\.\.': 505 bytes, more than the 100"),
    ("session", "mine/a.yaml", "name: a", r"^file_name 'mine/a.yaml': not a plain file name"),
    ("session", "a\nb.yaml", "name: a", r"^file_name 'a\\nb.yaml': not a plain file name"),
    ("session", "a.yaml", "name: \udc80", r"^a.yaml: body: not UTF-8 text"),
])
def test_what_is_not_an_item_is_refused(kind: str, name: str, body: str, message: str) -> None:
    with pytest.raises(ItemError, match=message):
        check_item(kind, name, body)


# --- the service's files and environment ---------------------------------------------------------------------------


@pytest.mark.parametrize("field", ["profile", "controller", "hexapod_limits"])
def test_a_section_named_by_a_path_of_the_service_s_is_refused_unread(field: str) -> None:
    shadow = first_line("/etc/shadow")  # root's test run reads it; the service must never show it
    message = refusal("session", yaml.safe_dump(as_submitted(**{field: "/etc/shadow"})))
    assert message.startswith(f"item.yaml: {field}: names /etc/shadow, {RULE}"), message
    assert shadow not in message and "root:" not in message


@pytest.mark.parametrize("path", ["/etc/hostname", "../../../../../../etc/hostname"])
def test_an_mqtt_password_file_of_the_service_s_is_refused_unread(path: str) -> None:
    hostname = first_line("/etc/hostname")
    mqtt = {"host": "127.0.0.1", "port": 1883, "username": "u", "password_file": path}
    message = refusal("session", yaml.safe_dump(as_submitted(mqtt=mqtt)))
    assert message.startswith(f"item.yaml: mqtt.password_file: names {path}, {RULE}"), message
    assert hostname not in message.replace("hostname", "")


def test_a_file_of_the_service_s_is_refused_unread_however_it_is_named(tmp_path: Path) -> None:
    secret = tmp_path / "secret.yaml"
    secret.write_text("marker-5d41402a: [\n")  # its text would show in a YAML error if it were read
    for named in (str(secret), "../" * 12 + str(secret.relative_to("/")), f"{tmp_path}/../{tmp_path.name}/secret.yaml"):
        message = refusal("session", yaml.safe_dump(as_submitted(profile=named)))
        assert f"profile: names {named}, {RULE}" in message and "marker" not in message, message


def test_an_environment_variable_of_the_service_s_is_refused_unread(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HIL_TEST_SECRET", "marker-7c4a8d09")
    for name in ("HOME", "HIL_TEST_SECRET"):
        mqtt = {"host": "127.0.0.1", "username": "u", "password_env": name}
        message = refusal("session", yaml.safe_dump(as_submitted(mqtt=mqtt)))
        assert message.startswith("item.yaml: mqtt.password_env: a submitted item reads no environment variable of "
                                  "the service's"), message
        assert "marker" not in message and os.environ["HOME"] not in message


def test_the_submitter_s_own_password_and_own_password_file_are_theirs() -> None:
    literal = {"host": "127.0.0.1", "username": "u", "password": "s3cret"}
    item = check_item("session", "item.yaml", yaml.safe_dump(as_submitted(mqtt=literal)))
    assert item.config.mqtt.password_value == "s3cret"
    own = {"host": "127.0.0.1", "username": "u", "password_file": "secrets/broker.txt"}
    item = check_item("session", "item.yaml", yaml.safe_dump(as_submitted(mqtt=own)),
                      files={"secrets/broker.txt": "hunter2\n"})
    assert item.config.mqtt.password_value == "hunter2"


def test_an_emulator_file_is_the_service_s_own() -> None:
    message = refusal("session", yaml.safe_dump(as_submitted(emulator={"config": "emu.yaml"})),
                      files={"emu.yaml": "plant: /etc/shadow\n"})
    assert message.startswith("item.yaml: emulator.config: a submitted item runs on the service's own lab"), message


# --- the item's own files ------------------------------------------------------------------------------------------


def test_sections_in_the_item_s_own_files_load_nested_and_confined() -> None:
    data = yaml.safe_load(SESSION.read_text())
    files = {"controllers/eso.yaml": (SESSION.parent / data["controller"]).read_text(),
             "swing/swing.yaml": (SESSION.parent / data["profile"]).read_text(),
             "hexapod/limits.yaml": (SESSION.parent / data["hexapod_limits"]).read_text()}
    data.update(controller="controllers/eso.yaml", profile="swing/swing.yaml", hexapod_limits="hexapod/limits.yaml")
    data.pop("emulator")
    item = check_item("session", "item.yaml", yaml.safe_dump(data), files=files)
    assert item.config.profile == load_session(SESSION).profile
    files["swing/swing.yaml"] = "segments: /etc/shadow\n"  # a section file is data, not a name: it is its own
    assert "swing/swing.yaml: segments:" in refusal("session", yaml.safe_dump(data), files=files)


@pytest.mark.parametrize(("files", "message"), [
    ({"../x.yaml": "a: 1"}, "files: '../x.yaml': not a relative name"),
    ({"/etc/x.yaml": "a: 1"}, "files: '/etc/x.yaml': not a relative name"),
    ({".hidden": "a: 1"}, "files: '.hidden': not a relative name"),
    ({"a/./b": "a: 1"}, "files: 'a/./b': not a relative name"),
    ({"a/b/c/d/e": "a: 1"}, "files: 'a/b/c/d/e': not a relative name of at most 4 levels"),
    ({"x" * 101: "a: 1"}, "not a relative name"),
    ({"a\x00b": "a: 1"}, "not a relative name"),
    ({"a": "x", "a/b": "y"}, "files: a is both a file and a folder of the item"),
    ({"item.yaml": "a: 1"}, "files: item.yaml is the item's file itself"),
    ({"a": "\ud800"}, "files: a: not UTF-8 text"),
    ({"a": b"bytes"}, "files: a: not text"),
    ({"a": "x" * MAX_ITEM_BYTES}, f"bytes, more than the {MAX_ITEM_BYTES} an item may have"),
    ({f"f{i}": "" for i in range(65)}, "files: 65 files, more than the 64"),
])
def test_the_item_s_own_files_are_plain_relative_names(files: dict[str, Any], message: str) -> None:
    assert message in refusal("session", yaml.safe_dump(as_submitted()), files=files)


# --- campaigns -----------------------------------------------------------------------------------------------------


def test_the_client_sends_a_campaign_with_its_session_and_profiles_as_its_own_files() -> None:
    file_name, body, files = item_text(CAMPAIGN, "campaign")
    data = yaml.safe_load(body)
    assert file_name == "swing-rate-error.yaml" and data["session"] == "session.yaml"
    assert sorted(files) == ["profiles/swing-1deg-1hz.yaml", "session.yaml"]
    assert [p["path"] for p in data["profiles"]] == ["profiles/swing-1deg-1hz.yaml"] * len(data["profiles"])
    assert files["profiles/swing-1deg-1hz.yaml"] == (REPO / "profiles/swing/swing-1deg-1hz.yaml").read_text()
    session = yaml.safe_load(files["session.yaml"])
    assert "ports" not in session and "emulator" not in session and "dir" not in session["logging"]
    assert str(REPO) not in body + "".join(files.values())  # nothing names a file of the client's
    item = check_item("campaign", file_name, body, files=files)
    assert item.kind == "campaign" and item.name == "swing-rate-error"


def test_a_campaign_naming_a_path_of_the_service_s_is_refused_naming_the_field() -> None:
    _name, body, files = item_text(CAMPAIGN, "campaign")
    data = yaml.safe_load(body)
    message = refusal("campaign", yaml.safe_dump({**data, "session": str(SESSION)}), "c.yaml", files=files)
    assert message.startswith(f"c.yaml: session: names {SESSION}, {RULE}"), message
    profiles = [{**data["profiles"][0], "path": "/etc/shadow"}]
    message = refusal("campaign", yaml.safe_dump({**data, "profiles": profiles}), "c.yaml", files=files)
    assert message.startswith(f"c.yaml: profiles.0.path: names /etc/shadow, {RULE}"), message
    as_written = CAMPAIGN.read_text()  # its session and profiles relative to a folder the item does not have
    assert refusal("campaign", as_written, "c.yaml").startswith("c.yaml: session: names ../sessions/")


@pytest.mark.parametrize(("where", "change", "field"), [
    ("session", {"mqtt": {"host": "h", "password_file": "/etc/hostname"}}, "session: session.yaml: mqtt.password_file"),
    ("session", {"mqtt": {"host": "h", "password_env": "HOME"}}, "session: session.yaml: mqtt.password_env"),
    ("session", {"hexapod_limits": "/etc/shadow"}, "session: session.yaml: hexapod_limits"),
    ("overrides", {"hexapod_limits": "/etc/shadow"}, "hexapod_limits: names /etc/shadow"),
    ("overrides", {"hexapod_limits": "session.yaml"}, "hexapod_limits: names session.yaml, relative to no file"),
    ("overrides", {"mqtt": {"host": "h", "password_file": "/etc/hostname"}}, "mqtt.password_file"),
    ("overrides", {"emulator": {"config": "/etc/shadow"}}, "emulator.config"),
])
def test_a_campaign_s_session_and_overrides_are_confined_too(where: str, change: dict[str, Any], field: str) -> None:
    file_name, body, files = item_text(CAMPAIGN, "campaign")
    if where == "session":
        files = {**files, "session.yaml": yaml.safe_dump({**yaml.safe_load(files["session.yaml"]), **change})}
    else:
        body = yaml.safe_dump({**yaml.safe_load(body), "overrides": change})
    message = refusal("campaign", body, file_name, files=files)
    assert field in message and "root:" not in message and first_line("/etc/hostname") not in message.replace(
        "hostname", ""), message


def test_a_campaign_on_the_lab_s_hardware_opens_the_lab_s_ports() -> None:
    ports = {"servo": {"port": "/dev/ttyS1", "baudrate": 921600}, "driver": {"port": "/dev/ttyS2"},
             "image": {"port": "/dev/ttyS3"}}
    data = yaml.safe_load(campaign_on_ports(yaml.safe_dump({"name": "c", "overrides": {
        "tracking": {"enabled": False}, "ports": {"hexapod": {"port": "/dev/sda"}}}}), ports))
    assert data["overrides"] == {"tracking": {"enabled": False}, "ports": {**ports, "hexapod": None}}


# --- options -------------------------------------------------------------------------------------------------------


def test_ident_options_are_checked_when_submitted() -> None:
    body = yaml.safe_dump(as_submitted())
    item = check_item("ident", "item.yaml", body, options={"axis": "az", "sweep_s": 10, "level": False})
    assert item.options == {"axis": "az", "sweep_s": 10.0, "level": False}
    assert set(IDENT_OPTIONS) == {"axis", "f_start_hz", "f_stop_hz", "sweep_s", "amplitude_dps", "offset_dps",
                                  "level"}
    for options, message in [
        ({"f_start_hz": "abc"}, "options: f_start_hz: Input should be a valid number"),
        ({"f_start_hz": float("nan")}, "options: f_start_hz:"),
        ({"f_stop_hz": 500.0}, "options: f_stop_hz: Input should be less than or equal to 450"),
        ({"amplitude_dps": 0}, "options: amplitude_dps: Input should be greater than 0"),
        ({"offset_dps": -201}, "options: offset_dps: Input should be greater than or equal to -200"),
        ({"axis": "roll"}, "options: axis: Input should be 'el' or 'az'"),
        ({"level": "yes"}, "options: level: Input should be a valid boolean"),
        ({"f_start_hz": 5, "f_stop_hz": 5}, "options: f_stop_hz must differ from f_start_hz"),
        ({"seed": 3}, "options: seed: Extra inputs are not permitted"),
        (["axis"], "options: not a mapping"),
    ]:
        got = refusal("ident", body, options=options)
        assert got.startswith("options: ") and message in got, (options, got)


@pytest.mark.parametrize("kind", ["session", "campaign"])
def test_a_session_or_a_campaign_takes_no_options(kind: str) -> None:
    file_name, body, files = item_text(CAMPAIGN if kind == "campaign" else SESSION, kind)
    assert check_item(kind, file_name, body, files=files, options={}).options == {}
    message = refusal(kind, body, file_name, files=files, options={"axis": "el"})
    assert message == "options: axis: Extra inputs are not permitted (got 'el')"


# --- the worker checks it again ------------------------------------------------------------------------------------


class Lines:
    def __init__(self) -> None:
        self.sent: list[tuple[str, dict[str, Any]]] = []

    def send(self, event: str, **body: Any) -> None:
        self.sent.append((event, body))


def test_the_worker_checks_the_item_again_with_its_files_and_options(tmp_path: Path) -> None:
    out = Lines()
    worker = Worker(state_dir=tmp_path, loopback=True, lab_session=None, emulator=None, seed=0,
                    outbox=out)  # type: ignore[arg-type]
    mqtt = {"host": "127.0.0.1", "password_file": "/etc/hostname"}
    items = ({"uid": "u1", "kind": "session", "file_name": "s.yaml", "body": yaml.safe_dump(as_submitted(mqtt=mqtt))},
             {"uid": "u2", "kind": "ident", "file_name": "s.yaml", "body": yaml.safe_dump(as_submitted()),
              "options": {"f_start_hz": "abc"}},
             {"uid": "u3", "kind": "campaign", "file_name": "c.yaml", "body": CAMPAIGN.read_text(), "files": {}})

    async def run(item: dict[str, Any]) -> None:
        worker.run(item)
        assert worker.item_task is not None
        await worker.item_task

    for item in items:
        asyncio.run(run(item))
    assert [(e, b["uid"], b["status"]) for e, b in out.sent] == [("done", u, "invalid") for u in ("u1", "u2", "u3")]
    messages = [b["message"] for _, b in out.sent]
    assert messages[0].startswith("s.yaml: mqtt.password_file: names /etc/hostname")
    assert messages[1].startswith("options: f_start_hz:") and messages[2].startswith("c.yaml: session:")
    assert not (tmp_path / "runs").exists()  # nothing ran, nothing was written


def test_the_service_s_own_broker_carries_its_password_to_every_session_item(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """`hil serve --mqtt FILE`: the worker reads the broker's password from the service's own configuration and
    every session item publishes there with it, whatever mqtt section the item had."""
    secret = tmp_path / "broker-password"
    secret.write_text("s3cret-of-the-service\n")
    broker = tmp_path / "broker.yaml"
    broker.write_text("host: 127.0.0.1\nport: 18830\nusername: lab\npassword_file: broker-password\n")
    worker = Worker(state_dir=tmp_path, loopback=True, lab_session=None, emulator=None, seed=0,
                    outbox=Lines(), mqtt=broker)  # type: ignore[arg-type]
    seen: list[Any] = []

    def fake_run(config: Any, **_: Any) -> Any:
        seen.append(config.mqtt)
        raise ValueError("not run here")

    monkeypatch.setattr("hil.service._worker.api.run", fake_run)
    item = check_item("session", "s.yaml", yaml.safe_dump(as_submitted(mqtt={"host": "10.0.0.9", "port": 1})))
    with pytest.raises(ValueError, match="not run here"):
        worker._run_session(Running("u", "session"), item.config, "session", tmp_path, {})
    assert (seen[0].host, seen[0].port, seen[0].username) == ("127.0.0.1", 18830, "lab")
    assert seen[0].password_value == "s3cret-of-the-service"


def test_a_bad_service_broker_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    broker = tmp_path / "broker.yaml"
    broker.write_text("host: 127.0.0.1\nport: 99999\n")
    run = subprocess.run([sys.executable, "-m", "hil", "serve", "--loopback", "--mqtt", str(broker), "--state-dir",
                          str(tmp_path / "state")], capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert "--mqtt" in run.stderr and "broker.yaml: port" in run.stderr
    assert not (tmp_path / "state").exists()


def test_a_session_that_cannot_run_on_an_emulated_realtime_lab_is_refused_when_submitted() -> None:
    """swing-1deg-1hz-eso.yaml has no emulator stall grace: on the service's emulated lab (real time, the PC's shared
    CPUs) its 5 ms watchdog trips at the emulator's first scheduling stall, so it faulted every time it ran there."""
    body = yaml.safe_dump(as_submitted())
    message = refusal("session", body, "swing.yaml", emulated=True)
    assert message.startswith("swing.yaml: safety.emulator_stall_grace_ms: 0 cannot run on this service's emulated")
    assert "clock='lockstep'" in message
    assert check_item("session", "swing.yaml", body).name == "swing-1deg-1hz-eso"  # a lab's service runs it
    graced = yaml.safe_dump(as_submitted(safety={"watchdog_ms": 5, "emulator_stall_grace_ms": 500}))
    assert check_item("session", "swing.yaml", graced, emulated=True).config.safety.emulator_stall_grace_ms == 500
