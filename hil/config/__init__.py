"""The bench's configuration: every file a pydantic model, read within bounds, one-line errors.

``load_session`` reads a session YAML (``SessionConfig``: ports, swing, controller, tracking, safety, log, MQTT);
``ConfigError`` is the one error a bad file gives (a ValueError naming the file and field; exit 2 at the CLI).
Files are read bounded (``read_yaml_mapping``: size, YAML node count, regular file), relative paths resolved
against the file that names them (``resolve_relative``), or kept inside a submitted item's own files
(``confined_to``); ``MqttConfig`` is the broker section."""

from hil.config._excitation import IDENT_SWEEP, SweptSine
from hil.config._files import (
    MAX_CONFIG_BYTES,
    MAX_YAML_NODES,
    ConfigError,
    confined_to,
    confinement,
    named,
    parse_yaml,
    read_file_bytes,
    read_text_file,
    read_yaml_mapping,
    require_regular_file,
    require_writable_dir,
    resolve_relative,
)
from hil.config._models import (
    MAX_SESSION_S,
    NAME_PATTERN,
    PROFILES,
    ControllerConfig,
    EmulatorRef,
    Excitation,
    HexapodLimits,
    PortConfig,
    SafetyConfig,
    Seed,
    SessionConfig,
    StartPoseConfig,
    Strict,
    SwingProfile,
    TrackingConfig,
    load_model,
    load_session,
    one_line,
    session_yaml,
)
from hil.config._mqtt import MqttConfig, check_topic_name

__all__ = [
    "IDENT_SWEEP",
    "MAX_CONFIG_BYTES",
    "MAX_SESSION_S",
    "MAX_YAML_NODES",
    "NAME_PATTERN",
    "PROFILES",
    "ConfigError",
    "ControllerConfig",
    "EmulatorRef",
    "Excitation",
    "HexapodLimits",
    "MqttConfig",
    "PortConfig",
    "SafetyConfig",
    "Seed",
    "SessionConfig",
    "StartPoseConfig",
    "Strict",
    "SweptSine",
    "SwingProfile",
    "TrackingConfig",
    "check_topic_name",
    "confined_to",
    "confinement",
    "load_model",
    "load_session",
    "named",
    "one_line",
    "parse_yaml",
    "read_file_bytes",
    "read_text_file",
    "read_yaml_mapping",
    "require_regular_file",
    "require_writable_dir",
    "resolve_relative",
    "session_yaml",
]
