"""The emulator's configuration: clock mode, board behaviour and fault injection (YAML -> pydantic).

profiles/emulator/default.yaml documents every field; the plant's physics live in their own file
(profiles/plant/default.yaml, :mod:`firmware_stub.plant`), referenced from here.
"""

from __future__ import annotations

import copy
import functools
import os
import stat
from collections.abc import Mapping
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hil.protocol import CATALOGUE, LINE_RATE_BAUD, DriveCmd, GyroSample, wire_time_s
from hil.protocol.budget import periodic_load_bits_per_s

REPO = Path(__file__).resolve().parents[1]
DEFAULT_EMULATOR_CONFIG = REPO / "profiles" / "emulator" / "default.yaml"


M = TypeVar("M", bound=BaseModel)


class ConfigError(ValueError):
    """A config file that cannot be used; the message is one line naming the file and the field."""


class LinkName(StrEnum):
    SERVO = "servo"
    DRIVER = "driver"
    IMAGE = "image"
    HEXAPOD = "hexapod"


class ClockMode(StrEnum):
    REALTIME = "realtime"  # the servo board is paced at 1 kHz by a precise clock
    LOCKSTEP = "lockstep"  # the world advances one tick when the host's DRIVE_CMD for it arrives


class Strict(BaseModel):
    """Base of every emulator config model: unknown fields refused, immutable, NaN and infinities refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


Probability = Annotated[float, Field(ge=0.0, le=1.0)]


class LinkFaults(Strict):
    """Continuous faults on what a board sends (board -> host), drawn from the link's own seeded RNG."""

    bit_error_rate: Probability = Field(0.0, description="chance that each transmitted bit is flipped")
    drop_byte_rate: Probability = Field(0.0, description="chance that each transmitted byte is lost")
    garbage_rate: Probability = Field(0.0, description="chance of a burst of random bytes before each frame")
    garbage_max_bytes: int = Field(32, ge=1, le=4096, description="longest garbage burst, bytes")


DEFAULT_BAUD = LINE_RATE_BAUD  # the protocol's default line rate (docs/protocol.md, "Link budget")
HOST_COMPUTE_US = 37.0  # the bench's sample in -> DRIVE_CMD out, p50 (docs/performance.md, the default placement)


class LinkConfig(LinkFaults):
    """One board's link: its line rate, and the faults on what the board sends."""

    baudrate: int = Field(DEFAULT_BAUD, ge=9600, le=12_000_000,
                          description="the line's rate, bit/s (8N1: 10 bits a byte); a loopback session sets it from "
                          "its ports")

    def faults(self) -> LinkFaults:
        return LinkFaults(**self.model_dump(exclude={"baudrate"}))


def _as_link(value: Any) -> Any:
    """A LinkFaults instance (a test's or a caller's) read as the fields it sets."""
    return value.model_dump() if isinstance(value, LinkFaults) and not isinstance(value, LinkConfig) else value


class LinksConfig(Strict):
    """The four links: the wire's time (on by default) and each link's rate and faults (docs/emulator.md, "The wire").

    With ``wire_time`` on, a frame arrives its wire time (10 bits a byte at the link's rate) after it starts. On the
    realtime clock the servo board's output is written that long after its deadline, and a host frame takes effect
    that long after it was read. On the lockstep and sim clocks, DRIVE_CMD k takes effect ``GYRO_SAMPLE`` wire time
    + ``host_compute_us`` + ``DRIVE_CMD`` wire time after tick k (the same in both, so their logs stay equal)."""

    wire_time: bool = Field(True, description="frames take their wire time; off: a frame arrives as it is written, "
                            "and a DRIVE_CMD acts from its tick's start")
    host_compute_us: float = Field(
        HOST_COMPUTE_US, ge=0.0, le=10_000.0,
        description="lockstep and sim: the bench's time from a GYRO_SAMPLE received to its DRIVE_CMD written, us")
    servo: LinkConfig = LinkConfig()
    driver: LinkConfig = LinkConfig()
    image: LinkConfig = LinkConfig()
    hexapod: LinkConfig = LinkConfig()

    _links = field_validator("servo", "driver", "image", "hexapod", mode="before")(_as_link)

    def link(self, name: LinkName | str) -> LinkConfig:
        return getattr(self, LinkName(name).value)

    @model_validator(mode="after")
    def _carries_the_periodic_load(self) -> LinksConfig:
        """A line slower than its periodic messages (docs/protocol.md, "Link budget") could not keep up at all."""
        loads = periodic_load_bits_per_s()
        for name in LinkName:
            baud = self.link(name).baudrate
            need = max((bps for d, bps in loads.items() if name.value in d.split(" → ")), default=0.0)
            if need > baud:
                raise ValueError(f"{name.value}.baudrate: {baud} baud cannot carry the link's periodic messages "
                                 f"({need / 1e3:.1f} kbit/s on the wire, docs/protocol.md link budget)")
        return self


FaultKind = Literal["stall", "latency_spike", "reset", "disconnect", "garbage"]


class ScheduledFault(Strict):
    """A one-off fault at a simulated time (the same tick in every run, in either clock mode).

    stall: the board sends nothing for duration_ms (what it would have sent is lost);
    latency_spike: the board's output is held for duration_ms, then sent at once;
    reset: the board reboots (sequence numbers restart, state back to power-on: the driver disabled,
    the servo stream stopped, the hexapod idle), and announces itself with IDENT;
    disconnect: the pty is closed (the host sees a hang-up) and a new one appears behind the same
    path after duration_ms;
    garbage: n_bytes random bytes (with a false sync word) on the link.
    """

    at_s: float = Field(ge=0.0, le=86400.0, description="simulated time of the fault, s")
    link: LinkName
    kind: FaultKind
    duration_ms: float = Field(0.0, ge=0.0, le=600000.0, description="stall / latency_spike / disconnect length, ms")
    n_bytes: int = Field(64, ge=1, le=65536, description="garbage length, bytes")


class DriverBoardConfig(Strict):
    stale_timeout_ms: float = Field(20.0, gt=0, description="no DRIVE_CMD for this long -> output forced to zero")
    current_limit_a: float = Field(4.0, gt=0, description="|armature current| above this, A ...")
    overcurrent_trip_ms: float = Field(10.0, ge=0, description="... for this long latches an OVERCURRENT fault")
    bus_voltage_v: float = Field(24.0, gt=0, le=655.35, description="reported in DRIVE_STATUS (u16, 0.01 V)")


class HexapodBoardConfig(Strict):
    max_segments: int = Field(32, ge=1, le=255, description="segments a profile may have")
    stop_ramp_s: float = Field(1.0, gt=0, description="HEXAPOD_STOP ramps the motion to zero over this time")


class BoardsConfig(Strict):
    driver: DriverBoardConfig = DriverBoardConfig()
    hexapod: HexapodBoardConfig = HexapodBoardConfig()
    serial_base: int = Field(1000, ge=0, le=2**32 - 256, description="IDENT serial numbers are serial_base + board id")
    host_timeout_ms: float = Field(
        500.0, ge=0, le=60000.0, description="no frame from the host for this long -> every board protects itself "
        "(driver disabled, hexapod home, stream stopped); 0 = never (docs/protocol.md, Host liveness)")


class EmulatorConfig(Strict):
    clock: ClockMode = ClockMode.REALTIME
    seed: int = Field(0, ge=0, description="seeds the plant's noise and every link's fault RNG")
    plant: Path = Field(REPO / "profiles" / "plant" / "default.yaml", description="plant YAML (relative to this file)")
    lockstep_timeout_ms: float = Field(
        1000.0, gt=0, le=60000.0,
        description="lockstep: wait this long (wall) for DRIVE_CMD k; a timeout breaks byte-identity, "
        "so keep it far above a loaded host's worst pause")
    realtime_prep_us: float = Field(
        300.0, ge=50, le=900,
        description="realtime: the world advances when DRIVE_CMD k arrives, or this long before the next "
        "sample is due if it has not; a command later than that is applied one tick late")
    boards: BoardsConfig = BoardsConfig()
    links: LinksConfig = Field(LinksConfig(), description="the wire's time, each link's rate and faults")
    faults: list[ScheduledFault] = Field(default_factory=list, description="one-off faults at simulated times")

    def link_faults(self, link: LinkName) -> LinkFaults:
        return self.links.link(link).faults()

    def drive_delay_s(self) -> float:
        """Lockstep and sim: how long after tick k DRIVE_CMD k acts (docs/emulator.md, "The wire"): the GYRO_SAMPLE's
        wire time on the servo link, ``links.host_compute_us``, the DRIVE_CMD's on the driver link; 0 with
        ``links.wire_time`` off."""
        links = self.links
        if not links.wire_time:
            return 0.0
        return (wire_time_s(CATALOGUE.by_type[GyroSample], links.servo.baudrate) + links.host_compute_us * 1e-6
                + wire_time_s(CATALOGUE.by_type[DriveCmd], links.driver.baudrate))


def describe_validation_error(source: str, err: ValidationError) -> str:
    """The first problem of a pydantic error as one line: `source: field.path: reason`."""
    first = err.errors()[0]
    where = ".".join(str(p) for p in first["loc"]) or "(top level)"
    got = first.get("input")
    text = repr(got)
    text = text if len(text) <= 80 else text[:77] + "..."
    shown = "" if isinstance(got, dict | list) or got is None else f" (got {text})"
    return " ".join(f"{source}: {where}: {str(first['msg']).removeprefix('Value error, ')}{shown}".split())


MAX_CONFIG_BYTES = 1 << 20  # an emulator or plant file larger than this is refused unread
MAX_YAML_DEPTH = 64  # nesting levels


class _PlainLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` without anchors and aliases (so no alias bomb), nesting at most ``MAX_YAML_DEPTH``."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
            line = event.start_mark.line + 1
            raise yaml.YAMLError(f"line {line}: anchors and aliases are not used in emulator files")
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise yaml.YAMLError(f"nested deeper than {MAX_YAML_DEPTH} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


@functools.lru_cache(maxsize=32)
def _parse_plain(text: str) -> Any:
    """The document of ``text`` (:class:`_PlainLoader`), its last 32 remembered by text: a process that runs cell
    after cell (a campaign's warm worker) reads the same plant and emulator files each time, and the pure-Python
    parser takes milliseconds a file."""
    loader = _PlainLoader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def read_yaml_mapping(path: str | Path) -> dict[str, Any]:
    """The top-level mapping of a YAML file; :class:`ConfigError` (one line naming the file) if it is not a regular
    file (a FIFO, device or directory is refused unopened), is larger than ``MAX_CONFIG_BYTES``, is not UTF-8 or
    not YAML. The emulator's own minimal reader: the bench's (``hil.config.read_yaml_mapping``) also bounds aliases."""
    path = Path(path)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO, device or directory: refused unopened
            raise ConfigError(f"{path}: not a regular file")
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise ConfigError(f"{path}: not a regular file")
            data = os.read(fd, MAX_CONFIG_BYTES + 1)
        finally:
            os.close(fd)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: more than the {MAX_CONFIG_BYTES} bytes a config file may have")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start})") from None
    try:
        doc = copy.deepcopy(_parse_plain(text))  # a copy: the caller may change what it gets
    except (yaml.YAMLError, ValueError, RecursionError) as exc:
        raise ConfigError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(doc).__name__}")
    return doc


def load_yaml_model(model: type[M], path: str | Path, overrides: dict | None = None) -> M:
    """Load a YAML file into a pydantic model; relative paths in it stay relative to the file."""
    path = Path(path)
    data = read_yaml_mapping(path)
    data.update(overrides or {})
    try:
        return model.model_validate(data, context={"base_dir": path.parent})
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(str(path), exc)) from None


def load_emulator_config(path: str | Path | None = None, *, baudrates: Mapping[str, int] | None = None,
                         **overrides: object) -> EmulatorConfig:
    """Load an emulator YAML (default profiles/emulator/default.yaml); overrides replace top-level fields,
    ``baudrates`` (link name -> bit/s: a loopback session's ports) the links' rates."""
    path = Path(path) if path is not None else DEFAULT_EMULATOR_CONFIG
    config = load_yaml_model(EmulatorConfig, path, {k: v for k, v in overrides.items() if v is not None})
    plant = config.plant if config.plant.is_absolute() else (path.parent / config.plant).resolve()
    config = config.model_copy(update={"plant": plant})
    if baudrates:
        data = config.model_dump()
        for name, baud in baudrates.items():
            data["links"][LinkName(name).value]["baudrate"] = baud
        try:
            config = EmulatorConfig.model_validate(data)
        except ValidationError as exc:
            raise ConfigError(describe_validation_error(str(path), exc)) from None
    return config
