"""Where and how the bench publishes telemetry (hil.telemetry does the publishing): the ``mqtt:`` section of a session
file, kept apart from the publisher so that reading a config loads no MQTT client.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Self
from urllib.parse import parse_qsl, unquote, urlsplit

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, SecretStr, field_validator, model_validator

from hil.config._files import confinement, read_text_file, resolve_relative

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")
_NAME_RULE = "1-64 characters from A-Z a-z 0-9 _ . - starting with a letter or digit (topic-safe: no / + # or spaces)"


def check_topic_name(what: str, value: str) -> str:
    """``value``, if it is safe as one level of an MQTT topic; ValueError naming ``what`` otherwise."""
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        raise ValueError(f"{what} {value!r} is not topic-safe: use {_NAME_RULE}")
    return value


MAX_PASSWORD_FILE_BYTES = 4096


class MqttConfig(BaseModel):
    """Where and how to publish. No config means no MQTT: the session creates no Telemetry.

    The password comes from one of ``password`` (in the file), ``password_env`` (an environment variable)
    or ``password_file`` (the file's first line); :attr:`password_value` is what the broker gets. No dump of
    this model holds it: ``password`` is a ``SecretStr`` (``'**********'`` in JSON, in the session log's
    ``config`` attribute and in ``repr``), the other two name where it is, and the resolved value is private.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    host: str = Field(min_length=1, max_length=253)
    port: int = Field(1883, ge=1, le=65535)
    bench_id: str = "bench"
    telemetry_hz: float = Field(50.0, gt=0, le=1000)
    queue_size: int = Field(1000, ge=1, le=1_000_000)
    qos: int = Field(0, ge=0, le=1)  # of telemetry; status, meta, state and events always use QoS 1
    keepalive_s: int = Field(10, ge=1, le=65535)
    reconnect_min_s: float = Field(0.5, gt=0, le=3600)
    reconnect_max_s: float = Field(10.0, gt=0, le=3600)
    username: str | None = Field(None, max_length=65535)
    password: SecretStr | None = Field(None, max_length=65535, description="the broker password (prefer the two below)")
    password_env: str | None = Field(None, pattern=r"^[A-Za-z_][A-Za-z0-9_]{0,127}$",
                                     description="the environment variable holding the password")
    password_file: Path | None = Field(None, description="a file whose first line is the password "
                                                         "(relative to the session file)")
    _password: str | None = PrivateAttr(None)

    @field_validator("bench_id")
    @classmethod
    def _bench_id_topic_safe(cls, v: str) -> str:
        return check_topic_name("bench_id", v)

    _relative_to_the_file = field_validator("password_file", mode="before")(resolve_relative)

    @field_validator("password_env", mode="before")
    @classmethod
    def _not_the_service_s_environment(cls, v: Any) -> Any:
        """A submitted item (:func:`hil.config.confined_to`) names no variable of the environment it is read in."""
        if v is not None and confinement() is not None:
            raise ValueError("a submitted item reads no environment variable of the service's; the broker's password "
                             "comes from the service's own configuration")
        return v

    @model_validator(mode="after")
    def _backoff_order(self) -> Self:
        if self.reconnect_min_s > self.reconnect_max_s:
            raise ValueError(f"reconnect_min_s ({self.reconnect_min_s}) > reconnect_max_s ({self.reconnect_max_s})")
        return self

    @model_validator(mode="after")
    def _resolve_password(self) -> Self:
        """Read the password from where it is (at validation, so a missing one is bad input, exit 2)."""
        given = [name for name in ("password", "password_env", "password_file") if getattr(self, name) is not None]
        if len(given) > 1:
            raise ValueError(f"{given[1]}: give the password one way only (also given: {given[0]})")
        if self.password is not None:
            self._password = self.password.get_secret_value()
        elif self.password_env is not None:
            value = os.environ.get(self.password_env)
            if value is None:
                raise ValueError(f"password_env: the environment variable {self.password_env} is not set")
            self._password = value
        elif self.password_file is not None:
            text = read_text_file(self.password_file, MAX_PASSWORD_FILE_BYTES)  # ValueError naming the file
            self._password = text.splitlines()[0] if text else ""
        return self

    @property
    def password_value(self) -> str | None:
        """The password to give the broker (None: no password); never dumped, never logged."""
        return self._password

    @classmethod
    def from_url(cls, url: str, **overrides: Any) -> MqttConfig:
        """``mqtt://[user[:password]@]host[:port][?bench_id=rig2&telemetry_hz=20]`` -> MqttConfig.

        Query parameters and keyword overrides set the other fields (keywords win). Only plain
        TCP (``mqtt://`` or ``tcp://``) is supported; raises ValueError on anything else.
        """
        parts = urlsplit(url.strip())
        if parts.password:  # messages show the URL without its password
            url = url.replace(f":{parts.password}@", ":***@", 1)
        if parts.scheme not in ("mqtt", "tcp"):
            raise ValueError(f"MQTT URL {url!r}: scheme must be mqtt:// (TLS is not supported)")
        if parts.path not in ("", "/") or parts.fragment:
            raise ValueError(f"MQTT URL {url!r}: expected mqtt://host[:port], with no path")
        try:
            port = parts.port
        except ValueError as exc:
            raise ValueError(f"MQTT URL {url!r}: {exc}") from None
        if not parts.hostname:
            raise ValueError(f"MQTT URL {url!r} names no host")
        fields: dict[str, Any] = {"host": parts.hostname}
        if port is not None:
            fields["port"] = port
        if parts.username:
            fields["username"] = unquote(parts.username)
        if parts.password:
            fields["password"] = unquote(parts.password)
        fields.update(parse_qsl(parts.query, strict_parsing=False))
        fields.update(overrides)
        return cls(**fields)

    @property
    def url(self) -> str:
        """The broker address, without credentials (for messages)."""
        return f"mqtt://{self.host}:{self.port}"
