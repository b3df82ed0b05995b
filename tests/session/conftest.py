from tests.telemetry.broker import mqtt_broker  # noqa: F401  (the real-broker fixture)
