"""A bench owns the serial ports it opens (docs/reliability.md, "Ports").

Linux lets any number of processes open one tty, and they then split its bytes: a second bench on the same ports
would take the first one's samples and send its boards commands. So every port the bench opens is claimed first:

* an advisory lock file per port (``flock`` on ``LOCK_DIR/<port>.lock``) that names its holder: pid, command line,
  session, since when. A second bench reads the name and is refused before it opens the port. The kernel releases a
  ``flock`` when its process dies, so a lock left by a dead process (SIGKILL, power cut of a container) is simply
  taken over; the previous holder's record says whose it was.
* once the port is open, the kernel's exclusive-use flag on the tty (``TIOCEXCL``): a further ``open`` by any
  program, not only a bench, fails with EBUSY (except for root, which the kernel lets through: the lock file is what
  stops a second bench run as root). The flag is cleared again before the port closes (``TIOCNXCL``).

A port is claimed under its path as given (the emulator's stable symlink, ``/dev/serial/by-id/...``) and under the
device it resolves to, so two names of one device are one port. Claims are all-or-nothing (:func:`claim_ports`) and
are checked before any port is opened, so a refused bench has sent no byte.

``HIL_LOCK_DIR`` overrides the lock directory (default ``/run/lock/hil`` where it can be made, else a ``hil-locks``
folder in the system's temporary directory); every bench on a host must use the same one.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shlex
import socket
import stat
import sys
import tempfile
import termios
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import quote

LOCK_DIR_ENV = "HIL_LOCK_DIR"
TIOCGEXCL = 0x80045440  # Linux: read the tty's exclusive-use flag (not in the termios module)


class PortUnavailable(RuntimeError):
    """A port cannot be used: missing, not a serial port, not permitted, or held by another bench or program.
    Bad input: one line naming the link, the port and the reason (exit 2), raised before any byte is sent.
    ``holder``: the bench that holds it, when that is why (its lock file's record), else None."""

    def __init__(self, message: str, holder: Holder | None = None) -> None:
        super().__init__(message)
        self.holder = holder


@dataclass(frozen=True)
class Holder:
    """Who holds a port: written into the lock file, read back by whoever is refused."""

    pid: int
    command: str
    session: str
    since_utc: str
    host: str

    @classmethod
    def this_process(cls, session: str) -> Holder:
        argv = [Path(sys.argv[0]).name, *sys.argv[1:]] if sys.argv and sys.argv[0] else ["python"]
        command = shlex.join(argv)
        return cls(pid=os.getpid(), command=command[:300], session=session[:200],
                   since_utc=datetime.now(UTC).isoformat(timespec="seconds"), host=socket.gethostname())

    def describe(self) -> str:
        return f"pid {self.pid} ({self.command!r}, session {self.session!r}, since {self.since_utc})"

    @classmethod
    def parse(cls, text: str) -> Holder | None:
        try:
            data = json.loads(text)
            return cls(**{k: data[k] for k in ("pid", "command", "session", "since_utc", "host")})
        except (ValueError, TypeError, KeyError):
            return None


def lock_dir() -> Path:
    """The directory of the port lock files (created world-writable and sticky, as /run/lock itself is)."""
    env = os.environ.get(LOCK_DIR_ENV)
    candidates = [Path(env)] if env else [Path("/run/lock/hil"), Path(tempfile.gettempdir()) / "hil-locks"]
    for path in candidates:
        with contextlib.suppress(OSError):
            path.mkdir(mode=0o1777, parents=True, exist_ok=True)
            with contextlib.suppress(OSError):  # only its creator may (and needs to) set the mode
                if path.stat().st_uid == os.geteuid():
                    path.chmod(0o1777)
            if os.access(path, os.W_OK | os.X_OK):
                return path
    raise PortUnavailable(f"no writable directory for the port locks ({', '.join(map(str, candidates))}); set "
                          f"{LOCK_DIR_ENV}")


def check_serial_port(name: str, port: str, *, open_it: bool = True) -> None:
    """``port`` exists, is a terminal device and may be opened: PortUnavailable naming ``name`` and ``port``
    otherwise. Opens it without a byte written (O_NONBLOCK, O_NOCTTY) and closes it again; ``open_it=False`` checks
    only what ``stat`` tells."""
    try:
        mode = os.stat(port).st_mode
    except FileNotFoundError:
        raise PortUnavailable(f"{name}: {port}: no such port (is the board connected and powered? the lab's ports "
                              "are listed in /dev/serial/by-id/)") from None
    except OSError as exc:
        raise PortUnavailable(f"{name}: {port}: cannot be used: {exc.strerror or exc}") from None
    if not stat.S_ISCHR(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "a regular file" if stat.S_ISREG(mode) else "not a device"
        raise PortUnavailable(f"{name}: {port}: {kind}, not a serial port")
    if not open_it:
        return
    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise PortUnavailable(f"{name}: {port}: {open_refusal(exc)}") from None
    try:
        if not os.isatty(fd):
            raise PortUnavailable(f"{name}: {port}: not a serial port (not a terminal device)")
    finally:
        os.close(fd)


def open_refusal(exc: OSError) -> str:
    """Why opening a port failed, with what to do about it."""
    if exc.errno == errno.EBUSY:
        return ("in exclusive use by another program (the tty's TIOCEXCL flag); close it, or if none runs, "
                "replug the adapter or restart the emulator")
    if exc.errno in (errno.EACCES, errno.EPERM):
        return "permission denied (add the user to the dialout group, then log in again)"
    return f"cannot open: {exc.strerror or exc}"


def set_exclusive(fd: int, on: bool) -> None:
    """Set (or clear) the kernel's exclusive-use flag of the tty open on ``fd``."""
    fcntl.ioctl(fd, termios.TIOCEXCL if on else termios.TIOCNXCL)


def is_exclusive(fd: int) -> bool:
    """Whether the tty open on ``fd`` is in exclusive use (TIOCEXCL set)."""
    buf = bytearray(4)
    fcntl.ioctl(fd, TIOCGEXCL, buf)
    return int.from_bytes(buf, sys.byteorder) != 0


def _lock_keys(port: str) -> list[str]:
    """The names a port is locked under: its path as given (absolute) and the device it resolves to."""
    given = os.path.abspath(port)
    real = os.path.realpath(port)
    return [given] if real == given else [given, real]


class PortClaim:
    """One port held by this process: its lock files, each flocked and naming the holder. :meth:`release` lets go.
    ``took_over``: the record of a previous holder that died without letting go, else None."""

    def __init__(self, name: str, port: str, holder: Holder) -> None:
        self.name = name
        self.port = port
        self.holder = holder
        self.took_over: Holder | None = None
        self._fds: list[int] = []
        directory = lock_dir()
        try:
            for key in _lock_keys(port):
                self._lock(directory / f"{quote(key, safe='')}.lock")
        except BaseException:
            self.release()
            raise

    def _lock(self, path: Path) -> None:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            raise PortUnavailable(f"{self.name}: {self.port}: cannot create its lock {path}: "
                                  f"{exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            other = Holder.parse(_read_all(fd))
            os.close(fd)
            who = other.describe() if other is not None else "another process"
            raise PortUnavailable(f"{self.name}: {self.port} is in use by {who}; end that bench first, or use "
                                  "other ports", other) from None
        with contextlib.suppress(OSError):
            os.fchmod(fd, 0o666)  # another user's bench must be able to take it over later
        previous = Holder.parse(_read_all(fd))
        if previous is not None and previous.pid != self.holder.pid:
            self.took_over = previous
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(asdict(self.holder)).encode(), 0)
        self._fds.append(fd)

    def release(self) -> None:
        """Let go: the lock files are emptied (a reader sees no holder) and unlocked; the files stay, so a bench
        waiting to lock one never holds a file that another has already replaced."""
        fds, self._fds = self._fds, []
        for fd in fds:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
            os.close(fd)


def _read_all(fd: int) -> str:
    try:
        return os.pread(fd, 4096, 0).decode("utf-8", "replace")
    except OSError:
        return ""


class PortClaims:
    """Every port of one bench, claimed together: each checked (it exists and is a serial port), then each locked;
    all or none. Use as a context manager, or call :meth:`release`."""

    def __init__(self, ports: Mapping[str, str], holder: Holder) -> None:
        seen: dict[str, str] = {}
        for name, port in ports.items():  # what stat tells first: a missing port is named as missing
            check_serial_port(name, port, open_it=False)
            for key in _lock_keys(port):
                if key in seen:
                    raise PortUnavailable(f"{name}: {port} is also the {seen[key]} link's port")
                seen[key] = name
        self.claims: list[PortClaim] = []
        try:
            for name, port in ports.items():  # then the holder: a port in use is named with whoever has it
                self.claims.append(PortClaim(name, port, holder))
            for name, port in ports.items():  # then the device itself: opened, a tty, not in exclusive use
                check_serial_port(name, port)
        except BaseException:
            self.release()
            raise

    def release(self) -> None:
        claims, self.claims = self.claims, []
        for claim in claims:
            claim.release()

    @property
    def taken_over(self) -> dict[str, Holder]:
        """Ports whose previous holder had died without letting go: link name -> that holder."""
        return {c.name: c.took_over for c in self.claims if c.took_over is not None}

    def __enter__(self) -> PortClaims:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def claim_ports(ports: Mapping[str, str], session: str) -> PortClaims:
    """Claim ``ports`` (link name -> device path) for this process's ``session``; PortUnavailable naming the first
    port that is missing, not a serial port, or held (with its holder), before any of them is opened."""
    return PortClaims(ports, Holder.this_process(session))
