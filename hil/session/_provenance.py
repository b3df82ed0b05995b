"""Where a session log came from: the software, the plant and the controller, as the session records it.

A session stores ``collect_provenance(config)`` as the log's ``provenance`` file attribute (JSON text);
``hil.log.read_provenance(path)`` gives it back. With it a figure made from a log can be traced to the
bench's version and commit, the versions of the numerical libraries, the exact plant file the emulator
ran (by its SHA-256) and every controller parameter actually used, defaults included
(docs/log-format.md, "Provenance").

Collecting never raises and never takes long: a value that cannot be found is ``None``, and the one
external call (``git status``) is given about a second.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil._version import __version__
from hil.control.registry import effective_params

if TYPE_CHECKING:
    from hil.config import SessionConfig

GIT_TIMEOUT_S = 1.0
_PACKAGES = ("numpy", "h5py", "scipy", "numba")
_SOURCE_ROOT = Path(__file__).resolve().parents[2]  # the directory holding the hil package


def collect_provenance(config: SessionConfig, *, emulated: bool | None = None) -> dict[str, Any]:
    """The provenance of a session about to run with ``config`` (plain JSON types).

    Keys: ``hil_version``; ``git_commit`` (the commit of the checkout the bench runs from, with
    ``-dirty`` when tracked files differ from it; ``None`` outside a git checkout or without git);
    ``python``, ``numpy``, ``h5py``, ``hdf5``, ``scipy``, ``numba`` (versions, ``None`` when not
    installed); ``plant`` (``{"path", "sha256"}`` of the plant file the emulator loads, ``None`` when
    the session does not run against the emulator or the file cannot be read); ``controller``
    (``{"name", "params"}`` with every parameter resolved, defaults included).

    ``emulated``: whether the boards are the emulator of ``config.emulator`` (a loopback run). ``None``
    guesses from the config: a session without ``ports`` can only run against the emulator.
    """
    out: dict[str, Any] = {"hil_version": str(__version__), "git_commit": git_commit()}
    out["python"] = platform.python_version()
    for name in _PACKAGES:
        out[name] = _version(name)
    out["hdf5"] = _hdf5_version()
    if emulated is None:
        emulated = getattr(config, "ports", None) is None
    out["plant"] = _plant(config) if emulated else None
    out["controller"] = _controller(config)
    return out


# --- the parts ---------------------------------------------------------------------------------


def git_commit(root: Path = _SOURCE_ROOT, timeout_s: float = GIT_TIMEOUT_S) -> str | None:
    """The commit checked out at ``root`` (``-dirty`` if tracked files changed), or None.

    None when ``root`` is not the top of a git checkout (an installed package), git is missing,
    fails or takes longer than ``timeout_s``. Untracked files do not count (as ``git describe
    --dirty``). The index is not touched (``GIT_OPTIONAL_LOCKS=0``), so this is safe beside other
    git commands.
    """
    if not (root / ".git").exists() or shutil.which("git") is None:
        return None
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0", "LC_ALL": "C"}
    try:
        proc = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain=v2", "--branch", "--untracked-files=no"],
            capture_output=True, text=True, timeout=timeout_s, env=env, stdin=subprocess.DEVNULL, check=False,
        )
    except (OSError, subprocess.SubprocessError, ValueError):
        return None
    if proc.returncode != 0:
        return None
    commit = None
    dirty = False
    for line in proc.stdout.splitlines():
        if line.startswith("# branch.oid "):
            oid = line.split()[-1]
            commit = oid if all(c in "0123456789abcdef" for c in oid) and len(oid) >= 40 else None
        elif line and not line.startswith("#"):
            dirty = True
    if commit is None:
        return None
    return commit + "-dirty" if dirty else commit


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except (metadata.PackageNotFoundError, ValueError):
        return None


def _hdf5_version() -> str | None:
    try:
        import h5py  # noqa: PLC0415  (optional: its absence is handled here)

        return str(h5py.version.hdf5_version)
    except Exception:
        return None


def plant_file(emulator_config: str | Path) -> Path | None:
    """The plant file an emulator YAML names (its ``plant:``, relative to that file), or None if unreadable."""
    try:
        from firmware_stub.config import load_emulator_config  # noqa: PLC0415  (optional: its absence is handled here)

        return Path(load_emulator_config(emulator_config).plant).resolve()
    except Exception:
        return None


def _plant(config: SessionConfig) -> dict[str, str] | None:
    emulator = getattr(config, "emulator", None)
    if emulator is None:
        return None
    path = plant_file(emulator.config)
    if path is None:
        return None
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None
    return {"path": str(path), "sha256": digest}


def _controller(config: SessionConfig) -> dict[str, Any]:

    controller = config.controller
    try:
        return {"name": controller.name, "params": effective_params(controller)}
    except Exception as exc:  # a config that validated cannot fail here; record what was given if it does
        return {"name": controller.name, "params": dict(controller.params), "error": str(exc)}
