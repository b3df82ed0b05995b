"""The log's writer process with a file-size limit (RLIMIT_FSIZE): writes past it fail with EFBIG.

    python tests/log/limited_writer.py LIMIT_BYTES

Stands in for a full disk: the test points ``hil.log.session_log._writer_argv`` here.
"""

from __future__ import annotations

import resource
import signal
import sys

if __name__ == "__main__":
    limit = int(sys.argv[1])
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    from hil.log.writer import _child_main

    _child_main()
