"""Who may do what (docs/service.md, "Tokens and roles").

Bound to localhost the service needs no token: every caller is an operator, named by the ``X-Hil-User`` header
its client sends (the login name; ``local`` without one). Bound to any other address it refuses to start
without a token file: a YAML file of tokens, each with its user and role, ``viewer`` (read and watch) or
``operator`` (submit, lease, stop, abort). A request carries its token as ``Authorization: Bearer TOKEN``, a
``hil_token`` cookie, or a ``token`` query parameter (a WebSocket from a browser cannot set a header). A token is
compared in constant time and never written anywhere: not in a log, a record, a report or an error message.
"""

from __future__ import annotations

import hmac
import ipaddress
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError

from hil.config import ConfigError, one_line, read_yaml_mapping

Role = Literal["viewer", "operator"]
ROLES: tuple[str, ...] = ("viewer", "operator")
LOCAL_USER = "local"
MIN_TOKEN_CHARS = 16


class TokenEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    user: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.@-]+$")
    role: Role
    token: SecretStr = Field(min_length=MIN_TOKEN_CHARS)


class TokenFile(BaseModel):
    """The token file `hil serve` is given: the service's tokens (docs/service.md)."""

    model_config = ConfigDict(extra="forbid")
    tokens: list[TokenEntry] = Field(min_length=1)


@dataclass(frozen=True)
class Caller:
    user: str
    role: str

    @property
    def operator(self) -> bool:
        return self.role == "operator"


class AuthError(Exception):
    """A request without a valid token (HTTP 401) or with too little a role (HTTP 403); the message never holds
    the token."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def load_tokens(path: Path) -> TokenFile:
    """The token file at ``path``; ConfigError naming the file and the field (never a token's value)."""
    try:
        data = read_yaml_mapping(path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        tokens = TokenFile.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(one_line(str(path), exc)) from None
    seen: set[str] = set()
    for i, entry in enumerate(tokens.tokens):
        value = entry.token.get_secret_value()
        if value in seen:
            raise ConfigError(f"{path}: tokens.{i}.token: the same token twice")
        seen.add(value)
    return tokens


def is_loopback_host(host: str) -> bool:
    """Does binding to ``host`` keep the service on this machine (127.0.0.0/8, ::1, localhost)?"""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Gate:
    """Maps a request's token (or, without a token file, its ``X-Hil-User``) to a :class:`Caller`."""

    def __init__(self, tokens: TokenFile | None) -> None:
        self.tokens = tokens

    @property
    def open(self) -> bool:
        return self.tokens is None

    def caller(self, token: str | None, user_header: str | None) -> Caller:
        if self.tokens is None:
            user = (user_header or LOCAL_USER).strip()[:64] or LOCAL_USER
            return Caller("".join(c if c.isalnum() or c in "_.@-" else "_" for c in user), "operator")
        if not token:
            raise AuthError(401, "a token is needed: send Authorization: Bearer TOKEN (or the hil_token cookie)")
        given = token.encode()
        for entry in self.tokens.tokens:
            if hmac.compare_digest(given, entry.token.get_secret_value().encode()):
                return Caller(entry.user, entry.role)
        raise AuthError(401, "the token is not one of this service's")

    @staticmethod
    def require_operator(caller: Caller, what: str) -> None:
        if not caller.operator:
            raise AuthError(403, f"{what}: needs the operator role; {caller.user} is a {caller.role}")
