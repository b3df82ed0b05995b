"""A session log as pandas DataFrames, for notebooks: ``read_log_frames(path)``.

One DataFrame per log group (``.loop``, ``.timing``, ``.image``, ``.hexapod``, ``.links``,
``.events``), columns named as the log's channels, units in ``df.attrs["units"]``. It reads through
``read_log``, so a log still being written or left by a crash reads too (docs/log-format.md).
pandas is imported on first use only: the bench itself never needs it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.log.reader import LogData as _ArrayLog
from hil.log.reader import frame_attrs, read_log

if TYPE_CHECKING:
    import pandas as pd


class LogFrames:
    """A session log read into pandas: one DataFrame per group, plus the session's metadata.

    Attributes:
        loop, timing, image, hexapod, links, events: one ``pandas.DataFrame`` per group of the log
            (every group the file has, named after it; also ``frames[name]`` or ``data[name]``).
            Columns are the log's channels with their stored dtypes; ``df.attrs["units"]`` is
            ``{column: unit}`` (``"1"`` for counts, flags and ratios), ``df.attrs["docs"]`` describes each
            column, ``df.attrs["rate"]`` is the group's rate. In ``events``, ``kind`` and ``detail`` are
            text; ``detail`` is JSON text (``json.loads``), and ``event_details()`` decodes it.
        config: the session configuration the run used (a dict, as in its YAML file).
        provenance: software and library versions, git commit, plant file hash and the controller's
            full parameters (``{}`` for logs written before the bench recorded them).
        attrs: every file attribute, JSON ones decoded.
        path: the log file.
        closed_cleanly: False for a log still being written or left by a crash.
        trimmed: rows per group dropped as never written (a crashed log's unwritten tail).
    """

    def __init__(self, data: _ArrayLog, frames: dict[str, pd.DataFrame]) -> None:
        self.path: Path = data.path
        self.attrs: dict[str, Any] = data.attrs
        config = data.attrs.get("config")
        self.config: dict[str, Any] = config if isinstance(config, dict) else {}
        provenance = data.attrs.get("provenance")
        self.provenance: dict[str, Any] = provenance if isinstance(provenance, dict) else {}
        self.closed_cleanly: bool = data.closed_cleanly
        self.trimmed: dict[str, int] = dict(data.trimmed)
        self.frames: dict[str, pd.DataFrame] = frames

    # the groups as attributes: data.loop, data.image, ... (a group named like a fixed attribute: data["name"])
    def __getattr__(self, name: str) -> pd.DataFrame:
        frames = self.__dict__.get("frames")
        if frames is not None and name in frames:
            return frames[name]
        raise AttributeError(f"{type(self).__name__} has no attribute or log group {name!r}"
                             + (f" (groups: {', '.join(frames)})" if frames else ""))

    def __getitem__(self, group: str) -> pd.DataFrame:
        try:
            return self.frames[group]
        except KeyError:
            raise KeyError(f"no log group {group!r} (groups: {', '.join(self.frames)})") from None

    def __dir__(self) -> list[str]:
        return sorted({*super().__dir__(), *self.frames})

    @property
    def groups(self) -> list[str]:
        """The names of the log's groups, in file order."""
        return list(self.frames)

    @property
    def units(self) -> dict[str, dict[str, str]]:
        """``{group: {column: unit}}`` for every group."""
        return {g: dict(df.attrs.get("units", {})) for g, df in self.frames.items()}

    def event_details(self, kind: str | None = None) -> list[dict[str, Any]]:
        """The events as dicts (``t_host_ns``, ``tick``, ``kind`` and the decoded ``detail``), optionally of one kind.

        A detail that is not a JSON object (plain text, or JSON cut at 480 bytes) comes back as ``{"text": ...}``.
        """

        events = self.frames.get("events")
        if events is None:
            return []
        out = []
        for row in events.itertuples(index=False):
            if kind is not None and row.kind != kind:
                continue
            try:
                detail = json.loads(row.detail)
            except (TypeError, ValueError):
                detail = None
            if not isinstance(detail, dict):
                detail = {"text": row.detail}
            out.append({"t_host_ns": int(row.t_host_ns), "tick": int(row.tick), "kind": row.kind, "detail": detail})
        return out

    def __repr__(self) -> str:
        state = "" if self.closed_cleanly else ", live or crashed"
        head = f"<LogFrames {self.path}{state}"
        who = [f"{k} {self.attrs[k]}" for k in ("session_name", "controller", "clock") if self.attrs.get(k)]
        lines = [head + (f": {', '.join(who)}" if who else "")]
        width = max((len(g) for g in self.frames), default=0)
        for g, df in self.frames.items():
            rate = df.attrs.get("rate", "")
            line = f"  .{g:<{width}}  {len(df):>9} rows x {df.shape[1]:>2} columns"
            lines.append(line + (f"  ({rate})" if rate else ""))
        return "\n".join(lines) + ">"


def read_log_frames(path: str | Path, *, groups: list[str] | None = None) -> LogFrames:
    """Read a session log (.h5) into pandas DataFrames, one per group.

    Example::

        data = read_log_frames("runs/swing-1deg-1hz-eso-20261121-101500.h5")
        data                                   # the groups with their row counts
        loop = data.loop                       # a DataFrame: one row per 1 kHz control cycle
        loop.attrs["units"]["gyro_y_dps"]      # 'deg/s'
        t = (loop.t_host_ns - loop.t_host_ns.iloc[0]) * 1e-9   # seconds since the first sample
        loop.plot(x="t_s", y=["rate_cmd_el_dps", "gyro_y_dps"])
        data.image[data.image.track_valid == 1][["miss_x_px", "miss_y_px"]].describe()
        data.config["controller"], data.provenance["controller"]["params"]
        data.event_details("fault")            # the faults, details decoded

    Columns keep the log's channel names and dtypes. ``t_host_ns`` (the bench PC's monotonic clock, ns)
    is in every group except ``timing``; join ``timing`` to ``loop`` on ``tick``. Units are in
    ``df.attrs["units"]`` (pandas keeps ``attrs`` through most operations, not through every one:
    ``data.units`` always has them). docs/log-format.md describes every group and channel.

    Works on a closed log, on one still being written (it reads what has been flushed so far: call
    again for more) and on one left by a crash (the unwritten tail is trimmed, see ``.trimmed``).
    ``groups``: read only these (default: all). Raises ``hil.log.LogError`` if the file is not a
    readable session log or lacks a group asked for.
    """
    import pandas as pd  # noqa: PLC0415  (heavy: loaded only for DataFrames)

    data = read_log(path, groups=groups)
    frames: dict[str, pd.DataFrame] = {}
    for g, cols in data.groups.items():
        df = pd.DataFrame({c: v for c, v in cols.items()}, copy=False)
        df.attrs.update(frame_attrs(g, data))
        frames[g] = df
    return LogFrames(data, frames)


LogData = LogFrames  # the name the top-level API (``hil.read_log``) gives it; hil.log.LogData is read_log's numpy form
