"""Session logs: HDF5 (SWMR, crash-safe), one group per rate, one 1-D dataset per channel.

Layout and semantics: docs/log-format.md. Write with ``SessionLog``; read with ``read_log``;
repair a file left by a crash with ``recover_log`` (``hil recover LOG``); export with
``export_log`` (``hil export LOG --format parquet|csv``).
"""

from hil.log.reader import LogData, RecoverReport, export_log, read_log, recover_log
from hil.log.schema import ATTRS, LOG_FORMAT_VERSION, SCHEMA, AttrSpec, Channel, Group
from hil.log.writer import LogError, SessionLog

__all__ = [
    "ATTRS",
    "LOG_FORMAT_VERSION",
    "SCHEMA",
    "AttrSpec",
    "Channel",
    "Group",
    "LogData",
    "LogError",
    "RecoverReport",
    "SessionLog",
    "export_log",
    "read_log",
    "recover_log",
]
