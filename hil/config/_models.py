"""Session configuration: every YAML file the bench reads is one of these pydantic models.

    profiles/sessions/*.yaml      SessionConfig (references the files below by relative path)
    profiles/controllers/*.yaml   ControllerConfig (a registry name and its parameters)
    profiles/swing/*.yaml         SwingProfile (hexapod segments)
    profiles/hexapod/*.yaml       HexapodLimits (the swing table's envelope, checked before upload)

Bad input is a :class:`ConfigError` whose message is one line naming the file, the field and the
reason; the CLI prints it and exits 2. Every file goes through :func:`read_yaml_mapping` (a regular
file of at most ``MAX_CONFIG_BYTES``, UTF-8, bounded YAML: docs/reliability.md); every number must be
finite and lie in its documented range.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    PrivateAttr,
    SecretStr,
    SerializationInfo,
    SerializerFunctionWrapHandler,
    Tag,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_serializer,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from hil.boards import load_hexapod_driver
from hil.config._excitation import SweptSine
from hil.config._files import ConfigError, confinement, read_yaml_mapping, resolve_relative
from hil.config._mqtt import MqttConfig
from hil.control.registry import ControllerConfigError, controller_params
from hil.link import baud_budget
from hil.protocol import LINE_RATE_BAUD, HexAxis
from hil.protocol.swing import Envelope, Segment, check_envelope

M = TypeVar("M", bound=BaseModel)
REPO = Path(__file__).resolve().parents[2]
PROFILES = REPO / "profiles"
DEFAULT_EMULATOR = PROFILES / "emulator" / "default.yaml"

MAX_SESSION_S = 24 * 3600.0  # longest session
MAX_PROFILE_S = 3600.0  # latest end of a swing segment: the envelope check samples the profile every 1 ms
MAX_SWING_FREQUENCY_HZ = 100.0  # a fifth of the envelope check's 500 Hz Nyquist
MAX_SEED = 2**32 - 1
NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$"  # a file or directory name: no '/', no leading '.'
Seed = Annotated[int, Field(ge=0, le=MAX_SEED)]


class Strict(BaseModel):
    """Base of every config model: unknown fields refused, immutable, NaN and infinities refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class PortConfig(Strict):
    port: str = Field(min_length=1, max_length=4096,
                      description="serial device, e.g. /dev/ttyUSB0 or /dev/serial/by-id/...")
    baudrate: int = Field(LINE_RATE_BAUD, gt=0, le=12_000_000, description="the line's rate, bit/s (8N1)")


class PortsConfig(Strict):
    servo: PortConfig
    driver: PortConfig
    image: PortConfig
    hexapod: PortConfig | None = Field(
        None, description="the hexapod controller's link; needed only by a hexapod driver that uses the bench's "
        "link (the protocol driver, the default), never opened otherwise")
    wire_delay_budget_us: float = Field(
        100.0, gt=0, le=1000,
        description="what the wire may add to every 1 kHz cycle (GYRO_SAMPLE in, DRIVE_CMD out) before `hil doctor` "
        "warns: 10 % of the period, which the default line rate keeps (docs/emulator.md)")

    @model_validator(mode="after")
    def _carries_the_link_budget(self) -> PortsConfig:
        """Each link's baud rate carries its periodic messages (docs/protocol.md, "Link budget"; the check `hil
        doctor` makes): a line too slow for 1 kHz GYRO_SAMPLEs is refused before anything is sent."""
        for name in ("servo", "driver", "image", "hexapod"):
            port = getattr(self, name)
            if port is not None:
                budget = baud_budget(name, port.baudrate)
                if not budget.ok:
                    raise ValueError(f"{name}.baudrate: {budget.detail}")
        return self


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
    amplitude: float = Field(ge=-1000, le=1000, description="mm for x/y/z, deg for roll/pitch/yaw")
    frequency_hz: float = Field(ge=0, le=MAX_SWING_FREQUENCY_HZ)
    start_s: float = Field(0.0, ge=0, le=MAX_PROFILE_S)
    duration_s: float = Field(gt=0, le=MAX_PROFILE_S)
    phase_deg: float = Field(0.0, ge=-360, le=360)
    ramp_s: float = Field(0.0, ge=0, le=MAX_PROFILE_S, description="linear ramp in and out")

    @model_validator(mode="after")
    def _ends_in_time(self) -> SwingSegment:
        if self.start_s + self.duration_s > MAX_PROFILE_S:
            raise ValueError(f"duration_s: the segment ends at {self.start_s + self.duration_s:g} s, after the "
                             f"{MAX_PROFILE_S:g} s a profile may last")
        return self

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
    position: float = Field(gt=0, le=1e4, description="mm or deg")
    rate: float = Field(gt=0, le=1e6, description="mm/s or deg/s")
    accel: float = Field(gt=0, le=1e8, description="mm/s^2 or deg/s^2")


class HexapodLimits(Strict):
    """The swing table's envelope, as its datasheet gives it (symmetric +- limits)."""

    x: AxisLimits
    y: AxisLimits
    z: AxisLimits
    roll: AxisLimits
    pitch: AxisLimits
    yaw: AxisLimits

    def envelope(self) -> Envelope:
        x, y, z, roll, pitch, yaw = self.x, self.y, self.z, self.roll, self.pitch, self.yaw
        return Envelope((x.position, y.position, z.position, roll.position, pitch.position, yaw.position),
                        (x.rate, y.rate, z.rate, roll.rate, pitch.rate, yaw.rate),
                        (x.accel, y.accel, z.accel, roll.accel, pitch.accel, yaw.accel))


class HexapodConfig(BaseModel):
    """The session's ``hexapod`` section: which driver moves the swing table, with that driver's options
    (docs/hexapod-drivers.md). ``driver`` names an entry point of the group ``hil.hexapod_drivers``; every other key
    is an option of that driver, checked by the driver's own ``Options`` model (a fault names ``hexapod.FIELD``).

    Dumps and repr show the validated options (defaults included) as the driver's model dumps them, so an option
    the driver declares as ``SecretStr`` is ``'**********'`` in the session log's ``config`` attribute."""

    model_config = ConfigDict(extra="allow", frozen=True, allow_inf_nan=False)

    driver: str = Field("protocol", min_length=1, max_length=128,
                        description="an installed hexapod driver: protocol (this bench's protocol on the hexapod "
                        "link, the default) or a driver package's entry point in hil.hexapod_drivers")
    _driver_class: Any = PrivateAttr(None)
    _options: Any = PrivateAttr(None)

    @model_validator(mode="after")
    def _driver_and_options(self, info: ValidationInfo) -> HexapodConfig:


        try:
            cls = load_hexapod_driver(self.driver)
        except ValueError as exc:
            raise ValidationError.from_exception_data(type(self).__name__, [InitErrorDetails(
                type=PydanticCustomError("value_error", str(exc)), loc=("driver",), input=self.driver)]) from None
        self._driver_class = cls
        self._options = cls.Options.model_validate(self.model_extra or {}, context=info.context)
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler, info: SerializationInfo) -> dict[str, Any]:
        if self._options is None:
            return handler(self)
        return {"driver": self.driver, **self._options.model_dump(mode=info.mode)}

    def __repr_args__(self) -> Any:
        yield "driver", self.driver
        if self._options is not None:
            yield from self._options.__repr_args__()

    @property
    def driver_class(self) -> Any:
        """The driver's class (a ``hil.boards.HexapodDriver``), resolved when the section was validated."""
        return self._driver_class

    @property
    def options(self) -> Any:
        """The driver's options: an instance of its ``Options`` model."""
        return self._options

    def secret_options(self) -> list[str]:
        """The options holding a secret (a ``SecretStr`` that is set): a dump shows them masked."""
        if self._options is None:
            return []
        return [name for name, value in self._options if isinstance(value, SecretStr)]


class TrackingConfig(Strict):
    """The outer loop: miss distance (px) at camera rate -> rate command (deg/s) per axis."""

    enabled: bool = True
    kp_per_s: float = Field(8.0, ge=0, le=1000)
    ki_per_s2: float = Field(0.0, ge=0, le=1e4)
    ifov_deg_per_px: float = Field(0.002, gt=0, le=1, description="the camera's pixel angle")
    max_rate_dps: float = Field(20.0, gt=0, le=1000)
    max_lost_s: float = Field(
        1.0, gt=0, le=MAX_SESSION_S,
        description="tracking enabled: the longest the target may go without a valid frame once acquired; a session "
        "that never acquires it, or loses it for longer, ends lost_target (exit code 4), not completed")
    stale_s: float = Field(0.05, gt=0, le=10)
    gate_px: int = Field(0, ge=0, le=65535, description="TRACK_CMD gate half-size, 0 = the whole field")
    apply_after_ms: float = Field(
        11.0, ge=0, le=100,
        description="a frame is used from the first gyro sample later than its exposure + this (board clock), "
        "or when it arrives if that is later: one 100 Hz frame of latency + 1 ms, so every run of a lockstep "
        "session uses each frame at the same tick")


class StartPoseConfig(Strict):
    """Before the swing and the tracking start, the gimbal is brought to its start pose: a position hold on the
    encoders (rate command = ``kp_per_s`` x the angle error, at most ``max_rate_dps``), the platform at rest, until
    both axes have stayed within ``tolerance_deg`` for ``hold_ms``. Not there within ``timeout_s``: the session
    ends ``fault``, unarmed, before anything swings (docs/control.md, "The start pose")."""

    enabled: bool = Field(True, description="false: the swing starts with the stream, wherever the gimbal is")
    az_deg: float = Field(0.0, ge=-180, le=180, description="azimuth encoder angle to start from")
    el_deg: float = Field(0.0, ge=-90, le=90, description="elevation encoder angle to start from")
    tolerance_deg: float = Field(0.05, gt=0, le=10, description="both axes this close to the pose ...")
    hold_ms: float = Field(50.0, ge=1, le=10_000, description="... for this long (board time) ends the phase")
    kp_per_s: float = Field(5.0, gt=0, le=100, description="position gain: deg/s of rate command per deg of error")
    max_rate_dps: float = Field(20.0, gt=0, le=200, description="the largest rate the phase commands")
    timeout_s: float = Field(10.0, gt=0, le=120, description="not at the pose within this: the session faults")


class SafetyConfig(Strict):
    watchdog_ms: float = Field(5.0, gt=0, le=10_000, description="no GYRO_SAMPLE for this long -> zero drive, DISABLE")
    on_fault: Literal["stop", "recover"] = Field("stop", description="after a watchdog/link/driver fault")
    recover_after_ms: float = Field(200.0, ge=0, le=60_000, description="recover: wait this long, then re-arm")
    max_recoveries: int = Field(3, ge=0, le=1000)
    max_drive_counts: int = Field(30000, gt=0, le=32767, description="|DRIVE_CMD| saturation")
    max_slew_counts: int = Field(32767, gt=0, le=65535, description="largest change of the drive per tick")
    emulator_stall_grace_ms: float = Field(
        0.0, ge=0, le=10_000,
        description="emulated boards only (a loopback run, realtime): a silence past watchdog_ms that ends with the "
        "emulator's CLOCK_LATE (the host it shares with the bench did not run its clock in time), or with the next "
        "sample and none lost (the host held the bytes up), is a host stall, not a fault; a silence that lost samples, "
        "or is longer than this, still trips. 0 = off; refused with real ports")


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
    """What a loopback run starts in place of the lab."""

    config: Path = DEFAULT_EMULATOR
    clock: Literal["realtime", "lockstep", "sim"] = Field(
        "lockstep", description="realtime: paced 1 kHz over ptys; lockstep: the full protocol over ptys, "
        "byte-reproducible; sim: boards and plant in the bench's process, logs identical to lockstep")
    rt_priority: int = Field(0, ge=0, le=99, description="SCHED_FIFO priority of the emulator's clock, 0 = normal")
    cpu: int | None = Field(
        None, ge=-1024, le=1023,
        description="pin the emulator to this CPU index (-1 = the last); the same CPU as host.loop_cpu keeps "
        "the sample/command round trip on one core (docs/performance.md)")

    def process_args(self) -> list[str]:
        """Its scheduling options on the emulator's command line (``python -m firmware_stub ...``)."""
        args = ["--rt-priority", str(self.rt_priority)]
        return args if self.cpu is None else [*args, "--cpu", str(self.cpu)]

    @field_validator("config", mode="before")
    @classmethod
    def _relative_to_the_file(cls, value: Any, info: ValidationInfo) -> Any:
        """Relative to the session file; confined (a submitted item, :func:`hil.config.confined_to`), only the
        default: an emulator file names further files (its plant) that the emulator reads itself, unconfined."""
        if confinement() is None or not isinstance(value, str | Path):
            return resolve_relative(value, info)
        if Path(value) != DEFAULT_EMULATOR:
            raise ValueError("a submitted item runs on the service's own lab and names no emulator file (the emulator "
                             "reads the files an emulator file names)")
        return DEFAULT_EMULATOR


class SineExcitation(Strict):
    """A sine added to one axis's rate command, on top of tracking (seed 000 Fig. 13: 5 deg/s at 15 Hz)."""

    axis: Literal["el", "az"] = "el"
    amplitude_dps: float = Field(gt=0, le=200, description="peak rate added to the command")
    freq_hz: float = Field(gt=0, le=450, description="below the 500 Hz Nyquist of the 1 kHz loop")
    start_s: float = Field(0.0, ge=0, le=MAX_SESSION_S, description="zero before this session time")

    def rate_dps(self, t_s: float) -> float:
        """The added rate command at session time ``t_s`` (plain floats: it runs in the 1 kHz loop)."""
        if t_s < self.start_s:
            return 0.0
        return self.amplitude_dps * math.sin(2.0 * math.pi * self.freq_hz * (t_s - self.start_s))


_SECTIONS: dict[str, type[Strict]] = {}  # session fields that may name a file holding them (filled below)


def _excitation_kind(value: Any) -> str:
    """A sine has ``freq_hz`` (or ``start_s``); anything else is a swept sine (all its fields have defaults).
    Telling them apart first makes an error name the field of the kind that was meant."""
    if isinstance(value, BaseModel):
        return "sine" if isinstance(value, SineExcitation) else "sweep"
    return "sine" if isinstance(value, dict) and ("freq_hz" in value or "start_s" in value) else "sweep"


Excitation = Annotated[Annotated[SineExcitation, Tag("sine")] | Annotated[SweptSine, Tag("sweep")],
                       Discriminator(_excitation_kind)]


class SessionConfig(Strict):
    name: str = Field(pattern=NAME_PATTERN, description="used in the log file name")
    description: str = ""
    duration_s: float = Field(gt=0, le=MAX_SESSION_S, description="run time with the stream on, s")
    seed: Seed = Field(0, description="emulator seed in loopback; recorded in the log")
    ports: PortsConfig | None = Field(None, description="the lab's serial ports (not needed for a loopback run; "
                                      "their baud rates set the emulated links' when given)")
    controller: ControllerConfig = ControllerConfig()
    tracking: TrackingConfig = TrackingConfig()
    start_pose: StartPoseConfig = StartPoseConfig()
    profile: SwingProfile = SwingProfile()
    hexapod_limits: HexapodLimits
    hexapod: HexapodConfig = Field(default_factory=HexapodConfig,
                                   description="the swing table's driver and its options (docs/hexapod-drivers.md)")
    safety: SafetyConfig = SafetyConfig()
    logging: LoggingConfig = LoggingConfig()
    host: HostConfig = HostConfig()
    mqtt: MqttConfig | None = Field(None, description="no broker configured -> no telemetry")
    emulator: EmulatorRef = EmulatorRef()
    excitation: Excitation | None = Field(
        None, description="a signal added to one axis's rate command: a sine, or a swept sine (hil ident)")

    def link_baudrates(self) -> dict[str, int]:
        """The ports' baud rates by link: an emulated lab's links run at them (empty without ``ports``)."""
        if self.ports is None:
            return {}
        return {name: port.baudrate for name in ("servo", "driver", "image", "hexapod")
                if (port := getattr(self.ports, name)) is not None}

    @field_validator("controller", "profile", "hexapod_limits", mode="before")
    @classmethod
    def _include(cls, value: Any, info: ValidationInfo) -> Any:
        """A string is a path to a YAML file holding that section (relative to the session file); a fault
        in it names that file."""
        if isinstance(value, str | Path):
            assert info.field_name is not None
            return load_model(_SECTIONS[info.field_name], resolve_relative(value, info))
        return value

    @model_validator(mode="after")
    def _profile_in_envelope(self) -> SessionConfig:
        violation = check_envelope(self.profile.protocol_segments(), self.hexapod_limits.envelope())
        if violation:
            raise ValueError(f"profile: {violation.describe()}")
        return self

    @model_validator(mode="after")
    def _hexapod_port(self) -> SessionConfig:
        if self.ports is not None and self.ports.hexapod is None and self.hexapod.driver_class.uses_link:
            raise ValueError(f"ports.hexapod: the hexapod driver {self.hexapod.driver!r} talks over the bench's "
                             "hexapod link; give its serial port")
        return self


_SECTIONS.update(controller=ControllerConfig, profile=SwingProfile, hexapod_limits=HexapodLimits)


def _shown(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def one_line(source: str, err: ValidationError) -> str:
    """The first problem of a pydantic error as one line: ``source: field.path: reason (got value)``."""
    first = err.errors()[0]
    where = ".".join(str(p) for p in first["loc"])
    msg = str(first["msg"]).removeprefix("Value error, ")
    got = first.get("input")
    secret = any(word in str(p) for p in first["loc"] for word in ("password", "token"))  # never echoed
    shown = "" if isinstance(got, dict | list) or got is None or first["type"].startswith("value_error") or secret \
        else f" (got {_shown(got)})"
    return " ".join(f"{source}: {where + ': ' if where else ''}{msg}{shown}".split())


def load_model(model: type[M], path: str | Path) -> M:
    """Read a YAML config file into ``model`` (relative paths in it are relative to the file)."""
    path = Path(path)
    try:
        data = read_yaml_mapping(path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        return model.model_validate(data, context={"base_dir": path.parent})
    except ValidationError as exc:
        raise ConfigError(one_line(str(path), exc)) from None


def load_session(path: str | Path) -> SessionConfig:
    return load_model(SessionConfig, path)


def session_yaml(config: SessionConfig, *, exclude: Any = None) -> str:
    """A loaded session as YAML that loads back to the same session anywhere (its parts inline); ``exclude`` as
    pydantic's ``model_dump`` takes it (``{"ports": True, "logging": {"dir"}}``) leaves those fields out."""
    return yaml.safe_dump(config.model_dump(mode="json", exclude_none=True, exclude=exclude), sort_keys=False)
