"""MQTT telemetry: the session's publisher (never blocks the loop; queues, drops and counts while the broker is
away), its helper process, and ``hil watch``, the terminal view of a bench's topics (docs/telemetry.md)."""

from hil.config import MqttConfig  # the broker section of a session's config, also importable from here
from hil.telemetry._publisher import Telemetry, TelemetryProcess, TelemetryStats
from hil.telemetry._watch import sparkline, watch
from hil.telemetry._wire import dumps, schema_units

__all__ = [
    "MqttConfig",
    "Telemetry",
    "TelemetryProcess",
    "TelemetryStats",
    "dumps",
    "schema_units",
    "sparkline",
    "watch",
]
