"""What a client submits: the text of a YAML file the command line takes, with the item's own files (a campaign's
session and profiles) and its options, checked by that kind's own loader when it is submitted and again just before
it runs (docs/service.md, "Items").

A submitted item stands on its own (docs/service.md, "A submitted item stands on its own"): its files are written
into a fresh directory and loaded confined to it (:func:`hil.config.confined_to`), so a field that names a file
outside them (an absolute path, ``..``) or an environment variable of the service's is refused by name before
anything is opened, and no refusal can quote a file of the service's.
"""

from __future__ import annotations

import re
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hil.analysis import IDENT_SWEEP, SweptSine
from hil.campaign import CampaignConfig, cell_session, load_campaign
from hil.config import SwingProfile, confined_to, load_model, load_session, one_line
from hil.service._store import ITEM_KINDS, StoreError

MAX_ITEM_BYTES = 1 << 20  # the file and its own files, together
MAX_ITEM_FILES = 64  # the item's own files
MAX_NAME_BYTES = 100  # a file name, or the name of one of the item's files (its folders included), in UTF-8
MAX_FILE_LEVELS = 4  # folders and name of one of the item's files: profiles/swing.yaml is 2
_SEGMENT = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")  # a plain name that does not start with '.'


def _load_campaign(path: Path) -> CampaignConfig:
    """A campaign, its base session, its profiles and its cells as they will load them (one cell a profile: the
    same overrides, each profile's envelope), so a file any of them names is checked where it is named."""
    config = load_campaign(path)
    try:
        base = load_session(config.session)
    except ValueError as exc:
        raise ValueError(f"session: {exc}") from None
    for i, entry in enumerate(config.profiles):
        try:
            load_model(SwingProfile, entry.path)
        except ValueError as exc:
            raise ValueError(f"profiles.{i}.path: {exc}") from None
    first: dict[str, Any] = {}
    for spec in config.cells():
        first.setdefault(spec.profile.label, spec)
    for spec in first.values():
        cell_session(config, spec, path.parent / "cells" / spec.cell_id, base=base)
    return config


LOADERS: dict[str, Callable[[Path], Any]] = {"session": load_session, "ident": load_session,
                                             "campaign": _load_campaign}


class ItemError(StoreError):
    """A submitted file that its kind's loader refuses: the loader's one line, naming the submitted file's name
    (HTTP 422, exit 2 at the client)."""


class NoOptions(BaseModel):
    """A session's or a campaign's options: none."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class IdentOptions(BaseModel):
    """An ident item's options: :func:`hil.api.ident`'s keyword parameters, within the bounds it and
    :class:`hil.analysis.SweptSine` hold them to (the sweep itself is built here, so what it refuses is refused
    when the item is submitted)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    axis: Literal["el", "az"] = "el"
    f_start_hz: float = Field(IDENT_SWEEP.f_start_hz, gt=0, le=450)
    f_stop_hz: float = Field(IDENT_SWEEP.f_stop_hz, gt=0, le=450)
    sweep_s: float = Field(IDENT_SWEEP.duration_s, gt=0, le=3600)
    amplitude_dps: float = Field(IDENT_SWEEP.amplitude_dps, gt=0, le=200)
    offset_dps: float = Field(IDENT_SWEEP.offset_dps, ge=-200, le=200)
    level: bool = True

    @model_validator(mode="after")
    def _a_sweep(self) -> IdentOptions:
        SweptSine(f_start_hz=self.f_start_hz, f_stop_hz=self.f_stop_hz, duration_s=self.sweep_s,
                  amplitude_dps=self.amplitude_dps, axis=self.axis, offset_dps=self.offset_dps)
        return self


OPTIONS: dict[str, type[BaseModel]] = {"session": NoOptions, "ident": IdentOptions, "campaign": NoOptions}
IDENT_OPTIONS = tuple(IdentOptions.model_fields)  # hil.api.ident's options an ident item may carry


@dataclass(frozen=True)
class CheckedItem:
    kind: str
    name: str
    config: Any
    options: dict[str, Any] = field(default_factory=dict)  # as given, checked: the keyword arguments of its run


def _shown(text: str, limit: int = 80) -> str:
    shown = repr(text)
    return shown if len(shown) <= limit else shown[: limit - 4] + "...'"


def _utf8(what: str, text: Any) -> int:
    """The size of ``text`` in UTF-8; ItemError naming ``what`` if it is not text that UTF-8 can hold."""
    if not isinstance(text, str):
        raise ItemError(f"{what}: not text")
    try:
        return len(text.encode("utf-8"))
    except UnicodeEncodeError as exc:
        raise ItemError(f"{what}: not UTF-8 text (character {exc.start}: a lone surrogate)") from None


def _check_file_name(file_name: Any) -> str:
    if not isinstance(file_name, str) or not file_name:
        raise ItemError("file_name: not a file name")
    size = _utf8("file_name", file_name)
    if "/" in file_name or file_name in (".", "..") or not file_name.isprintable():
        raise ItemError(f"file_name {_shown(file_name)}: not a plain file name (no '/', no control characters)")
    if size > MAX_NAME_BYTES:
        raise ItemError(f"file_name {_shown(file_name)}: {size} bytes, more than the {MAX_NAME_BYTES} a name may have")
    if not file_name.endswith((".yaml", ".yml")):
        raise ItemError(f"{file_name}: not a YAML file (.yaml or .yml)")
    return file_name


def _check_own_files(file_name: str, files: Any) -> dict[str, str]:
    """The item's own files, their names checked: relative POSIX paths of plain names, none the item's file."""
    if not isinstance(files, dict):
        raise ItemError("files: not a mapping of names to texts")
    if len(files) > MAX_ITEM_FILES:
        raise ItemError(f"files: {len(files)} files, more than the {MAX_ITEM_FILES} an item may have")
    for name in files:
        if not isinstance(name, str):
            raise ItemError(f"files: {_shown(str(name))}: not a file name")
        size = _utf8(f"files: {_shown(name)}", name)
        parts = name.split("/")
        if size > MAX_NAME_BYTES or len(parts) > MAX_FILE_LEVELS or not all(_SEGMENT.fullmatch(p) for p in parts):
            raise ItemError(f"files: {_shown(name)}: not a relative name of at most {MAX_FILE_LEVELS} levels of plain "
                            f"names (A-Z a-z 0-9 _ . -, none starting with '.'), {MAX_NAME_BYTES} bytes in all")
    folders = {str(p) for name in files for p in PurePosixPath(name).parents if str(p) != "."}
    clash = sorted(folders & ({*files, file_name}))
    if clash:
        raise ItemError(f"files: {clash[0]} is both a file and a folder of the item")
    if file_name in files:
        raise ItemError(f"files: {file_name} is the item's file itself")
    return files


def _check_options(kind: str, options: Any) -> dict[str, Any]:
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ItemError("options: not a mapping")
    try:
        checked = OPTIONS[kind].model_validate(options)
    except ValidationError as exc:
        raise ItemError(one_line("options", exc)) from None
    return checked.model_dump(exclude_unset=True)


def write_item(directory: Path, file_name: str, body: str, files: dict[str, str]) -> Path:
    """Write an item's file and its own files (their relative names kept, folders made) into ``directory``; the
    item's file's path. The names are :func:`check_item`'s."""
    for name, text in files.items():
        path = directory.joinpath(*name.split("/"))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    path = directory / file_name
    path.write_text(body, encoding="utf-8")
    return path


def check_item(kind: str, file_name: str, body: str, *, files: dict[str, str] | None = None,
               options: dict[str, Any] | None = None, emulated: bool = False) -> CheckedItem:
    """Load ``body`` as ``file_name`` of ``kind`` with the item's own ``files`` (name -> text), exactly as the command
    line would load that file, confined to those files (:func:`hil.config.confined_to`), and check ``options``;
    ItemError with the loader's one-line message (naming ``file_name`` and the field, never a path of the
    service's, never a line of a file of the service's) if it does not load. ``emulated``: the service's lab is the
    emulated one on the realtime clock; a session that cannot run on it is refused (:func:`require_realtime_grace`)."""
    if kind not in ITEM_KINDS:
        raise ItemError(f"kind={kind!r}: not {', '.join(ITEM_KINDS)}")
    file_name = _check_file_name(file_name)
    own = _check_own_files(file_name, files or {})
    size = _utf8(f"{file_name}: body", body) + sum(_utf8(f"files: {name}", text) for name, text in own.items())
    if size > MAX_ITEM_BYTES:
        raise ItemError(f"{file_name}: {size} bytes, more than the {MAX_ITEM_BYTES} an item may have")
    chosen = _check_options(kind, options)
    with tempfile.TemporaryDirectory(prefix="hil-item-") as tmp:
        root = Path(tmp).resolve()
        try:
            path = write_item(root, file_name, body, own)
        except OSError as exc:
            raise ItemError(f"{file_name}: cannot be written as given ({exc.strerror or type(exc).__name__})") from None
        try:
            with confined_to(root):
                config = LOADERS[kind](path)
        except (ValueError, TypeError, RecursionError) as exc:  # TypeError: a loader tripped on a malformed value
            message = " ".join(str(exc).split()).replace(str(path), file_name)
            for where in (root, Path(tmp)):
                message = message.replace(f"{where}/", "").replace(str(where), ".")
            raise ItemError(message if message.startswith(f"{file_name}:") else f"{file_name}: {message}") from None
    if emulated and kind in ("session", "ident"):
        require_realtime_grace(file_name, config)
    return CheckedItem(kind, str(config.name), config, chosen)


def require_realtime_grace(file_name: str, config: Any) -> None:
    """A session on the service's emulated lab runs in real time beside the service on the PC's shared CPUs: without
    ``safety.emulator_stall_grace_ms`` its watchdog trips the first time the emulator is not scheduled within
    ``safety.watchdog_ms``, so it would fault, not measure; refused with that reason (ItemError)."""
    safety = config.safety
    if safety.emulator_stall_grace_ms == 0:
        raise ItemError(f"{file_name}: safety.emulator_stall_grace_ms: 0 cannot run on this service's emulated lab, "
                        "which runs in real time on the PC's shared CPUs: its watchdog "
                        f"({safety.watchdog_ms:g} ms) would trip the first time the emulator is not scheduled in "
                        "time; give the session a grace (profiles/sessions/demo.yaml has 500 ms), or run it on your "
                        "own emulated lab on the lockstep clock (loopback=True, clock='lockstep')")

