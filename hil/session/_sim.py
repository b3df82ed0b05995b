"""The ``sim`` session clock: the bench's own Session and ControlLoop, the emulated boards and the plant in one
process, with no ptys and no child process (docs/emulator.md, "Clocks").

Messages pass as objects after their wire round trip (the encoder's checks, then the decoder:
:meth:`hil.protocol.MessageSpec.roundtrip`); commands with replies go as encoded bytes through the board's own
decoder. The world (:class:`firmware_stub.sim.SimWorld`) advances as the lockstep emulator does, one tick per
GYRO_SAMPLE answered, so for the same seed and config a ``sim`` log's channels equal a ``lockstep`` log's, apart
from the host's own clock (``t_host_ns``, ``latency_us``). Campaigns, fits and tuning use it.

The world ticks in a task of the session's event loop, :data:`TICKS_PER_YIELD` ticks between yields, so the
session's own coroutines (handshake, wind-down, shutdown) run as they do against a real board.

Because the plant lives in this process, the sim clock alone can also hand the session the plant's true state
(:class:`PlantTruth`): what the ``oracle`` controller feeds back (hil.control.oracle, docs/control.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Callable
from pathlib import Path
from time import perf_counter
from typing import TYPE_CHECKING, Any

from firmware_stub.config import ConfigError, LinkName, load_emulator_config
from hil.config import PortConfig, SessionConfig
from hil.control.oracle import AxisTruth
from hil.link import Link, LinkError
from hil.log.truth import write_truth
from hil.protocol import CATALOGUE, LINKS, Frame
from hil.session._session import Session

if TYPE_CHECKING:
    from firmware_stub.plant import Plant
    from hil.session._session import Session, SessionResult

TICKS_PER_YIELD = 20  # world ticks between two yields to the event loop (a sim tick is ~20-40 us)
CAPTURE_REFUSED = ("capture: the sim clock's links pass messages, not bytes, so there is nothing to capture; "
                   "use clock='lockstep' (the same run over ptys)")


class SimLink(Link):
    """A link to a board of an in-process :class:`SimLab`. The hot path (:meth:`send`) passes the message as an
    object through its wire round trip; :meth:`request` (inherited) writes encoded bytes, which the board's own
    decoder reads. Frames from the board arrive through :meth:`deliver`, counted in the decoder's counters as
    frames received."""

    def __init__(self, name: str, lab: SimLab, on_frame: Callable[[Frame], None] | None) -> None:
        super().__init__(name, on_frame)
        self.lab = lab
        self.port = f"sim:{name}"
        self._roundtrip = CATALOGUE.roundtrips()
        self._to_board = lab.to_board(name)
        self._open = True

    @property
    def is_open(self) -> bool:
        return self._open

    def _write(self, data: bytes) -> None:
        self.lab.from_host_bytes(self.name, bytes(data))

    def close(self) -> None:
        if self._open:
            self._open = False
            self._closed_with(None)

    def send(self, message: Any, dst: int) -> int:
        if not self._open:
            raise LinkError(f"{self.name}: link is closed")
        enc = self.encoder
        seq = enc.take_seq()
        self._to_board(Frame(enc.src, dst, seq, self._roundtrip[type(message)](message)))
        return seq

    def deliver(self, frame: Frame) -> None:
        self.decoder.counters.frames_ok += 1
        super().deliver(frame)


class PlantTruth:
    """The plant's true state per axis in the rate loop's units, at the tick the plant has reached: the truth source
    of the ``oracle`` (hil.control.oracle.TruthSource). Called with no argument, it returns
    ``{"az": AxisTruth, "el": AxisTruth}``, computed once per tick.

    ``rate_dps``: the true LOS rate each axis' gyro measures (azimuth: z, elevation: y), before the gyro's filter,
    delay and noise. ``disturbance_counts``: ``d`` of the rate-loop model ``d(rate)/dt = k_m (u + d)``, every effect
    on the axis but the motor's nominal drive torque ``K_t V_count u / R`` (:meth:`Plant.truth` names the torques):

    - the torques acting on the axis: friction (bearing, on the motor side's rate relative to the carrier, so the
      carrier's motion reaches the axis through it), the cable harness, the mass imbalance (the carrier's
      acceleration), and the motor's torque ripple ``a K_t i sin(N theta_m)``; each as the counts that make that
      torque at standstill, ``T R / (K_t V_count)``;
    - the back-EMF of the motor side's rate relative to the carrier, ``-K_e w_rel / V_count`` counts (the voltage
      it takes away from the drive).

    The shaft torque of a compliant axis is internal (between the motor and the load) and is not counted; the
    electrical lag (L/R ~0.1 ms) and the driver's current limit are left to the loop, as for every controller.
    """

    def __init__(self, plant: Plant) -> None:
        self.plant = plant
        cfg = plant.config
        self._axes = []
        for axis in ("az", "el"):
            motor = getattr(cfg, f"motor_{axis}")
            ripple = cfg.ripple_of(axis)
            self._axes.append((
                axis,
                motor.resistance_ohm / (motor.torque_constant_n_m_per_a * motor.volts_per_count),  # counts per N m
                motor.back_emf_v_s_per_rad / motor.volts_per_count,  # counts per rad/s of relative motor rate
                0.0 if ripple is None else ripple.amplitude_fraction * motor.torque_constant_n_m_per_a,
                0.0 if ripple is None else float(ripple.periods_per_rev),
            ))
        self._t_s = -1.0
        self._value: dict[str, AxisTruth] = {}

    def __call__(self) -> dict[str, AxisTruth]:
        t_s = self.plant.t_s
        if t_s != self._t_s:
            self._t_s = t_s
            self._value = self.compute(self.plant.truth())
        return self._value

    def compute(self, truth: dict[str, float]) -> dict[str, AxisTruth]:
        """``{"az", "el"}`` -> AxisTruth from a :meth:`Plant.truth` dict."""
        d2r = math.pi / 180.0
        out = {}
        for axis, counts_per_n_m, counts_per_rad_s, ripple_n_m_per_a, ripple_n in self._axes:
            torque = truth[f"friction_{axis}_n_m"] + truth[f"cable_{axis}_n_m"] + truth[f"imbalance_{axis}_n_m"]
            if ripple_n_m_per_a:
                torque += (ripple_n_m_per_a * truth[f"current_{axis}_a"]
                           * math.sin(ripple_n * truth[f"{axis}_motor_deg"] * d2r))
            carrier_dps = truth[f"{axis}_rate_dps"] - truth[f"{axis}_rel_rate_dps"]  # the carrier's rate on the axis
            motor_rel_rad_s = (truth[f"{axis}_motor_rate_dps"] - carrier_dps) * d2r
            los = truth["los_rate_z_dps"] if axis == "az" else truth["los_rate_y_dps"]
            out[axis] = AxisTruth(los, torque * counts_per_n_m - counts_per_rad_s * motor_rel_rad_s)
        return out


class TruthLog:
    """The sim clock's truth recorder (hil.log.truth): called with each loop row's sample counter, it keeps the
    plant's true LOS rates y and z at that tick; :meth:`write` puts them beside the session log."""

    def __init__(self, plant: Plant) -> None:
        self.plant = plant
        self.ticks: list[int] = []
        self.rates_y_dps: list[float] = []
        self.rates_z_dps: list[float] = []

    def __call__(self, tick: int) -> None:
        _, y, z = self.plant.los_rate_dps()
        self.ticks.append(tick)
        self.rates_y_dps.append(y)
        self.rates_z_dps.append(z)

    def write(self, log_path: Path) -> Path:

        return write_truth(log_path, self.ticks, self.rates_y_dps, self.rates_z_dps)


class SimLab:
    """The emulated lab of ``emulator_config`` in this process. Use as an async context manager around a
    Session built with ``open_link=lab.open_link``; the world ticks while the session runs."""

    def __init__(self, emulator_config: Path, *, seed: int, baudrates: dict[str, int] | None = None) -> None:
        from firmware_stub.plant import PlantConfigError, load_plant_config  # noqa: PLC0415  (the emulated plant's numba kernel: loaded only on the sim clock)
        from firmware_stub.sim import SimWorld  # noqa: PLC0415  (the emulated plant's numba kernel: loaded only on the sim clock)

        config = load_emulator_config(emulator_config, clock="lockstep", seed=seed, baudrates=baudrates)
        try:
            load_plant_config(config.plant)
        except PlantConfigError as exc:

            raise ConfigError(f"{emulator_config}: plant: {exc}") from None
        self.world = SimWorld(config, self._to_host)
        self.truth = PlantTruth(self.world.plant)  # the oracle's truth source (only this clock has one)
        self.truth_log = TruthLog(self.world.plant)  # the truth file beside the log (hil.log.truth)
        self.links: dict[str, SimLink] = {}
        self._wake = asyncio.Event()
        self._delivery_due = False
        self._ticking = False
        self._task: asyncio.Task[None] | None = None
        self.ticks = 0
        self.busy_s = 0.0  # wall time spent ticking (the loop time: world, boards, the bench's loop, the log)
        self.summary: dict[str, Any] = {}
        self.on_error: Callable[[str], None] | None = None  # the session's fault(): the world failed

    # --- links --------------------------------------------------------------------------------------

    async def open_link(self, name: str, port: PortConfig, on_frame: Callable[[Frame], None]) -> Link:
        """The Session's ``open_link``: a SimLink to the board ``name`` (the port is not used)."""
        link = SimLink(name, self, on_frame)
        self.links[name] = link
        return link

    def _to_host(self, link: Any, frame: Frame) -> None:
        host = self.links.get(link)  # a LinkName is a str: it finds the link by its name
        if host is not None and host.is_open:
            host.deliver(frame)

    def to_board(self, name: str) -> Callable[[Frame], None]:
        """What a host link calls with each frame for board ``name``."""

        link = LinkName(name)
        from_host = self.world.from_host

        def send(frame: Frame) -> None:
            from_host(link, frame)
            if not self._ticking:  # inside a tick, the tick delivers what the boards answer
                self._after_host_frame()

        return send

    def from_host_bytes(self, name: str, data: bytes) -> None:

        self.world.from_host_bytes(LinkName(name), data)
        if not self._ticking:
            self._after_host_frame()

    def _after_host_frame(self) -> None:
        """A reply (or a stream now on) must reach the host: deliver soon, from the event loop, never from
        inside the host's own call; and the world may have to start ticking."""
        self._wake.set()
        if self.world.outbox and not self._delivery_due:
            self._delivery_due = True
            asyncio.get_running_loop().call_soon(self._deliver)

    def _deliver(self) -> None:
        self._delivery_due = False
        self.world.deliver()

    # --- the clock ----------------------------------------------------------------------------------

    async def _run(self) -> None:
        try:
            await self._tick_forever()
        except Exception as exc:  # a bug in the world must end the session as a fault, not hang it
            if self.on_error is None:
                raise
            self.on_error(f"sim world failed: {type(exc).__name__}: {exc}")

    async def _tick_forever(self) -> None:
        world = self.world
        while True:
            if world.streaming:
                t0 = perf_counter()
                n = 0
                self._ticking = True
                try:
                    while n < TICKS_PER_YIELD and world.tick():
                        n += 1
                finally:
                    self._ticking = False
                self.ticks += n
                self.busy_s += perf_counter() - t0
                if world.outbox:  # a stream stopped mid-batch leaves its last replies
                    self._after_host_frame()
                await asyncio.sleep(0)
            else:
                self._wake.clear()
                await self._wake.wait()

    async def __aenter__(self) -> SimLab:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="hil-sim-world")
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self.summary = {**self.world.summary(), "sim_ticks": self.ticks, "sim_loop_s": round(self.busy_s, 4)}
        self.world.close()


def sim_ports() -> dict[str, PortConfig]:
    """Placeholder ports for a Session whose links a SimLab opens."""
    return {name: PortConfig(port=f"sim:{name}") for name in LINKS}


async def run_sim_session(config: SessionConfig, out_dir: Path, *, progress: Callable[[int, int], None] | None = None,
                          log_attrs: dict[str, Any] | None = None, capture_dir: Path | None = None,
                          on_session: Callable[[Session], None] | None = None,
                          ) -> tuple[SessionResult, dict[str, Any]]:
    """Run one session against the emulated lab of ``config.emulator`` in this process (the ``sim`` clock).
    Returns the session's result and the emulator's summary. A bad emulator or plant file raises ConfigError.
    ``capture_dir`` is refused (ValueError, before anything starts): the sim clock's links pass messages as
    objects, so there are no bytes to capture; the lockstep clock runs the same session over ptys. ``on_session``
    gets the Session once it exists (hil.api: to interrupt it from another thread). The session gets the lab's
    :class:`PlantTruth`, which only the ``oracle`` controller reads, and its :class:`TruthLog`, written beside the
    log as its truth file (hil.log.truth: the true LOS rates per loop row), even when the session faults."""

    if capture_dir is not None:
        raise ValueError(CAPTURE_REFUSED)

    lab = SimLab(config.emulator.config, seed=config.seed, baudrates=config.link_baudrates())
    session = Session(config, sim_ports(), out_dir, progress=progress, lockstep=True, open_link=lab.open_link,
                      watchdog=False, log_attrs={"loopback": True, "clock": "sim", **(log_attrs or {})},
                      truth=lab.truth, record_truth=lab.truth_log)
    lab.on_error = session.fault
    if on_session is not None:
        on_session(session)
    try:
        async with lab:
            result = await session.run()
    finally:
        if session.log_path is not None and session.log_path.exists():
            lab.truth_log.write(session.log_path)
    return result, lab.summary


