"""Session logs: HDF5 (SWMR, crash-safe), one group per rate, one 1-D dataset per channel.

Layout and semantics: docs/log-format.md. Write with ``SessionLog``; read with ``read_log`` (numpy)
or ``read_log_frames`` (pandas DataFrames, for notebooks); repair a file left by a crash with
``recover_log`` (``hil recover LOG``); export with ``export_log`` (``hil export LOG``, Parquet or
CSV). ``read_provenance`` reads back what a session recorded of its software, plant and controller
(``hil.session.collect_provenance``).
"""

from hil.log.frames import LogFrames, read_log_frames
from hil.log.provenance import read_provenance
from hil.log.reader import (
    LogData,
    RecoverReport,
    export_log,
    free_path,
    read_attrs,
    read_log,
    recover_log,
    units_path,
)
from hil.log.schema import ATTRS, LOG_FORMAT_VERSION, SCHEMA, AttrSpec, Channel, Group
from hil.log.session_log import SessionLog, prestart_writer
from hil.log.writer import LogError

__all__ = [
    "ATTRS",
    "LOG_FORMAT_VERSION",
    "SCHEMA",
    "AttrSpec",
    "Channel",
    "Group",
    "LogData",
    "LogError",
    "LogFrames",
    "RecoverReport",
    "SessionLog",
    "export_log",
    "free_path",
    "prestart_writer",
    "read_attrs",
    "read_log",
    "read_log_frames",
    "read_provenance",
    "recover_log",
    "units_path",
]
