"""A load confined to a directory (hil.config.confined_to: a submitted item's own files) reads nothing outside it and
no environment variable, and says so by field before anything is opened; a load that is not confined is as it
always was (docs/service.md, "A submitted item stands on its own")."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import ValidationInfo, field_validator

from hil.api import check_file
from hil.config import (
    PROFILES,
    ConfigError,
    EmulatorRef,
    MqttConfig,
    Strict,
    confined_to,
    confinement,
    load_model,
    load_session,
    resolve_relative,
)

OUTSIDE = "outside the submitted item"


class Inner(Strict):
    secret: Path

    _rel = field_validator("secret", mode="before")(resolve_relative)


class Outer(Strict):
    inner: Inner

    @field_validator("inner", mode="before")
    @classmethod
    def _include(cls, value: Any, info: ValidationInfo) -> Any:
        return load_model(Inner, resolve_relative(value, info)) if isinstance(value, str) else value


def write(path: Path, data: Any) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return path


@pytest.fixture
def item(tmp_path: Path) -> Path:
    """An item's directory beside a secret it must not read (its text would show in a YAML error)."""
    write(tmp_path / "secret.yaml", "marker-0cc175b9: [\n")
    root = tmp_path / "item"
    write(root / "sub" / "own.txt", "mine\n")
    return root


def confined_error(root: Path, model: type[Any], data: dict[str, Any], base: Path) -> str:
    with confined_to(root), pytest.raises(ValueError) as exc:
        model.model_validate(data, context={"base_dir": base})
    message = " ".join(str(exc.value).split())
    assert "marker" not in message
    return message


@pytest.mark.parametrize("named", ["{outside}/secret.yaml", "../secret.yaml", "sub/../../secret.yaml",
                                   "link/secret.yaml", "/etc/passwd"])
def test_a_path_that_leaves_the_directory_is_refused_by_field_unopened(item: Path, named: str) -> None:
    (item / "link").symlink_to(item.parent)  # a symlink inside that points out
    named = named.format(outside=item.parent)
    message = confined_error(item, Inner, {"secret": named}, item)
    assert f"secret Value error, names {named}, {OUTSIDE}" in message, message


def test_a_path_inside_the_directory_resolves_as_always(item: Path) -> None:
    with confined_to(item) as root:
        assert root == item.resolve() and confinement() == root
        got = Inner.model_validate({"secret": "../sub/own.txt"}, context={"base_dir": item / "sub"})
    assert confinement() is None
    assert got.secret == item.resolve() / "sub" / "own.txt"


def test_a_relative_path_with_no_file_to_be_relative_to_is_refused(item: Path) -> None:
    with confined_to(item), pytest.raises(ValueError, match=r"names sub/own\.txt, relative to no file"):
        Inner.model_validate({"secret": "sub/own.txt"})


def test_a_file_named_by_a_file_named_by_the_item_stays_confined(item: Path) -> None:
    write(item / "a" / "inner.yaml", {"secret": "../../secret.yaml"})  # one level further out than the item
    write(item / "outer.yaml", {"inner": "a/inner.yaml"})
    with confined_to(item), pytest.raises(ConfigError) as exc:
        load_model(Outer, item / "outer.yaml")
    assert f"inner.yaml: secret: names ../../secret.yaml, {OUTSIDE}" in str(exc.value), exc.value
    assert "marker" not in str(exc.value)
    write(item / "a" / "inner.yaml", {"secret": "../sub/own.txt"})
    with confined_to(item):
        assert load_model(Outer, item / "outer.yaml").inner.secret == item.resolve() / "sub" / "own.txt"


def test_the_confinement_ends_with_its_block_even_on_an_error(item: Path) -> None:
    with pytest.raises(RuntimeError), confined_to(item):
        raise RuntimeError
    assert confinement() is None
    assert Inner.model_validate({"secret": "../secret.yaml"}, context={"base_dir": item}).secret == (
        item.parent / "secret.yaml").resolve()


def test_mqtt_reads_no_environment_variable_while_confined(item: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HIL_TEST_BROKER", "marker-92eb5ffe")
    assert MqttConfig(host="h", password_env="HIL_TEST_BROKER").password_value == "marker-92eb5ffe"
    message = confined_error(item, MqttConfig, {"host": "h", "password_env": "HIL_TEST_BROKER"}, item)
    assert "password_env" in message and "reads no environment variable of the service's" in message
    password = item / "sub" / "own.txt"
    message = confined_error(item, MqttConfig, {"host": "h", "password_file": str(item.parent / "secret.yaml")}, item)
    assert "password_file" in message and OUTSIDE in message
    with confined_to(item):
        assert MqttConfig.model_validate({"host": "h", "password_file": "sub/own.txt"},
                                         context={"base_dir": item}).password_value == "mine"
    assert password.read_text() == "mine\n"


def test_the_emulator_is_the_default_one_while_confined(item: Path) -> None:
    default = PROFILES / "emulator" / "default.yaml"
    with confined_to(item):
        assert EmulatorRef.model_validate({"config": str(default)}).config == default
    message = confined_error(item, EmulatorRef, {"config": "sub/own.txt"}, item)
    assert "names no emulator file" in message
    assert EmulatorRef.model_validate({"config": "rigid.yaml"}, context={"base_dir": PROFILES / "emulator"}).config == (
        PROFILES / "emulator" / "rigid.yaml")


@pytest.mark.parametrize("path", sorted((PROFILES / "sessions").glob("*.yaml")) + sorted(
    (PROFILES / "campaigns").glob("*.yaml")), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_the_shipped_files_load_as_before_when_not_confined(path: Path) -> None:
    assert confinement() is None
    checked = check_file(path)  # what `hil check` does
    assert checked["kind"] in ("session", "campaign")
    if checked["kind"] == "session":
        config = load_session(path)
        assert config.emulator.config.is_absolute() and config.emulator.config.is_file()


def test_a_session_names_files_relative_to_itself_or_absolutely_when_not_confined(tmp_path: Path) -> None:
    shipped = yaml.safe_load((PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml").read_text())
    data = {**shipped, "profile": str((PROFILES / "sessions" / shipped["profile"]).resolve()),
            "controller": os.path.relpath(PROFILES / "sessions" / shipped["controller"], tmp_path),
            "hexapod_limits": os.path.relpath(PROFILES / "sessions" / shipped["hexapod_limits"], tmp_path)}
    data.pop("emulator")
    config = load_session(write(tmp_path / "s.yaml", data))
    assert config == load_session(PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml").model_copy(
        update={"emulator": config.emulator})
