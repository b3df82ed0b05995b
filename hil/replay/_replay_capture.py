"""How a capture's bytes reach a board from ``hil replay CAPTURE`` (docs/capture.md): :func:`replay_capture` (what
``hil replay CAPTURE`` calls, through hil.api) checks its options, finds the boards' ports (:func:`resolve_ports`, a
ports file or ``LINK=PATH``) or starts a fresh emulator as the capture's header says (:func:`emulator_settings`),
plays the capture there (``_playback``) and writes the result (:func:`write_playback_json`): everything but the
parsing and printing, bad input refused with a ReplayError or CaptureError (ValueErrors) naming the parameter.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.analysis import json_safe
from hil.config import read_text_file, require_writable_dir
from hil.link import (
    LINKS,
    CaptureReader,
    LinkError,
    find_capture,
)
from hil.replay._controller import ReplayError
from hil.replay._playback import PlaybackResult, Timing, play_capture
from hil.session import EmulatorProcess

TIMINGS = ("samples", "clock")
EMULATOR_CLOCKS = ("lockstep", "realtime")


def ports_from_file(path: Path) -> dict[str, str]:
    """A ports file (the one an emulator writes: JSON ``{"servo": path, ...}``) as link -> path (its ``control``
    socket left out). ReplayError naming ``ports_file`` and the file otherwise."""


    try:
        text = read_text_file(path, 1 << 20)
    except ValueError as exc:  # names the file
        raise ReplayError(f"ports_file: {exc}") from None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise ReplayError(f"ports_file={str(path)!r}: not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ReplayError(f"ports_file={str(path)!r}: not a ports file (a JSON object of link: path)")
    return {str(k): str(v) for k, v in data.items() if k != "control"}


def resolve_ports(ports: Mapping[str, str] | Iterable[str] | None = None,
                  ports_file: Path | str | None = None) -> dict[str, str]:
    """The boards' ports (link name -> device path): ``ports_file``'s (:func:`ports_from_file`), then ``ports`` over
    them, a mapping or ``"LINK=PATH"`` strings ReplayError naming ``ports`` otherwise."""
    out: dict[str, str] = {}
    if ports_file is not None:
        out.update(ports_from_file(Path(ports_file)))
    if ports is None:
        return out
    if isinstance(ports, str):
        raise ReplayError(f"ports={ports!r}: give a list of LINK=PATH, or a dict of link: path")
    items = [f"{k}={v}" for k, v in ports.items()] if isinstance(ports, Mapping) else [str(p) for p in ports]
    for item in items:
        name, eq, path = item.partition("=")
        if not eq or name not in LINKS or not path:
            raise ReplayError(f"ports={item!r}: not LINK=PATH with LINK servo, driver, image or hexapod")
        out[name] = path
    return out


@dataclass(frozen=True)
class EmulatorSettings:
    """What a fresh emulator for a playback is started with (:func:`emulator_settings`)."""

    config: Path | None  # None: the emulator's default config
    clock: str  # lockstep | realtime
    seed: int

    def as_dict(self) -> dict[str, Any]:
        return {"config": None if self.config is None else str(self.config), "clock": self.clock, "seed": self.seed}


def emulator_settings(meta: Mapping[str, Any], *, clock: str | None = None, seed: int | None = None,
                      config: Path | str | None = None) -> EmulatorSettings:
    """The fresh emulator a capture with header ``meta`` is played to: ``clock``, ``seed`` and ``config`` where given,
    else what the header recorded (``emulator_clock`` or ``session_clock``, ``emulator_seed`` or ``seed``,
    ``emulator_config``; lockstep, 0 and the default config for a capture that says nothing). ReplayError naming the
    option for a clock or seed that is not one, or a config file that does not exist here."""
    if clock is None:
        clock = str(meta.get("emulator_clock") or meta.get("session_clock") or "lockstep")
        if clock not in EMULATOR_CLOCKS:
            raise ReplayError(f"the capture's session clock {clock!r} is not one the emulator runs: give clock= "
                              f"{' or '.join(EMULATOR_CLOCKS)}")
    elif clock not in EMULATOR_CLOCKS:
        raise ReplayError(f"clock={clock!r}: not {' or '.join(EMULATOR_CLOCKS)}")
    if seed is None:
        recorded = meta.get("emulator_seed", meta.get("seed"))
        try:
            seed = int(recorded or 0)
        except (TypeError, ValueError):
            raise ReplayError(f"the capture's seed {recorded!r} is not an integer: give seed=") from None
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ReplayError(f"seed={seed!r}: not an integer >= 0")
    path: Path | None = None
    if config is not None:
        path = Path(config)
        if not path.is_file():
            raise ReplayError(f"emulator config {path}: no such file")
    elif meta.get("emulator_config"):
        path = Path(str(meta["emulator_config"]))
        if not path.is_file():
            raise ReplayError(f"the captured emulator config {path} is not a file here: start an emulator with it "
                              f"and give its ports (ports_file=)")
    return EmulatorSettings(path, clock, seed)


def replay_capture(capture: Path | str, *, ports: Mapping[str, str] | Iterable[str] | None = None,
                   ports_file: Path | str | None = None, clock: str | None = None, seed: int | None = None,
                   timing: Timing = "samples", record_dir: Path | str | None = None, links: Iterable[str] | None = None,
                   emulator_config: Path | str | None = None, **kwargs: Any) -> PlaybackResult:
    """Play ``capture`` (a ``.hilcap`` file, or the directory holding one) back at the boards, as ``hil replay
    CAPTURE`` does. The boards: ``ports`` (a mapping link -> path, or ``"LINK=PATH"`` strings) over
    ``ports_file``'s (the ports file an emulator writes); with neither, a fresh emulator is started for the playback
    and stopped after it, with ``clock``, ``seed`` and ``emulator_config`` where given, else the capture's
    (:func:`emulator_settings`; the result's ``emulator`` says which). ``timing``, ``record_dir`` (where the replay's
    own capture goes), ``links`` (only these) and the other keywords as :func:`play_capture`. Bad input raises
    ReplayError or CaptureError (ValueErrors, one line naming the option) before anything is sent."""

    if timing not in TIMINGS:
        raise ReplayError(f"timing={timing!r}: not {' or '.join(TIMINGS)}")
    path = find_capture(Path(capture))
    named = resolve_ports(ports, ports_file)
    if record_dir is not None:

        try:
            require_writable_dir(Path(record_dir), "record_dir")
        except ValueError as exc:
            raise ReplayError(str(exc)) from None
    options = {"timing": timing, "record_dir": None if record_dir is None else Path(record_dir),
               "links": None if links is None else set(links), **kwargs}
    if named:
        if clock is not None or seed is not None or emulator_config is not None:
            raise ReplayError("clock= and seed= start a fresh emulator: not with ports= or ports_file=")
        return play_capture(path, named, **options)
    settings = emulator_settings(CaptureReader(path).meta, clock=clock, seed=seed, config=emulator_config)

    emulator = EmulatorProcess(settings.config, clock=settings.clock, seed=settings.seed)
    try:
        try:
            started = emulator.start()
        except LinkError as exc:
            raise ReplayError(str(exc)) from None
        result = play_capture(path, {k: v for k, v in started.items() if k != "control"}, **options)
    finally:
        emulator.stop()
    result.emulator = settings.as_dict()
    return result


def write_playback_json(result: PlaybackResult, out_dir: Path | str) -> Path:
    """``replay-<capture stem>.json`` in ``out_dir``: ``result.as_dict()`` as strict JSON; returns its path."""

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"replay-{result.capture.stem}.json"
    path.write_text(json.dumps(json_safe(result.as_dict()), indent=1) + "\n")
    return path
