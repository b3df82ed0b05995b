"""Reading the bench's input files safely, and checking where its output goes: bounded reads (a FIFO, a device or a
huge file is refused unread), a YAML loader with depth, node and alias limits, and relative paths resolved against
the file that names them, or kept inside one directory (:func:`confined_to`: a submitted item reads only its own
files). Imports no other part of the bench, so any layer may use it.
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
import functools
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationInfo

MAX_CONFIG_BYTES = 1 << 20  # a config file larger than this is refused unread
MAX_YAML_DEPTH = 64  # nesting levels of a YAML document, aliases expanded
MAX_YAML_NODES = 100_000  # values of a YAML document, aliases expanded (an alias bomb stops here)
MAX_YAML_ALIASES = 64  # alias uses (*name) in one document


class ConfigError(ValueError):
    """A config file that cannot be used: one line, naming the file and the field."""


# --- reading files ---------------------------------------------------------------------------------------------------


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def read_file_bytes(path: str | Path, max_bytes: int = MAX_CONFIG_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``; ValueError (one line naming the file) otherwise.

    A FIFO, a device or a directory is refused before it is opened (so nothing blocks and nothing is read
    from a device), and at most ``max_bytes + 1`` bytes are ever read."""
    path = require_regular_file(Path(path))
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):  # replaced since the check above
            raise ValueError(f"{path}: {_kind(info.st_mode)}, not a regular file")
        if info.st_size > max_bytes:
            raise ValueError(f"{path}: {info.st_size} bytes, more than the {max_bytes} a file here may have")
        chunks, n = [], 0
        while n <= max_bytes and (chunk := os.read(fd, max_bytes + 1 - n)):
            chunks.append(chunk)
            n += len(chunk)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if n > max_bytes:
        raise ValueError(f"{path}: more than the {max_bytes} bytes a file here may have")
    return b"".join(chunks)


def read_text_file(path: str | Path, max_bytes: int = MAX_CONFIG_BYTES) -> str:
    """:func:`read_file_bytes` decoded as UTF-8; ValueError naming the file if it is not text."""
    data = read_file_bytes(path, max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start})") from None


class _YamlLimit(yaml.YAMLError):
    """A document beyond the reader's bounds."""


class _BoundedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` with bounded nesting and alias uses (the composer recurses per level)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._aliases = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_YAML_ALIASES:
                raise _YamlLimit(f"more than {MAX_YAML_ALIASES} aliases")
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise _YamlLimit(f"nested deeper than {MAX_YAML_DEPTH} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def _check_expansion(root: yaml.Node) -> None:
    """Refuse a document whose aliases expand it beyond ``MAX_YAML_NODES`` values or ``MAX_YAML_DEPTH`` levels,
    or refer to themselves; every distinct node is visited once (no expansion happens here)."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            on_path.discard(key)
            kids = _children(node)
            size[key] = 1 + sum(size[id(k)] for k in kids)
            depth[key] = 1 + max((depth[id(k)] for k in kids), default=0)
            if size[key] > MAX_YAML_NODES:
                raise _YamlLimit(f"more than {MAX_YAML_NODES} values once its aliases are expanded")
            if depth[key] > MAX_YAML_DEPTH:
                raise _YamlLimit(f"nested deeper than {MAX_YAML_DEPTH} levels once its aliases are expanded")
        elif key not in size:
            if key in on_path:
                raise _YamlLimit("an alias refers to a value that contains it")
            on_path.add(key)
            stack.append((node, True))
            stack.extend((k, False) for k in _children(node) if id(k) not in size)


def parse_yaml(text: str) -> Any:
    """Safe YAML with bounded size once expanded; ``yaml.YAMLError`` (or ValueError) if not. The last 32 documents
    are remembered by their text (a campaign's warm worker loads the same session files cell after cell, and the
    pure-Python parser takes milliseconds a file); each call returns a copy of its own."""
    return copy.deepcopy(_parse_bounded(text))


@functools.lru_cache(maxsize=32)
def _parse_bounded(text: str) -> Any:
    loader = _BoundedLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_expansion(node)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def read_yaml_mapping(path: str | Path) -> dict[str, Any]:
    """The top-level mapping of a YAML config file, read through :func:`read_text_file` and
    :func:`parse_yaml`; ValueError (one line naming the file) if anything is wrong."""
    text = read_text_file(path)
    try:
        data = parse_yaml(text)
    except (yaml.YAMLError, ValueError, RecursionError) as exc:
        raise ValueError(f"{path}: cannot read YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


# --- what a file may name -------------------------------------------------------------------------------------------

ITEM_RULE = 'a submitted item carries its own files (docs/service.md, "A submitted item stands on its own")'
_CONFINED: contextvars.ContextVar[Path | None] = contextvars.ContextVar("hil_config_confined", default=None)


@contextlib.contextmanager
def confined_to(directory: str | Path) -> Iterator[Path]:
    """While the block runs (in this thread or task, and in every load it makes), a file a config names must lie
    inside ``directory``, the submitted item's own files: :func:`resolve_relative` refuses any other path before
    anything is opened, and ``mqtt.password_env`` is refused. Yields the directory, resolved."""
    root = Path(directory).resolve()
    token = _CONFINED.set(root)
    try:
        yield root
    finally:
        _CONFINED.reset(token)


def confinement() -> Path | None:
    """The directory loads are confined to (:func:`confined_to`), or None."""
    return _CONFINED.get()


def _as_named(value: str | Path, limit: int = 120) -> str:
    text = str(value)
    text = text if text.isprintable() else repr(text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def resolve_relative(value: Any, info: ValidationInfo) -> Any:
    """A pydantic validator: a relative path in a file is relative to that file (``context={"base_dir": ...}``).

    Confined (:func:`confined_to`), a path that resolves outside the directory (an absolute path of the machine's,
    ``..``, a symlink) or a relative one with no file to be relative to is refused, ValueError, unopened."""
    base = (info.context or {}).get("base_dir")
    root = _CONFINED.get()
    if not isinstance(value, str | Path):
        return value
    if root is None:
        if base is not None and not Path(value).is_absolute():
            return (Path(base) / value).resolve()
        return value
    path = Path(value)
    if not path.is_absolute():
        if base is None:
            raise ValueError(f"names {_as_named(value)}, relative to no file of the submitted item: {ITEM_RULE}")
        path = Path(base) / path
    try:
        resolved = path.resolve()
    except (OSError, ValueError, RuntimeError):
        resolved = None
    if resolved is None or not resolved.is_relative_to(root):
        raise ValueError(f"names {_as_named(value)}, outside the submitted item: {ITEM_RULE}")
    return resolved


def require_regular_file(path: Path) -> Path:
    """``path`` if it names a regular file; ValueError otherwise (checked without opening it)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{path}: {_kind(mode)}, not a regular file")
    return path


def named(what: str, value: object) -> str:
    """How an error names an input: a parameter as ``name='value'`` (``what`` an identifier), a config field or
    an option as ``what value`` (``logging.dir /data``)."""
    return f"{what}={str(value)!r}" if what.isidentifier() else f"{what} {value}"


def require_writable_dir(path: Path, what: str) -> Path:
    """``path`` if it is a directory we may write into, or one we may create (nothing is created here);
    ConfigError naming ``what`` (the parameter or field, :func:`named`) otherwise."""
    target = Path(path).absolute()
    if target.exists() and not target.is_dir():
        raise ConfigError(f"{named(what, path)}: exists and is not a directory")
    parent = target
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"{named(what, path)}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{named(what, path)}: {parent} is not writable")
    return Path(path)
