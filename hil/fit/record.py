"""The logs ``hil fit`` needs: the recording set as sessions derived from the lab's own (:func:`recording_plan`, which
``hil fit`` prints and runs for a session, docs/fit.md "What to record"), and the same set recorded on an emulated
plant (sim clock) for the hidden-plant acceptance tests and ``benchmarks/fit_hidden_plants.py``.

The set: a static session (ESO+KF holding the gimbal, no swing), an ``hil ident`` sweep on each axis, and swing
sessions at 1 deg and 3 deg / 1 Hz with the plain ESO and at 3 deg with the high-gain ESO+KF (the hardest the
shipped controllers drive the axes: where a current limit shows, if anything does). Every session is a shipped
profile with the emulator pointed at the given plant file; nothing is re-implemented here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from hil.analysis import IDENT_SWEEP, SweptSine
from hil.campaign import load_campaign, run_campaign
from hil.config import PROFILES, ControllerConfig, SessionConfig, load_session, session_yaml
from hil.fit.logs import load_fit_log
from hil.fit.twin import UnusableSweep, linear_frf
from hil.ident import ident_sweeps
from hil.protocol import LINKS
from hil.session import emulator_for_plant, run

SWING_SESSION = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"


def session_on_plant(plant: str | Path, work_dir: str | Path, *, name: str, swing: str | None,
                     controller: str = "eso", seconds: float = 20.0, seed: int = 1,
                     tracking: bool = False, baudrate: int | None = None) -> SessionConfig:
    """The shipped swing session with another swing (``None``: static), controller, duration and the given plant;
    ``baudrate``: every link's line rate (default the lab's, hil.protocol.LINE_RATE_BAUD; 921 600 is the slow-wire
    lab's, docs/emulator.md "The default lab's line rate")."""
    base = load_session(SWING_SESSION)
    data = base.model_dump(mode="json", exclude_none=True)
    data.update(
        name=name, duration_s=seconds, seed=seed,
        controller=str(PROFILES / "controllers" / f"{controller}.yaml"),
        profile=str(PROFILES / "swing" / f"{swing or 'static'}.yaml"),
        tracking={**data.get("tracking", {}), "enabled": tracking},
        emulator={**data["emulator"], "config": str(emulator_for_plant(plant, work_dir, seed=seed)), "clock": "sim"},
        logging={**data.get("logging", {}), "dir": str(Path(work_dir) / "runs")},
        mqtt=base.mqtt, hexapod=base.hexapod,
    )
    if baudrate is not None:  # a loopback session's links run at its ports' rates (the paths are not opened)
        data["ports"] = {link: {"port": f"/dev/emulated-{link}", "baudrate": baudrate} for link in LINKS}
    return SessionConfig.model_validate(data)


@dataclass(frozen=True)
class Recording:
    """One log of the recording set ``hil fit`` needs (docs/fit.md, "What to record"): the session that records it
    (``config``), how long it runs, and what the fit takes from it."""

    name: str
    kind: str  # static | ident | swing
    seconds: float
    why: str
    config: SessionConfig
    sweep: SweptSine | None = None

    def write(self, directory: Path) -> Path:
        """This recording's session YAML in ``directory`` (its parts inline, the sweep left to ``hil ident``)."""
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / f"{self.name}.yaml"
        path.write_text(session_yaml(self.config.model_copy(update={"excitation": None})), encoding="utf-8")
        return path


def recording_plan(base: SessionConfig, *, static_s: float = 30.0, swing_s: float = 20.0,
                   sweep_s: float = IDENT_SWEEP.duration_s, f_start_hz: float = IDENT_SWEEP.f_start_hz,
                   f_stop_hz: float = IDENT_SWEEP.f_stop_hz, amplitude_dps: float = IDENT_SWEEP.amplitude_dps,
                   offset_dps: float = IDENT_SWEEP.offset_dps,
                   swings: tuple[tuple[str, str], ...] = (("swing-1deg-1hz", "eso"), ("swing-3deg-1hz", "eso"),
                                                          ("swing-3deg-1hz", "eso_kf_high_gain")),
                   axes: tuple[str, ...] = ("el", "az")) -> list[Recording]:
    """The logs a fit needs, as sessions derived from ``base`` (the lab's own session: its ports, limits and lab):
    a static session, an ident sweep per axis, swing sessions. The sweep is where ``hil ident`` starts by default
    (docs/ident.md, ``hil.analysis.IDENT_SWEEP``): around a rate offset (no friction reversal), kept short
    (``offset_dps * (sweep_s + 1 s)`` = 27 deg) because a cable harness restrains the travel; `hil ident` levels it
    from there, and so does the fit's recording (:func:`record`)."""

    def session(name: str, swing: str | None, controller: str, seconds: float, tracking: bool) -> SessionConfig:
        data = base.model_dump(mode="json", exclude_none=True)
        data.update(name=name, duration_s=seconds, controller=str(PROFILES / "controllers" / f"{controller}.yaml"),
                    profile=str(PROFILES / "swing" / f"{swing or 'static'}.yaml"),
                    tracking={**data.get("tracking", {}), "enabled": tracking}, mqtt=base.mqtt, hexapod=base.hexapod)
        data.pop("excitation", None)
        return SessionConfig.model_validate(data)

    plan = [Recording("fit-static", "static", static_s, "the gyro's white and coloured noise and its bias (30 s: "
                      "a 1-sigma of 1-2 % on x for the 5 % target, up to ~5 % on y and z, where the loop's "
                      "drive leaves fewer bins; 10 s gives 1.7 times as much)",
                      session("fit-static", None, "eso_kf", static_s, False))]
    for axis in axes:
        sweep = SweptSine(f_start_hz=f_start_hz, f_stop_hz=f_stop_hz, duration_s=sweep_s, amplitude_dps=amplitude_dps,
                          axis=axis, offset_dps=offset_dps)
        cfg = session(f"fit-ident-{axis}", None, "eso", sweep.total_s + 0.5, False)
        plan.append(Recording(f"fit-ident-{axis}", "ident", cfg.duration_s,
                              f"k_m of {axis}, the gyro's bandwidth and delay (the whole loop delay, the wire's "
                              f"included), the {axis} structural mode: a sweep to {f_stop_hz:g} Hz, levelled (up "
                              "to 6 sweeps, the amplitude raised where the coherence fails; again with pi_lpf if "
                              "the ESO loop clips through the band where k_m shows)",
                              cfg.model_copy(update={"excitation": sweep}), sweep))
    for swing, controller in swings:
        name = f"fit-{swing}-{controller.replace('_', '-')}"
        plan.append(Recording(name, "swing", swing_s, "friction, the cable's spring, the imbalance and the current "
                              f"limit from the torque balance ({controller} drives the axes through the swing); the "
                              "breakaway, where the balance cannot see it, from the rate error with the swing "
                              "re-run on the twin",
                              session(name, swing, controller, swing_s, True)))
    return plan


def record(plan: list[Recording], *, loopback: bool, out_dir: str | Path | None = None,
           progress: Callable[[str], Any] | None = None, level: bool = True) -> list[Path]:
    """Run a recording plan: on the emulated lab (``loopback``: the sim clock) or on the lab's boards; an ident
    recording as `hil ident` runs it by default, levelled (``level``; False: its sweep once, as planned; docs/fit.md
    "Hidden plants, recorded with the defaults"). The logs' paths, in the plan's order; RuntimeError naming the
    recording when one does not complete.

    An ident sweep whose loop was not linear where k_m shows (the drive at its limit through the band, or the axis
    turning back: ``hil.fit.twin.linear_frf``) is recorded again with PI + LPF (``FALLBACK_CONTROLLER``), whose
    gain does not depend on a b0 guessed for the axis; the log that passes is kept."""
    logs: list[Path] = []
    clock: Literal["sim"] | None = "sim" if loopback else None
    for i, rec in enumerate(plan, 1):
        if progress is not None:
            each = " a sweep, up to 6 sweeps when levelled" if rec.sweep is not None and level else ""
            progress(f"{i}/{len(plan)} {rec.name} ({rec.seconds:g} s{each})")
        if rec.sweep is not None:
            result = ident_sweeps(rec.config, rec.sweep, level=level, loopback=loopback, clock=clock,
                                  out=out_dir).run
            if (result.status == "completed" and not _passes_linearly(result.log_path)
                    and rec.config.controller.name != FALLBACK_CONTROLLER):
                if progress is not None:
                    progress(f"{i}/{len(plan)} {rec.name}: the loop was not linear where k_m shows; again with "
                             f"{FALLBACK_CONTROLLER}")
                config = rec.config.model_copy(update={"controller": ControllerConfig(name=FALLBACK_CONTROLLER)})
                result = ident_sweeps(config, rec.sweep, level=level, loopback=loopback, clock=clock,
                                      out=out_dir).run
        else:
            result = run(rec.config, loopback=loopback, clock=clock, out=out_dir)
        if result.status != "completed" or result.log_path is None:
            raise RuntimeError(f"{rec.name}: {result.status}: {result.message}")
        logs.append(result.log_path)
    return logs


FALLBACK_CONTROLLER = "pi_lpf"  # an ident sweep the plan's ESO could not pass linearly is recorded again with it


def _passes_linearly(log: Path | None) -> bool:
    """Whether an ident log gives k_m: its loop linear somewhere below ``hil.fit.twin.LINEAR_LOW_HZ``."""
    if log is None:
        return True
    try:
        linear_frf(load_fit_log(log))
    except UnusableSweep:
        return False
    return True


def record_platform_logs(plant: str | Path, out_dir: str | Path, *, seed: int = 1, progress: Callable[[str], Any]
                         | None = None, level: bool = True, baudrate: int | None = None, **plan: Any) -> list[Path]:
    """Record a fit's logs on ``plant`` (sim clock, ``seed``; ``baudrate`` as :func:`session_on_plant`'s):
    :func:`recording_plan` on the shipped swing session with the emulator pointed at ``plant``, the sweeps as planned
    (levelled with ``level``). Their paths."""
    base = session_on_plant(plant, out_dir, name="fit", swing=None, seed=seed, baudrate=baudrate)
    return record(recording_plan(base, **plan), loopback=True, progress=progress, level=level)


ACCEPTANCE_CAMPAIGN = PROFILES / "campaigns" / "swing-miss-distance.yaml"


def campaign_on_plant(plant: str | Path, out_dir: str | Path, *, seeds: tuple[int, ...] = (1,),
                      duration_s: float = 10.0, jobs: int = 1) -> dict[tuple[str, str, str], float]:
    """The fit's acceptance campaign (ESO, ESO+KF, high-gain ESO+KF at 1 and 3 deg / 1 Hz, tracking on: the shipped
    swing-miss-distance campaign) on ``plant``: (profile, controller, metric) -> the mean over ``seeds``."""
    out = Path(out_dir)
    base = load_campaign(ACCEPTANCE_CAMPAIGN)
    overrides = {**base.overrides, "emulator": {"config": str(emulator_for_plant(plant, out))}}
    cfg = base.model_copy(update={"overrides": overrides, "seeds": list(seeds), "duration_s": duration_s,
                                  "name": f"fit-check-{Path(plant).stem}"})
    result = run_campaign(cfg, out / "campaign", jobs=jobs)
    means: dict[tuple[str, str, str], float] = {}
    for p in cfg.profiles:
        for c in cfg.controllers:
            for m in cfg.metrics:
                means[(p.label, c.label, m)] = result.mean(p.label, c.label, m)
    return means
