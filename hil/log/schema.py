"""The session log's layout: every group, channel, dtype and unit, in one place.

The writer creates exactly these datasets, the reader and the exporters follow them, and
docs/log-format.md renders its tables from them (``hil.log.docgen``). Change a channel here and
the document test fails until ``hil.log.docgen`` regenerates the tables (its docstring says how).

Rows are appended as tuples of values in the order of ``Group.channels``.
"""

from __future__ import annotations

import json
import re
from typing import Any, NamedTuple

import numpy as np

from hil.protocol import CATALOGUE, LINKS, DriveStatus

LOG_FORMAT_VERSION = 1

KIND_LEN = 32  # events/kind: fixed-length ASCII, NUL-padded
DETAIL_LEN = 480  # events/detail: fixed-length ASCII (JSON text), NUL-padded, truncated with "..." if longer
LATE_US = 1000.0  # loop/latency_us above this: a late cycle (its command went out after the next sample was due)



class Channel(NamedTuple):
    name: str
    dtype: str  # a numpy dtype string: 'f8', 'f4', 'i4', 'u4', 'u1', 'i8', or 'S<n>' (fixed-length ASCII)
    unit: str  # '1' for dimensionless numbers, flags and counts
    doc: str


class Group(NamedTuple):
    name: str
    rate: str
    doc: str
    channels: tuple[Channel, ...]


class AttrSpec(NamedTuple):
    name: str
    type: str  # as stored in the file: 'str', 'int', 'float', 'JSON text'
    source: str  # 'caller' (required in SessionLog's attrs), 'caller or writer' (default filled in), 'writer',
    # 'session' (hil.session writes it; optional for other SessionLog users), 'recover'
    doc: str


# The links group's columns per link, in order: name -> meaning. Cumulative counts of the bench's
# decoder for that link since the session connected (hil.protocol.LinkCounters.totals(), same names;
# docs/protocol.md, "Receiving").
LINK_COUNTER_DOCS: dict[str, str] = {
    "frames_ok": "frames delivered (good CRC, right addressing)",
    "crc_errors": "frame candidates rejected for a bad CRC",
    "bad_frames": "frame candidates rejected at the header: wrong version, unknown id or wrong length",
    "bytes_discarded": "bytes skipped while hunting for a frame",
    "frames_lost": "frames never seen: the sum of the forward gaps in the board's sequence numbers",
    "duplicates": "frames received twice (same sequence number again: a resend); delivered, not an error",
    "reordered": "frames that arrived after a later one (sequence number stepped back)",
    "restarts": "times the board's sequence number restarted at 0 (board reset); no frame counted lost",
    "rejected": "good frames refused by addressing: wrong source or destination node, or a message "
    "this link does not carry",
}
LINK_COUNTERS = tuple(LINK_COUNTER_DOCS)


def _links_channels() -> tuple[Channel, ...]:
    out = [Channel("t_host_ns", "i8", "ns", "host monotonic time when the counters were read")]
    for link in LINKS:
        out += [Channel(f"{link}_{name}", "u4", "1", f"{link} link: {doc}") for name, doc in LINK_COUNTER_DOCS.items()]
    return tuple(out)


_LOG_DTYPE = {"u8": "u1", "bool": "u1", "u32": "u4", "i32": "i4"}  # a catalogue field's unscaled integer kinds


def _message_channels(message: type) -> tuple[Channel, ...]:
    """One channel per field of a catalogue message, named and documented as the catalogue has it: a scaled field
    as ``f4`` in its engineering unit, an integer one in its own width (docs/protocol.md)."""
    out = []
    for f in CATALOGUE.by_type[message].fields:
        w = f.wire
        out.append(Channel(f.name, "f4" if w.scale != 1 else _LOG_DTYPE[w.kind], w.unit or "1", w.doc))
    return tuple(out)


SCHEMA: tuple[Group, ...] = (
    Group(
        "loop",
        "1 kHz",
        "One row per GYRO_SAMPLE the bench answered: what the rate loop saw, computed and wrote.",
        (
            Channel("tick", "u4", "1", "board sample counter (GYRO_SAMPLE.tick)"),
            Channel("t_s", "f8", "s", "board time of the sample, unwrapped (GYRO_SAMPLE.t_us / 1e6 plus wraps)"),
            Channel("t_host_ns", "i8", "ns", "host monotonic time (time.monotonic_ns) when the sample was decoded"),
            Channel("gyro_x_dps", "f4", "deg/s", "raw gyro rate about x (elevation frame: line of sight)"),
            Channel("gyro_y_dps", "f4", "deg/s", "raw gyro rate about y (elevation frame: elevation axis)"),
            Channel("gyro_z_dps", "f4", "deg/s", "raw gyro rate about z (elevation frame: cross-elevation)"),
            Channel("az_deg", "f8", "deg", "azimuth encoder angle"),
            Channel("el_deg", "f8", "deg", "elevation encoder angle"),
            Channel("rate_cmd_az_dps", "f4", "deg/s", "azimuth rate command"),
            Channel("rate_cmd_el_dps", "f4", "deg/s", "elevation rate command"),
            Channel(
                "rate_fb_az_dps",
                "f4",
                "deg/s",
                "azimuth rate feedback the loop used (filtered / KF estimate; raw gyro for a plain ESO)",
            ),
            Channel(
                "rate_fb_el_dps",
                "f4",
                "deg/s",
                "elevation rate feedback the loop used (filtered / KF estimate; raw gyro for a plain ESO)",
            ),
            Channel("rate_err_az_dps", "f4", "deg/s", "azimuth rate error: command minus raw gyro"),
            Channel("rate_err_el_dps", "f4", "deg/s", "elevation rate error: command minus raw gyro"),
            Channel("dist_az_counts", "f4", "counts", "azimuth ESO lumped-disturbance estimate"),
            Channel("dist_el_counts", "f4", "counts", "elevation ESO lumped-disturbance estimate"),
            Channel("ff_az_counts", "f4", "counts", "azimuth feed-forward (e.g. UKF imbalance compensation)"),
            Channel("ff_el_counts", "f4", "counts", "elevation feed-forward (e.g. UKF imbalance compensation)"),
            Channel("drive_az_counts", "i4", "counts", "azimuth drive command written (DRIVE_CMD)"),
            Channel("drive_el_counts", "i4", "counts", "elevation drive command written (DRIVE_CMD)"),
            Channel("latency_us", "f4", "us", "bench side: sample decoded -> DRIVE_CMD written"),
            Channel(
                "tick_gap",
                "u4",
                "1",
                "samples missed before this one (0 normally); older logs store it as u1, 255 meaning 255 or more",
            ),
        ),
    ),
    Group(
        "timing",
        "1 kHz",
        "The servo board's LOOP_TIMING reports (10 ticks per report), one row per tick.",
        (
            Channel("tick", "u4", "1", "board sample counter the latency belongs to"),
            Channel(
                "board_latency_us",
                "f4",
                "us",
                "GYRO_SAMPLE k written -> DRIVE_CMD k received, measured by the board; NaN when no command arrived",
            ),
        ),
    ),
    Group(
        "image",
        "camera rate (100 Hz)",
        "Miss distances from the image-processing board (MISS_DISTANCE), one row per frame.",
        (
            Channel("frame", "u4", "1", "camera frame counter"),
            Channel("t_exposure_s", "f8", "s", "mid-exposure time on the board clock"),
            Channel("t_host_ns", "i8", "ns", "host monotonic time when the report was decoded"),
            Channel("miss_x_px", "f4", "px", "miss distance, image x (target minus boresight)"),
            Channel("miss_y_px", "f4", "px", "miss distance, image y (target minus boresight)"),
            Channel("track_valid", "u1", "1", "1 if the tracker had a valid target in this frame, else 0"),
            Channel("loop_tick", "u4", "1", "the last loop tick when the report arrived"),
        ),
    ),
    Group(
        "hexapod",
        "100 Hz",
        "The hexapod's POSE reports: the motion it actually applied to the platform base.",
        (
            Channel("t_profile_s", "f8", "s", "time along the loaded motion profile"),
            Channel("t_host_ns", "i8", "ns", "host monotonic time when the report was decoded"),
            Channel("x_mm", "f4", "mm", "translation x"),
            Channel("y_mm", "f4", "mm", "translation y"),
            Channel("z_mm", "f4", "mm", "translation z"),
            Channel("roll_deg", "f4", "deg", "rotation about x"),
            Channel("pitch_deg", "f4", "deg", "rotation about y"),
            Channel("yaw_deg", "f4", "deg", "rotation about z"),
        ),
    ),
    Group(
        "drive",
        "100 Hz",
        "The motor driver's DRIVE_STATUS reports: its power stage's state and the currents it measured.",
        (
            Channel("t_host_ns", "i8", "ns", "host monotonic time when the report was decoded"),
            Channel("loop_tick", "u4", "1", "the last loop tick when the report arrived"),
            *_message_channels(DriveStatus),
        ),
    ),
    Group(
        "links",
        "10 Hz",
        "Cumulative counters of the bench's frame decoders, one column set per serial link.",
        _links_channels(),
    ),
    Group(
        "events",
        "irregular",
        "State changes, faults, host stalls, recoveries and notes, one row per event.",
        (
            Channel("t_host_ns", "i8", "ns", "host monotonic time of the event"),
            Channel("tick", "u4", "1", "the last loop tick when the event was logged"),
            Channel(
                "kind",
                f"S{KIND_LEN}",
                "1",
                "event kind, ASCII: 'state', 'fault', 'recovered', 'host_stall', 'signal', 'info', 'summary', ...",
            ),
            Channel(
                "detail",
                f"S{DETAIL_LEN}",
                "1",
                f"details as JSON text (ASCII, non-ASCII escaped); cut to {DETAIL_LEN} bytes ending in '...' if longer",
            ),
        ),
    ),
)

ATTRS: tuple[AttrSpec, ...] = (
    AttrSpec("config", "JSON text", "caller", "the whole session configuration, as the session loaded it"),
    AttrSpec("ident", "JSON text", "caller",
             "every board's IDENT reply, by board name (the hexapod's with its `driver`)"),
    AttrSpec("seed", "int", "caller", "the session's random seed"),
    AttrSpec("software_version", "str", "caller or writer", "bench software version (default: hil.__version__)"),
    AttrSpec("start_time_utc", "str", "caller or writer", "session start, ISO 8601 UTC (default: when the log opened)"),
    AttrSpec("session_name", "str", "session", "the session's `name` (the log's file name starts with it)"),
    AttrSpec("controller", "str", "session", "the controller's registry name; its full parameters are in `provenance`"),
    AttrSpec(
        "clock",
        "str",
        "session",
        "what ran the boards' clock: `hardware` (the lab), or the emulator's `realtime`, `lockstep` or `sim`",
    ),
    AttrSpec("loopback", "JSON text", "session", "`true` when the boards were the emulator (a loopback run)"),
    AttrSpec(
        "provenance",
        "JSON text",
        "session",
        "software and library versions, git commit, plant file and its SHA-256, every controller parameter "
        "(see [Provenance](#provenance))",
    ),
    AttrSpec("log_created_unix_ns", "int", "writer", "wall-clock time (time.time_ns) when the log was created"),
    AttrSpec(
        "log_created_monotonic_ns",
        "int",
        "writer",
        "time.monotonic_ns() at the same instant: every t_host_ns minus this, plus log_created_unix_ns, is wall time",
    ),
    AttrSpec("log_format_version", "int", "writer", f"layout version of this file (currently {LOG_FORMAT_VERSION})"),
    AttrSpec("schema", "JSON text", "writer", "the schema the file was written with: groups, channels, dtypes, units"),
    AttrSpec("json_attrs", "JSON text", "writer", "names of the attributes that hold JSON text (decoded by read_log)"),
    AttrSpec("writer_host", "str", "writer", "host name of the machine that wrote the log"),
    AttrSpec("writer_pid", "int", "writer", "pid of the writer process (recover refuses a file whose writer runs)"),
    AttrSpec("recovered", "JSON text", "recover", "only in a recovered file: when, from which file, rows trimmed"),
)

REQUIRED_ATTRS = tuple(a.name for a in ATTRS if a.source == "caller")


IRREGULAR_RATE_HZ = 10.0  # what an "irregular" group (events) is budgeted at: a session logs far fewer
LOG_SIZE_MARGIN = 1.5  # HDF5's chunk and metadata overhead measured ~1.0-1.2x the rows' bytes
LOG_SIZE_FIXED_BYTES = 4 << 20  # attributes (config, provenance), the superblock, the first chunks


def nominal_rate_hz(group: Group) -> float:
    """A group's rows per second, as its ``rate`` says ("1 kHz", "camera rate (100 Hz)"); irregular groups are
    budgeted at IRREGULAR_RATE_HZ."""
    mo = re.search(r"([\d.]+)\s*(k?)Hz", group.rate)
    return float(mo.group(1)) * (1000.0 if mo.group(2) else 1.0) if mo else IRREGULAR_RATE_HZ


def estimated_log_bytes(duration_s: float, schema: tuple[Group, ...] = SCHEMA) -> int:
    """An upper estimate of a log's size for ``duration_s`` of logging: every group at its nominal rate, with
    margin for HDF5's overhead (a 10 s demo session wrote 1.5 MB; this gives 6 MB for its 10 s plus wind-down)."""
    per_s = sum(nominal_rate_hz(g) * numpy_dtype(g).itemsize for g in schema)
    return int(duration_s * per_s * LOG_SIZE_MARGIN) + LOG_SIZE_FIXED_BYTES


def group_by_name(schema: tuple[Group, ...] = SCHEMA) -> dict[str, Group]:
    return {g.name: g for g in schema}


def numpy_dtype(group: Group) -> np.dtype:
    """The structured dtype of one row of ``group``."""
    return np.dtype([(c.name, c.dtype) for c in group.channels])


def schema_to_json(schema: tuple[Group, ...] = SCHEMA) -> str:
    return json.dumps(
        [{"name": g.name, "rate": g.rate, "doc": g.doc, "channels": [c._asdict() for c in g.channels]} for g in schema],
        separators=(",", ":"),
    )


def schema_from_json(text: str) -> tuple[Group, ...]:
    data: list[dict[str, Any]] = json.loads(text)
    return tuple(Group(g["name"], g["rate"], g["doc"], tuple(Channel(**c) for c in g["channels"])) for g in data)


def validate(schema: tuple[Group, ...]) -> None:
    """Raise ValueError if ``schema`` cannot be written (unknown dtype, duplicate or bad names)."""
    seen: set[str] = set()
    for g in schema:
        if not g.name.isidentifier() or g.name in seen:
            raise ValueError(f"bad or duplicate group name {g.name!r}")
        seen.add(g.name)
        if not g.channels:
            raise ValueError(f"group {g.name!r} has no channels")
        names = [c.name for c in g.channels]
        if len(set(names)) != len(names) or not all(n.isidentifier() for n in names):
            raise ValueError(f"group {g.name!r}: bad or duplicate channel names")
        for c in g.channels:
            dt = np.dtype(c.dtype)
            if dt.kind not in "iufS" or dt.itemsize == 0:
                raise ValueError(f"{g.name}/{c.name}: dtype {c.dtype!r} is not a number or fixed-length string")
