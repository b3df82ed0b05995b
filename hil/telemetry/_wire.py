"""What the telemetry puts on the broker (docs/telemetry.md): its topics, the channels' units (from the session log's
schema) and compact JSON with NaN and infinities as null. The publisher (``_publisher``) and ``hil watch``
(``_watch``) both speak it.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Mapping
from functools import cache
from types import MappingProxyType
from typing import Any

from hil.log.schema import SCHEMA

TOPIC_ROOT = "hil"
MISS_X, MISS_Y = "miss_x_px", "miss_y_px"  # the miss distance's channels (named as in the log's image group)


@cache
def schema_units() -> Mapping[str, str]:
    """Channel name -> unit, from the session log's schema (hil.log.schema): the units telemetry publishes.

    A name that appears in several groups (``t_host_ns``, ``tick``) has the same unit in each; the first wins.
    """

    units: dict[str, str] = {}
    for group in SCHEMA:
        for channel in group.channels:
            units.setdefault(channel.name, channel.unit)
    return MappingProxyType(units)


# --- topics -----------------------------------------------------------------------------------


def status_topic(bench_id: str) -> str:
    """``hil/<bench_id>/status``: retained online/offline (the last will publishes offline)."""
    return f"{TOPIC_ROOT}/{bench_id}/status"


def session_topic(bench_id: str, session_id: str, leaf: str) -> str:
    """``hil/<bench_id>/session/<session_id>/<leaf>``; leaf is state, meta, telemetry or events."""
    return f"{TOPIC_ROOT}/{bench_id}/session/{session_id}/{leaf}"


def meta_topic(bench_id: str, session_id: str) -> str:
    return session_topic(bench_id, session_id, "meta")


# --- JSON -------------------------------------------------------------------------------------


def _json_default(o: Any) -> Any:
    item = getattr(o, "item", None)  # numpy scalars (float32, int64, bool_)
    if callable(item):
        with contextlib.suppress(Exception):
            return item()
    if isinstance(o, (set, frozenset, tuple)):
        return list(o)
    return str(o)


_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False, default=_json_default)


def _finite(o: Any) -> Any:
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


def dumps(obj: Any) -> str:
    """Compact JSON; NaN and infinities become null (strict JSON, readable by any client)."""
    try:
        return _ENCODER.encode(obj)
    except ValueError:  # a non-finite float: rare, so the sanitising pass is only paid then
        return _ENCODER.encode(_finite(json.loads(json.dumps(obj, default=_json_default))))
