"""Hexapod drivers for the tests, registered in ``hil.hexapod_drivers`` by :func:`register` (a dist-info directory
on ``sys.path``, as an installed package has): a recording software table, and entries that must be refused."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar

from pydantic import Field, SecretStr

from hil.boards import HexapodDriver, HexapodOptions
from hil.protocol.swing import Segment

ENTRY_POINTS = {
    "recording": "tests.boards.drivers:RecordingHexapod",
    "not_a_driver": "tests.boards.drivers:NotADriver",
    "incomplete": "tests.boards.drivers:IncompleteHexapod",
    "missing": "tests.boards.no_such_module:Driver",
}


def register(site: Path) -> Path:
    """Write the dist-info of a package declaring :data:`ENTRY_POINTS` into ``site`` (put it on sys.path)."""
    info = site / "hil_hexapod_test_drivers-0.1.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: hil-hexapod-test-drivers\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[hil.hexapod_drivers]\n" + "".join(f"{k} = {v}\n" for k, v in ENTRY_POINTS.items()))
    return site


class RecordingOptions(HexapodOptions):
    pitch_deg: float = Field(0.5, ge=-10, le=10, description="the pose it reports at start")
    label: str = "rec-1"
    token: SecretStr | None = Field(None, description="a controller password: in no dump of the session config")


class RecordingHexapod(HexapodDriver):
    """A software table that records every call it gets; ``hooks`` (class-wide) run inside a call, by name."""

    Options = RecordingOptions
    instances: ClassVar[list[RecordingHexapod]] = []
    hooks: ClassVar[dict[str, Callable[[RecordingHexapod], Any]]] = {}

    def __init__(self, options: RecordingOptions) -> None:
        self.options = options
        self.calls: list[str] = []
        self.moving = False
        self.segments: tuple[Segment, ...] = ()
        RecordingHexapod.instances.append(self)

    async def _hook(self, name: str) -> None:
        self.calls.append(name)
        hook = self.hooks.get(name)
        if hook is not None:
            result = hook(self)
            if asyncio.iscoroutine(result):
                await result

    async def identify(self) -> dict[str, Any]:
        await self._hook("identify")
        return {"label": self.options.label}

    async def load(self, segments: Sequence[Segment]) -> None:
        await self._hook("load")
        self.segments = tuple(segments)

    async def start(self) -> None:
        await self._hook("start")
        self.moving = True
        if self.on_pose is not None:
            self.on_pose(0.0, (0.0, 0.0, 0.0, 0.0, self.options.pitch_deg, 0.0))

    async def stop(self) -> None:
        await self._hook("stop")
        self.moving = False

    @property
    def running(self) -> bool:
        return self.moving

    async def close(self) -> None:
        await self._hook("close")

    def ident_dict(self) -> dict[str, Any]:
        return {"label": self.options.label}


class NotADriver:
    """An entry point that names something else."""


class IncompleteHexapod(HexapodDriver):
    """A driver that forgot ``start``, ``stop`` and ``running``."""

    async def identify(self) -> None:
        return None

    async def load(self, segments: Sequence[Segment]) -> None:
        return None
