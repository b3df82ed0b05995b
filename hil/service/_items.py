"""What a client submits: the text of a YAML file the command line takes, checked by that kind's own loader when
it is submitted and again just before it runs (docs/service.md, "Items").

A submitted file must stand on its own: the service cannot see the client's other files, so a path in it that is
relative is read next to nothing and refused by name. A client sends a session as loaded (its
controller, profile and limits inline), which always stands on its own.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.campaign import load_campaign
from hil.config import load_session, require_regular_file
from hil.service._store import ITEM_KINDS, StoreError

MAX_ITEM_BYTES = 1 << 20

LOADERS: dict[str, Callable[[Path], Any]] = {"session": load_session, "ident": load_session,
                                             "campaign": load_campaign}


class ItemError(StoreError):
    """A submitted file that its kind's loader refuses: the loader's one line, naming the submitted file's name
    (HTTP 422, exit 2 at the client)."""


@dataclass(frozen=True)
class CheckedItem:
    kind: str
    name: str
    config: Any


def check_item(kind: str, file_name: str, body: str, *, files: dict[str, str] | None = None,
               options: dict[str, Any] | None = None) -> CheckedItem:
    """Load ``body`` as ``file_name`` of ``kind`` exactly as the command line would load that file; ItemError with
    the loader's one-line message (naming ``file_name``, never a path of the service's) if it does not load."""
    if kind not in ITEM_KINDS:
        raise ItemError(f"kind={kind!r}: not {', '.join(ITEM_KINDS)}")
    name = Path(file_name).name
    if not name.endswith((".yaml", ".yml")):
        raise ItemError(f"{file_name}: not a YAML file (.yaml or .yml)")
    size = len(body.encode())
    if size > MAX_ITEM_BYTES:
        raise ItemError(f"{file_name}: {size} bytes, more than the {MAX_ITEM_BYTES} an item may have")
    with tempfile.TemporaryDirectory(prefix="hil-item-") as tmp:
        path = Path(tmp) / name
        path.write_text(body)
        try:
            config = LOADERS[kind](path)
        except ValueError as exc:
            message = " ".join(str(exc).split()).replace(str(path), file_name).replace(f"{tmp}/", "")
            raise ItemError(message) from None
    if kind == "campaign":
        _require_campaign_files(file_name, config)
    return CheckedItem(kind, str(config.name), config)


def _require_campaign_files(file_name: str, config: Any) -> None:
    """The files a campaign names (its session, its profiles) are on this machine: a submitted campaign names them
    by absolute path (hil.service.Bench sends it as loaded); ItemError naming the field otherwise."""
    named = [("session", config.session)] + [(f"profiles.{i}.path", p.path) for i, p in enumerate(config.profiles)]
    for field_name, path in named:
        if not Path(path).is_absolute():
            raise ItemError(f"{file_name}: {field_name}: {path} is relative; a submitted campaign names its files by "
                            "absolute path (submit it with hil.service.Bench, which does)")
        try:
            require_regular_file(Path(path))
        except ValueError as exc:
            raise ItemError(f"{file_name}: {field_name}: {exc} on the service's machine") from None
