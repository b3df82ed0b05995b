"""A pseudo-terminal that stands in for one board's serial port."""

from __future__ import annotations

import contextlib
import os
import tty


class PtyPort:
    """The board holds the master side; the bench opens ``path`` (the slave) like a serial port.

    The slave is put in raw mode at once and kept open here, so bytes pass unaltered (no echo,
    no CR/LF translation) and the pty survives the bench closing and reopening it.
    """

    def __init__(self) -> None:
        self.master_fd, self._slave_fd = os.openpty()
        tty.setraw(self._slave_fd)
        self.path = os.ttyname(self._slave_fd)

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.master_fd, view) :]

    def read(self, max_bytes: int = 65536) -> bytes:
        """Read what is there (call when select says readable); b'' when nothing is."""
        try:
            return os.read(self.master_fd, max_bytes)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        for fd in (self.master_fd, self._slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
