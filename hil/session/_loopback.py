"""The emulated lab as a child process (`python -m firmware_stub`), for a loopback `hil run`, `hil demo` and tests;
and an emulator config pointed at another plant (a fitted twin, a drawn hidden plant)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml

from hil.config import PROFILES, ConfigError, read_yaml_mapping
from hil.link import LinkError

DEFAULT_EMULATOR = PROFILES / "emulator" / "default.yaml"


def emulator_for_plant(plant: str | Path, out_dir: str | Path, *, base: str | Path = DEFAULT_EMULATOR,
                       seed: int | None = None, wire_time: bool | None = None) -> Path:
    """An emulator YAML with ``base``'s settings (the shipped default unless given) and ``plant`` as its plant
    (``seed`` and ``links.wire_time`` too, if given), written into ``out_dir`` as ``emulator-BASE-PLANT.yaml``
    (``...-nowire.yaml`` without the wire's time); its path. Written whole and renamed into place, so processes
    that share ``out_dir`` never read half a file. A plant file that does not load is a ConfigError naming it."""
    base, plant = Path(base), Path(plant)
    from firmware_stub.plant import PlantConfigError, load_plant_config  # noqa: PLC0415  (the plant's numba kernel comes with it: loaded only when a plant is given)

    try:
        load_plant_config(plant)
    except PlantConfigError as exc:
        raise ConfigError(f"plant={str(plant)!r}: {exc}") from None
    try:
        data = read_yaml_mapping(base)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    data["plant"] = str(plant.resolve())
    if seed is not None:
        data["seed"] = seed
    if wire_time is not None:
        data["links"] = {**(data.get("links") or {}), "wire_time": wire_time}
    suffix = "-nowire" if wire_time is False else ""
    out = Path(out_dir) / f"emulator-{base.stem}-{plant.stem}{suffix}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    tmp.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    tmp.replace(out)
    return out


def _die_with_parent() -> None:
    """Linux: SIGTERM the emulator if the bench dies (even by SIGKILL), so no orphan keeps the ptys."""
    try:
        import ctypes  # noqa: PLC0415  (optional: its absence is handled here)

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class EmulatorProcess:
    """Start with ``with EmulatorProcess(config, clock=..., seed=...) as emu: emu.ports ...``."""

    def __init__(self, config: Path | None = None, *, clock: str = "lockstep", seed: int = 0,
                 extra_args: list[str] | None = None) -> None:
        self.args = [sys.executable, "-m", "firmware_stub", "--clock", clock, "--seed", str(seed)]
        if config is not None:
            self.args += ["--config", str(config)]
        self.args += extra_args or []
        self.proc: subprocess.Popen[str] | None = None
        self.ports: dict[str, str] = {}
        self.summary: dict[str, Any] = {}
        self.last_stderr = ""  # what the emulator wrote on stderr, once stopped

    def start(self) -> dict[str, str]:
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     preexec_fn=_die_with_parent)  # noqa: PLW1509 (before any thread)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        try:
            ports = json.loads(line) if line else None
        except ValueError:
            ports = None
        if not isinstance(ports, dict):
            self.stop()
            raise LinkError(f"the emulator did not start: {self._why(line)}")
        self.ports = ports
        return self.ports

    def _why(self, line: str) -> str:
        """The emulator's own one-line error (a bad config: ``error: FILE: field: reason``), else its last words."""
        err = self.last_stderr.strip().splitlines()
        last = err[-1] if err else (line.strip() or "no output")
        return last.removeprefix("error: ")

    def stop(self) -> dict[str, Any]:
        if self.proc is None:
            return {}
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, err = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        self.last_stderr = err or ""
        lines = [ln for ln in out.strip().splitlines() if ln.startswith("{")]
        try:
            self.summary = json.loads(lines[-1]) if lines else {}
        except ValueError:
            self.summary = {}
        self.proc = None
        return self.summary

    def __enter__(self) -> EmulatorProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
