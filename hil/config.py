"""Session configuration: every YAML file the bench reads is one of these pydantic models.

    profiles/sessions/*.yaml      SessionConfig (references the files below by relative path)
    profiles/controllers/*.yaml   ControllerConfig (a registry name and its parameters)
    profiles/swing/*.yaml         SwingProfile (hexapod segments)
    profiles/hexapod/*.yaml       HexapodLimits (the swing table's envelope, checked before upload)

Bad input is a :class:`ConfigError` whose message is one line naming the file, the field and the
reason; the CLI prints it and exits 2.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from hil.control.registry import ControllerConfigError, controller_params
from hil.ident import SweptSine
from hil.protocol import HexAxis
from hil.protocol.swing import Envelope, Segment, check_envelope
from hil.telemetry import MqttConfig

M = TypeVar("M", bound=BaseModel)
REPO = Path(__file__).resolve().parents[1]
PROFILES = REPO / "profiles"


class ConfigError(ValueError):
    """A config file that cannot be used: one line, naming the file and the field."""


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _resolve(value: Any, info: ValidationInfo) -> Any:
    """Relative paths in a file are relative to that file."""
    base = (info.context or {}).get("base_dir")
    if isinstance(value, str | Path) and base is not None and not Path(value).is_absolute():
        return (Path(base) / value).resolve()
    return value


class PortConfig(Strict):
    port: str = Field(description="serial device, e.g. /dev/ttyUSB0 or /dev/serial/by-id/...")
    baudrate: int = Field(921600, gt=0)


class PortsConfig(Strict):
    servo: PortConfig
    driver: PortConfig
    image: PortConfig
    hexapod: PortConfig


class ControllerConfig(Strict):
    """A controller from hil.control's registry with its parameters (the same for both axes)."""

    name: str = Field("eso_kf", description="registry name: pi_lpf, eso, eso_nonlinear, eso_kf, ...")
    params: dict[str, Any] = Field(default_factory=dict, description="overrides of the registry defaults")

    @model_validator(mode="after")
    def _known(self) -> ControllerConfig:
        try:
            controller_params(self.name, self.params)
        except ControllerConfigError as exc:
            raise ValueError(str(exc)) from None
        return self


AxisName = Literal["x", "y", "z", "roll", "pitch", "yaw"]


class SwingSegment(Strict):
    axis: AxisName
    amplitude: float = Field(description="mm for x/y/z, deg for roll/pitch/yaw")
    frequency_hz: float = Field(ge=0)
    start_s: float = Field(0.0, ge=0)
    duration_s: float = Field(gt=0)
    phase_deg: float = 0.0
    ramp_s: float = Field(0.0, ge=0, description="linear ramp in and out")

    def segment(self) -> Segment:
        return Segment(HexAxis[self.axis.upper()], self.start_s, self.duration_s, self.amplitude,
                       self.frequency_hz, self.phase_deg, self.ramp_s)


class SwingProfile(Strict):
    """A hexapod swing: the sum of its segments (hil.protocol.swing)."""

    name: str = ""
    description: str = ""
    segments: list[SwingSegment] = Field(default_factory=list, max_length=32)

    def protocol_segments(self) -> list[Segment]:
        return [s.segment() for s in self.segments]


class AxisLimits(Strict):
    position: float = Field(gt=0, description="mm or deg")
    rate: float = Field(gt=0, description="mm/s or deg/s")
    accel: float = Field(gt=0, description="mm/s^2 or deg/s^2")


class HexapodLimits(Strict):
    """The swing table's envelope, as its datasheet gives it (symmetric +- limits)."""

    x: AxisLimits
    y: AxisLimits
    z: AxisLimits
    roll: AxisLimits
    pitch: AxisLimits
    yaw: AxisLimits

    def envelope(self) -> Envelope:
        axes = (self.x, self.y, self.z, self.roll, self.pitch, self.yaw)
        return Envelope(tuple(a.position for a in axes), tuple(a.rate for a in axes),  # type: ignore[arg-type]
                        tuple(a.accel for a in axes))


class TrackingConfig(Strict):
    """The outer loop: miss distance (px) at camera rate -> rate command (deg/s) per axis."""

    enabled: bool = True
    kp_per_s: float = Field(8.0, ge=0)
    ki_per_s2: float = Field(0.0, ge=0)
    ifov_deg_per_px: float = Field(0.002, gt=0, description="the camera's pixel angle")
    max_rate_dps: float = Field(20.0, gt=0)
    stale_s: float = Field(0.05, gt=0)
    gate_px: int = Field(0, ge=0, le=65535, description="TRACK_CMD gate half-size, 0 = the whole field")
    apply_after_ms: float = Field(
        11.0, ge=0, le=100,
        description="a frame is used from the first gyro sample later than its exposure + this (board clock), "
        "or when it arrives if that is later: one 100 Hz frame of latency + 1 ms, so every run of a lockstep "
        "session uses each frame at the same tick")


class SafetyConfig(Strict):
    watchdog_ms: float = Field(5.0, gt=0, description="no GYRO_SAMPLE for this long -> zero drive, DISABLE")
    on_fault: Literal["stop", "recover"] = Field("stop", description="after a watchdog/link/driver fault")
    recover_after_ms: float = Field(200.0, ge=0, description="recover: wait this long, then re-arm")
    max_recoveries: int = Field(3, ge=0)
    max_drive_counts: int = Field(30000, gt=0, le=32767, description="|DRIVE_CMD| saturation")
    max_slew_counts: int = Field(32767, gt=0, le=65535, description="largest change of the drive per tick")


class HostConfig(Strict):
    """How the bench process runs on the lab PC."""

    rt_priority: int = Field(
        0, ge=0, le=99,
        description="run the 1 kHz loop thread SCHED_FIFO at this priority (needs root or CAP_SYS_NICE; "
        "0 = normal scheduling). The log writer and other children keep normal scheduling")
    loop_cpu: int | None = Field(
        None, ge=-1024, le=1023,
        description="pin the 1 kHz loop thread to this CPU, as an index into the CPUs the bench may use "
        "(-1 = the last), and keep the log writer and telemetry processes off it; none = the OS places "
        "them. Needs two CPUs; otherwise the session runs unpinned and logs why")


class LoggingConfig(Strict):
    dir: Path = Field(Path("runs"), description="session logs go here (relative to the working directory)")
    flush_interval_s: float = Field(0.1, gt=0, le=0.1)
    fsync: bool = True


class EmulatorRef(Strict):
    """What `hil run --loopback` starts in place of the lab."""

    config: Path = PROFILES / "emulator" / "default.yaml"
    clock: Literal["realtime", "lockstep"] = "lockstep"
    rt_priority: int = Field(0, ge=0, le=99, description="SCHED_FIFO priority of the emulator's clock, 0 = normal")
    cpu: int | None = Field(
        None, ge=-1024, le=1023,
        description="pin the emulator to this CPU index (-1 = the last); the same CPU as host.loop_cpu keeps "
        "the sample/command round trip on one core (docs/performance.md)")

    def process_args(self) -> list[str]:
        """Its scheduling options on the emulator's command line (``python -m firmware_stub ...``)."""
        args = ["--rt-priority", str(self.rt_priority)]
        return args if self.cpu is None else [*args, "--cpu", str(self.cpu)]

    _rel = field_validator("config", mode="before")(_resolve)


class SineExcitation(Strict):
    """A sine added to one axis's rate command, on top of tracking (seed 000 Fig. 13: 5 deg/s at 15 Hz)."""

    axis: Literal["el", "az"] = "el"
    amplitude_dps: float = Field(gt=0, le=200, description="peak rate added to the command")
    freq_hz: float = Field(gt=0, le=450, description="below the 500 Hz Nyquist of the 1 kHz loop")
    start_s: float = Field(0.0, ge=0, description="zero before this session time")

    def rate_dps(self, t_s: float) -> float:
        """The added rate command at session time ``t_s`` (plain floats: it runs in the 1 kHz loop)."""
        if t_s < self.start_s:
            return 0.0
        return self.amplitude_dps * math.sin(2.0 * math.pi * self.freq_hz * (t_s - self.start_s))


class SessionConfig(Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", description="used in the log file name")
    description: str = ""
    duration_s: float = Field(gt=0, le=24 * 3600, description="run time with the stream on, s")
    seed: int = Field(0, ge=0, description="emulator seed in loopback; recorded in the log")
    ports: PortsConfig | None = Field(None, description="the lab's serial ports (not needed with --loopback)")
    controller: ControllerConfig = ControllerConfig()
    tracking: TrackingConfig = TrackingConfig()
    profile: SwingProfile = SwingProfile()
    hexapod_limits: HexapodLimits
    safety: SafetyConfig = SafetyConfig()
    logging: LoggingConfig = LoggingConfig()
    host: HostConfig = HostConfig()
    mqtt: MqttConfig | None = Field(None, description="no broker configured -> no telemetry")
    emulator: EmulatorRef = EmulatorRef()
    excitation: SineExcitation | SweptSine | None = Field(
        None, description="a signal added to one axis's rate command: a sine, or a swept sine (hil ident)")

    @field_validator("controller", "profile", "hexapod_limits", mode="before")
    @classmethod
    def _include(cls, value: Any, info: ValidationInfo) -> Any:
        """A string is a path to a YAML file holding that section (relative to the session file)."""
        if isinstance(value, str | Path):
            path = _resolve(value, info)
            return _read_yaml(Path(path))
        return value

    @model_validator(mode="after")
    def _profile_in_envelope(self) -> SessionConfig:
        violation = check_envelope(self.profile.protocol_segments(), self.hexapod_limits.envelope())
        if violation:
            raise ValueError(f"profile: {violation.describe()}")
        return self


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level")
    return data


def one_line(source: str, err: ValidationError) -> str:
    first = err.errors()[0]
    where = ".".join(str(p) for p in first["loc"])
    msg = str(first["msg"]).removeprefix("Value error, ")
    got = first.get("input")
    shown = "" if isinstance(got, dict | list) or got is None or first["type"].startswith("value_error") \
        else f" (got {got!r})"
    return f"{source}: {where + ': ' if where else ''}{msg}{shown}"


def load_model(model: type[M], path: str | Path) -> M:
    path = Path(path)
    try:
        data = _read_yaml(path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        return model.model_validate(data, context={"base_dir": path.parent})
    except ValidationError as exc:
        raise ConfigError(one_line(str(path), exc)) from None


def load_session(path: str | Path) -> SessionConfig:
    return load_model(SessionConfig, path)
