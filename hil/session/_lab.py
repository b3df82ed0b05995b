"""The lab a long-running process owns: `hil serve`'s worker claims the boards' ports once and holds them while it
serves (docs/service.md, "Ports owned, once"); every session run in that process runs on them.

A :class:`BenchLab` is the lab's ports (real, or the emulated lab the worker started), the claims on them and whether
they are emulated. :func:`serve_lab` makes it this process's lab: :func:`hil.session.run_async` (and so
``hil.run``, ident and the fit's recordings) then runs every session on it, whatever the session file's ``ports:``
or ``loopback`` say, without claiming or releasing the ports itself. Only the worker sets it; a process that never
calls :func:`serve_lab` runs sessions as before.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hil.config import PortConfig
from hil.link import PortClaims


@dataclass
class BenchLab:
    """Ports held for longer than a session: link name -> port, the claims that hold them, and whether they are
    the emulated lab's (its sessions are logged ``loopback`` on the realtime clock, with the emulator's grace)."""

    ports: dict[str, PortConfig]
    claims: PortClaims
    emulated: bool
    description: str = ""
    extra: dict[str, Any] = field(default_factory=dict)  # log attributes of its sessions (a "provenance" adds)
    on_session: Callable[[Any], None] | None = None  # called with each Session once it exists, on its event loop

    @property
    def clock(self) -> str:
        return "realtime" if self.emulated else "hardware"


_LAB: list[BenchLab] = []  # this process's lab, if it serves one (at most one)


def serve_lab(lab: BenchLab | None) -> None:
    """Make ``lab`` the lab every session of this process runs on (None: none, sessions claim their own ports)."""
    _LAB[:] = [lab] if lab is not None else []


def current_lab() -> BenchLab | None:
    """The lab this process serves (:func:`serve_lab`), or None."""
    return _LAB[0] if _LAB else None
