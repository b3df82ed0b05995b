"""Choosing the hexapod driver in a session file: the entry-point registry, the protocol default, the hexapod port,
and one line naming the field for a driver that is not installed or an option it does not take."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hil.boards import HEXAPOD_DRIVERS, HexapodOptions, ProtocolHexapod, installed_hexapod_drivers, load_hexapod_driver
from hil.config import PROFILES, ConfigError, SessionConfig, load_session
from tests.boards.drivers import RecordingHexapod, RecordingOptions

PORTS3 = "ports: {servo: {port: /dev/ttyS0}, driver: {port: /dev/ttyS1}, image: {port: /dev/ttyS2}}\n"


def session_file(tmp_path: Path, hexapod: str | None = None, extra: str = "", name: str = "s.yaml") -> Path:
    """A short session file (the shipped controller, swing and envelope) with ``hexapod: <hexapod>``."""
    text = (f"name: hexapod-driver-check\nduration_s: 0.5\nseed: 3\n"
            f"controller: {PROFILES / 'controllers' / 'eso.yaml'}\n"
            f"profile: {PROFILES / 'swing' / 'swing-1deg-1hz.yaml'}\n"
            f"hexapod_limits: {PROFILES / 'hexapod' / 'default.yaml'}\n"
            f"emulator: {{config: {PROFILES / 'emulator' / 'default.yaml'}}}\n")
    if hexapod is not None:
        text += f"hexapod: {hexapod}\n"
    path = tmp_path / name
    path.write_text(text + extra)
    return path


def config_error(path: Path) -> str:
    with pytest.raises(ConfigError) as err:
        load_session(path)
    return str(err.value)


def test_the_protocol_driver_is_registered_through_the_entry_point_and_is_the_default(tmp_path: Path) -> None:
    ep = installed_hexapod_drivers()["protocol"]
    assert (ep.group, ep.value) == (HEXAPOD_DRIVERS, "hil.boards:ProtocolHexapod") == ("hil.hexapod_drivers",
                                                                                       "hil.boards:ProtocolHexapod")
    assert ep.load() is ProtocolHexapod is load_hexapod_driver("protocol")
    assert ProtocolHexapod.uses_link is True and ProtocolHexapod.Options is HexapodOptions

    absent = load_session(session_file(tmp_path, None, name="absent.yaml"))
    explicit = load_session(session_file(tmp_path, "{driver: protocol}", name="explicit.yaml"))
    assert absent.hexapod.driver == explicit.hexapod.driver == "protocol"
    assert absent.hexapod.driver_class is explicit.hexapod.driver_class is ProtocolHexapod
    assert absent.model_dump(mode="json") == explicit.model_dump(mode="json")
    assert absent.model_dump(mode="json")["hexapod"] == {"driver": "protocol"}
    for shipped in sorted((PROFILES / "sessions").glob("*.yaml")):  # every session file keeps working unchanged
        assert load_session(shipped).hexapod.driver_class is ProtocolHexapod, shipped


def test_an_unknown_driver_is_one_line_naming_hexapod_driver_and_the_installed_ones(tmp_path: Path,
                                                                                    test_drivers: object) -> None:
    path = session_file(tmp_path, "{driver: vendor_x, host: 10.0.0.7}")
    assert config_error(path) == (f"{path}: hexapod.driver: 'vendor_x' is not an installed hexapod driver "
                                  "(installed: incomplete, missing, not_a_driver, protocol, recording)")


@pytest.mark.parametrize(("name", "why"), [
    ("not_a_driver", "'not_a_driver' (tests.boards.drivers:NotADriver) is not a hil.boards.HexapodDriver subclass"),
    ("incomplete", "'incomplete' (tests.boards.drivers:IncompleteHexapod) does not implement running, start, stop"),
    ("missing", "'missing' (tests.boards.no_such_module:Driver) cannot be loaded: ModuleNotFoundError: "
                "No module named 'tests.boards.no_such_module'"),
])
def test_an_entry_point_that_is_no_driver_is_refused_when_the_session_is_read(tmp_path: Path, test_drivers: object,
                                                                              name: str, why: str) -> None:
    path = session_file(tmp_path, f"{{driver: {name}}}")
    assert config_error(path) == f"{path}: hexapod.driver: {why}"


@pytest.mark.parametrize(("hexapod", "why"), [
    ("{driver: recording, pitch_deg: 45}", "hexapod.pitch_deg: Input should be less than or equal to 10 (got 45)"),
    ("{driver: recording, pitch_deg: .nan}", "hexapod.pitch_deg: Input should be a finite number (got nan)"),
    ("{driver: recording, pitch: 1}", "hexapod.pitch: Extra inputs are not permitted (got 1)"),
    ("{driver: recording, label: [a]}", "hexapod.label: Input should be a valid string"),
    ("{driver: protocol, baudrate: 9600}", "hexapod.baudrate: Extra inputs are not permitted (got 9600)"),
    ("{driver: ''}", "hexapod.driver: String should have at least 1 character (got '')"),
    ("[protocol]", "hexapod: Input should be a valid dictionary or instance of HexapodConfig"),
])
def test_bad_driver_options_are_one_line_naming_the_field(tmp_path: Path, test_drivers: object, hexapod: str,
                                                          why: str) -> None:
    path = session_file(tmp_path, hexapod)
    assert config_error(path).startswith(f"{path}: {why}")


def test_options_reach_the_driver_validated(tmp_path: Path, test_drivers: object) -> None:
    config = load_session(session_file(tmp_path, "{driver: recording, pitch_deg: -2.5, label: table-3}"))
    assert config.hexapod.driver_class is RecordingHexapod
    assert config.hexapod.options == RecordingOptions(pitch_deg=-2.5, label="table-3")
    # dumps (the log's `config` attribute) hold the validated options, defaults included
    assert config.model_dump(mode="json")["hexapod"] == {"driver": "recording", "pitch_deg": -2.5, "label": "table-3",
                                                         "token": None}
    assert repr(config.hexapod) == "HexapodConfig(driver='recording', pitch_deg=-2.5, label='table-3', token=None)"


def test_a_secret_option_is_in_no_dump_and_still_reaches_the_driver(tmp_path: Path, test_drivers: object) -> None:
    secret = "hunter2-s3cret"
    config = load_session(session_file(tmp_path, f"{{driver: recording, token: {secret}}}"))
    assert config.hexapod.options.token.get_secret_value() == secret
    dumps = [json.dumps(config.model_dump(mode="json")), str(config.model_dump()), config.model_dump_json(),
             repr(config), str(config)]
    assert not [d for d in dumps if secret in d]
    assert config.model_dump(mode="json")["hexapod"]["token"] == "**********"
    again = SessionConfig.model_validate(config.model_dump())  # what the test helpers and `hil ident` do
    assert again.hexapod.options.token.get_secret_value() == secret


def test_ports_hexapod_is_needed_only_by_a_driver_on_the_bench_link(tmp_path: Path, test_drivers: object) -> None:
    path = session_file(tmp_path, None, PORTS3)
    assert config_error(path) == (f"{path}: ports.hexapod: the hexapod driver 'protocol' talks over the bench's "
                                  "hexapod link; give its serial port")
    software = load_session(session_file(tmp_path, "{driver: recording}", PORTS3, name="sw.yaml"))
    assert software.ports is not None and software.ports.hexapod is None
    four = load_session(session_file(tmp_path, None, PORTS3.replace("}}\n", "}, hexapod: {port: /dev/ttyS3}}\n"),
                                     name="four.yaml"))
    assert four.ports is not None and four.ports.hexapod is not None and four.ports.hexapod.port == "/dev/ttyS3"


def _hil(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True, cwd=cwd, check=False,
                          timeout=120)


def test_the_cli_exits_2_with_one_line_for_an_unknown_driver_or_a_bad_option(tmp_path: Path) -> None:
    unknown = session_file(tmp_path, "{driver: vendor_x}", name="unknown.yaml")
    res = _hil("run", str(unknown), "--loopback", "--clock", "sim", "--out", str(tmp_path / "runs"), cwd=tmp_path)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert f"error: {unknown}: hexapod.driver: 'vendor_x' is not an installed hexapod driver (installed: " in lines[0]
    assert "protocol" in lines[0].split("(installed: ")[1]
    bad = session_file(tmp_path, "{driver: protocol, host: 10.0.0.7}", name="bad.yaml")
    res = _hil("run", str(bad), "--loopback", "--clock", "sim", "--out", str(tmp_path / "runs"), cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        f"error: {bad}: hexapod.host: Extra inputs are not permitted (got '10.0.0.7')"], res.stderr
    assert not (tmp_path / "runs").exists()  # refused before anything started


def test_a_campaign_refuses_a_secret_driver_option_a_cell_file_would_hold_masked(tmp_path: Path,
                                                                                  test_drivers: object) -> None:
    import yaml

    from hil.campaign import CampaignError, load_campaign
    from hil.campaign.runner import cell_sessions

    session = session_file(tmp_path, "{driver: recording, token: hunter2-s3cret}")
    campaign = tmp_path / "c.yaml"
    campaign.write_text(yaml.safe_dump({
        "name": "secret-check", "title": "t", "session": str(session), "metrics": ["rate_err_el_std_dps"],
        "profiles": [{"label": "1 deg", "path": str(PROFILES / "swing" / "swing-1deg-1hz.yaml")}],
        "controllers": [{"label": "ESO", "name": "eso"}], "seeds": [1]}))
    with pytest.raises(CampaignError, match=r"hexapod\.token: each cell's session file would hold it"):
        cell_sessions(load_campaign(campaign), tmp_path / "out")
    assert not (tmp_path / "out").exists()
