"""Where a session log came from, read back: the ``provenance`` file attribute a session recorded.

The session side records it (``hil.session.collect_provenance``): the software, the plant and the
controller (docs/log-format.md, "Provenance").
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hil.log.reader import read_attrs


def read_provenance(log_path: str | Path) -> dict[str, Any]:
    """The ``provenance`` a session recorded in its log; ``{}`` for a log written before it existed.

    Reads only the file's attributes, so it is quick on a long log, and works on a log still being
    written or left by a crash. Raises ``LogError`` if the file is not a readable session log.
    """

    value = read_attrs(log_path).get("provenance")
    return value if isinstance(value, dict) else {}
