"""Fixtures of the telemetry tests: a real MQTT broker (see tests/telemetry/broker.py).

Other test packages get the same fixture by importing it into their own conftest.py::

    from tests.telemetry.broker import mqtt_broker  # noqa: F401
"""

from __future__ import annotations

from tests.telemetry.broker import mqtt_broker

__all__ = ["mqtt_broker"]
