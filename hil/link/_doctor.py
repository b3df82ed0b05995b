"""`hil doctor`: is the hardware ready? The checks a lab needs before its first session on a PC (docs/service.md,
"Is the hardware ready?"): each port exists and is a serial port this user may open, no other process holds it, a
USB-serial adapter answers within a millisecond, and the configured baud rate carries the link's periodic load
(docs/protocol.md, "Link budget"). Each check is a :class:`Finding` that says what to do when it fails.
"""

from __future__ import annotations

import grp
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.link._ports import Holder, PortClaim, PortUnavailable, check_serial_port
from hil.protocol import LINE_RATE_BAUD
from hil.protocol.budget import loop_wire_delay_s, periodic_load_bits_per_s

SYSFS = Path("/sys")
LATENCY_TIMER_MAX_MS = 1  # FTDI adapters default to 16 ms: a 1 kHz loop needs 1
BAUD_HEADROOM = 0.8  # the periodic load may take this share of the line; commands and resends need the rest
UDEV_RULE = ('ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", ATTR{latency_timer}="1" in '
             "/etc/udev/rules.d/99-hil-latency.rules, then replug the adapter")


@dataclass(frozen=True)
class Finding:
    """One check of one link: passed or not, what was found, and what to do about it; ``values``: what was measured,
    for a script (the servo stream's rate and jitter, a board's firmware and fingerprint), empty for most checks."""

    link: str
    check: str
    ok: bool
    detail: str
    values: Mapping[str, Any] = field(default_factory=dict)
    warning: bool = False  # passed, but worth knowing: nothing is refused for it (`hil doctor` shows "warn")


def check_port(name: str, port: str, *, baud: int, sysfs: Path = SYSFS) -> list[Finding]:
    """Every check of one link's port (``name`` the link, ``port`` its device, ``baud`` its configured rate)."""
    findings = [_device(name, port)]
    if findings[0].ok:
        findings.append(_holder(name, port))
        findings.append(latency_timer(name, port, sysfs=sysfs))
    findings.append(baud_budget(name, baud))
    return findings


def check_ports(ports: Mapping[str, str], bauds: Mapping[str, int], *, sysfs: Path = SYSFS) -> list[Finding]:
    return [f for name, port in ports.items() for f in check_port(name, port, baud=bauds[name], sysfs=sysfs)]


def _device(name: str, port: str) -> Finding:
    try:
        check_serial_port(name, port)
    except PortUnavailable as exc:
        message = str(exc)
        if os.path.exists(port) and not os.access(port, os.R_OK | os.W_OK):
            group = _group(port)
            message = (f"{name}: {port}: this user may not open it: it belongs to group {group!r}; add the user "
                       f"(sudo usermod -aG {group} $USER), then log in again")
        return Finding(name, "port", False, message)
    return Finding(name, "port", True, f"{port}: a serial port this user may open")


def _group(port: str) -> str:
    gid = os.stat(port).st_gid
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def _holder(name: str, port: str) -> Finding:
    try:
        PortClaim(name, port, Holder.this_process("hil doctor")).release()
    except PortUnavailable as exc:
        return Finding(name, "holder", False, str(exc))
    return Finding(name, "holder", True, "no other bench holds it")


def latency_timer(name: str, port: str, *, sysfs: Path = SYSFS) -> Finding:
    """A USB-serial adapter's latency timer (``sysfs/bus/usb-serial/devices/TTY/latency_timer``, ms): how long the
    adapter holds a short read before it sends it on. More than 1 ms delays every GYRO_SAMPLE by that much."""
    tty = Path(os.path.realpath(port)).name
    timer = sysfs / "bus" / "usb-serial" / "devices" / tty / "latency_timer"
    try:
        ms = int(timer.read_text().strip())
    except FileNotFoundError:
        return Finding(name, "latency timer", True, f"{tty}: not a USB-serial adapter with a latency timer")
    except (OSError, ValueError) as exc:
        return Finding(name, "latency timer", False, f"{timer}: cannot be read: {exc}")
    if ms > LATENCY_TIMER_MAX_MS:
        return Finding(name, "latency timer", False,
                       f"{tty}: latency timer {ms} ms delays every sample by up to {ms} ms; set 1 ms: "
                       f"echo 1 | sudo tee {timer}, and for good with the udev rule {UDEV_RULE}")
    return Finding(name, "latency timer", True, f"{tty}: latency timer {ms} ms")


def baud_budget(name: str, baud: int) -> Finding:
    """Can ``baud`` carry the link's periodic messages (the busier direction), with room for commands?"""
    loads = {d: bps for d, bps in periodic_load_bits_per_s().items() if name in d.split(" → ")}
    if not loads:
        return Finding(name, "baud rate", True, f"{baud} baud; no periodic messages on this link")
    busiest, need = max(loads.items(), key=lambda kv: kv[1])
    if need > BAUD_HEADROOM * baud:
        return Finding(name, "baud rate", False,
                       f"{baud} baud carries {baud / 1e3:.1f} kbit/s, and the periodic messages {busiest} need "
                       f"{need / 1e3:.1f} kbit/s (at most {BAUD_HEADROOM:.0%} of the line, docs/protocol.md link "
                       f"budget); use at least {_enough(need)} baud on both ends")
    return Finding(name, "baud rate", True,
                   f"{baud} baud; the periodic load {busiest} is {need / baud:.0%} of it")


def wire_delay(servo_baud: int, driver_baud: int, budget_us: float) -> Finding:
    """What the wire adds to every cycle of the 1 kHz loop at these rates (GYRO_SAMPLE in, DRIVE_CMD out), against
    the session's budget (``ports.wire_delay_budget_us``): over it is a warning, not a failure."""
    delay_us = loop_wire_delay_s(servo_baud, driver_baud) * 1e6
    default_us = loop_wire_delay_s(LINE_RATE_BAUD, LINE_RATE_BAUD) * 1e6
    values = {"wire_delay_us": round(delay_us, 1), "budget_us": budget_us}
    if delay_us > budget_us:
        return Finding("loop", "wire delay", True,
                       f"the wire adds {delay_us:.0f} us to every cycle (servo {servo_baud} baud, driver {driver_baud} "
                       f"baud), over the {budget_us:g} us budget (ports.wire_delay_budget_us): the fastest loops "
                       f"lose their phase margin (docs/emulator.md, \"The default lab's line rate\"); "
                       f"{LINE_RATE_BAUD} baud on both ends adds {default_us:.0f} us",
                       values, warning=True)
    return Finding("loop", "wire delay", True, f"the wire adds {delay_us:.0f} us to every cycle, within the "
                   f"{budget_us:g} us budget", values)


def _enough(need_bps: float) -> int:
    for baud in (230_400, 460_800, 921_600, 2_000_000, 3_000_000, 4_000_000):
        if need_bps <= BAUD_HEADROOM * baud:
            return baud
    return 12_000_000
