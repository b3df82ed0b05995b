"""`hil doctor`: the ports' checks (hil.link), with a session the boards' (hil.boards) and what the wire adds to
every cycle, and whether this user may run the loop thread SCHED_FIFO (docs/service.md, "Is the hardware ready?")."""

from __future__ import annotations

import math
from pathlib import Path

from hil.boards import check_boards
from hil.config import ConfigError, PortConfig, SessionConfig, load_session
from hil.link import Finding, check_ports, wire_delay
from hil.session._host import SERVICE_RT_PRIORITY, fifo_refusal
from hil.session._run import run_coroutine


def check_hardware(session: SessionConfig | str | Path | None = None, *, sysfs: str | Path = "/sys",
                   boards: bool = True, listen_s: float = 2.0) -> list[Finding]:
    """Is the hardware ready (`hil doctor`, docs/service.md)? Every check of every port: ``session``'s ports, or
    with none every serial adapter in /dev/serial/by-id/ at the default line rate (hil.protocol.LINE_RATE_BAUD).
    ConfigError for a session without ports. With a session, also what the wire adds to every cycle at its rates
    (hil.link.wire_delay: a warning over ``ports.wire_delay_budget_us``).

    With a session and ``boards`` (the default), the boards are asked too (hil.boards.check_boards), on each port
    whose own checks passed: an ``ident`` finding per link the session opens (the board's IDENT and its catalogue
    fingerprint against this bench's), and a ``servo stream`` finding: the stream started, listened to ``listen_s``
    and stopped, its rate and jitter against 1 kHz and the session's ``safety.watchdog_ms``. The motor driver is
    never enabled and the hexapod never moved. ``boards=False`` checks the ports alone, without a byte sent."""
    if not (math.isfinite(listen_s) and listen_s > 0):
        raise ConfigError(f"listen_s={listen_s!r}: not a finite number of seconds above 0")
    refusal = fifo_refusal(SERVICE_RT_PRIORITY)
    host = Finding("host", "realtime scheduling", refusal is None, refusal or (
        f"this user may run the loop thread SCHED_FIFO (priority {SERVICE_RT_PRIORITY}; host.rt_priority, and "
        "`hil serve` does it by itself)"))
    if session is None:
        by_id = sorted(Path("/dev/serial/by-id").glob("*"))
        ports = {p.name: str(p) for p in by_id}
        bauds = dict.fromkeys(ports, PortConfig.model_fields["baudrate"].default)
        return [*check_ports(ports, bauds, sysfs=Path(sysfs)), host]
    config = session if isinstance(session, SessionConfig) else load_session(session)
    if config.ports is None:
        raise ConfigError("ports: not set in the session file; a loopback run needs no hardware check")
    links = {n: getattr(config.ports, n) for n in ("servo", "driver", "image", "hexapod")}
    ports = {n: c.port for n, c in links.items() if c is not None}
    bauds = {n: c.baudrate for n, c in links.items() if c is not None}
    findings = check_ports(ports, bauds, sysfs=Path(sysfs))
    loop = wire_delay(bauds["servo"], bauds["driver"], config.ports.wire_delay_budget_us)
    if not boards:
        return [*findings, loop, host]
    # the links a session opens: the hexapod's only for a driver that talks over it
    opened = [n for n in ports if n != "hexapod" or config.hexapod.driver_class.uses_link]
    free = {n: ports[n] for n in opened
            if all(f.ok for f in findings if f.link == n and f.check in ("port", "holder"))}
    for name in opened:
        if name not in free:
            findings.append(Finding(name, "ident", False, "not asked: this port failed its own checks"))
    if "servo" in opened and "servo" not in free:
        findings.append(Finding("servo", "servo stream", False, "not listened to: the servo port failed its checks"))
    if free:
        findings += run_coroutine(check_boards, free, bauds, listen_s=listen_s,
                                  watchdog_ms=config.safety.watchdog_ms)
    order = list(ports)
    # each link's rows together, then the loop's wire delay, then the host
    return [*sorted(findings, key=lambda f: order.index(f.link)), loop, host]
