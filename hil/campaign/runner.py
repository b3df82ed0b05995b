"""Run a campaign's cells, keep each cell's log, resume, judge thresholds and acceptance.

Each cell is one `hil run` of ``CELL/session.yaml`` in a process of its own (against its own emulated lab unless
``hardware``, on the ``sim`` clock by default or ``lockstep`` over ptys, so cells are reproducible and may run
``jobs`` at a time; on the lab's hardware one after another). A sim-clock cell runs in a warm worker
(:mod:`hil.campaign.warm`): the same session code, in a process that outlives the cell. An engine
(:mod:`hil.campaign.engines`) runs them: ``local`` here, ``dask`` on a dask.distributed cluster, where a worker runs
the same :func:`run_cell` and sends the cell's files back (or leaves them in a shared directory) for this process to
put where the local engine would. A cell's ``result.json`` is written when it finishes, and the campaign's
``campaign.json`` after every cell, so an interrupted campaign resumes where it stopped, with either engine.

A KeyboardInterrupt (Ctrl-C; SIGTERM where the caller maps it to :class:`hil.campaign.engines.Interrupted`) stops
the campaign: the signal is passed on to the cells running here (each session ends the safe way: driver
disabled, log closed), no other cell starts, and :func:`run_campaign` raises :class:`CampaignInterrupted` naming
the cells done and those cut short, once the cut-short cells have ended.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Collection, Generator, Iterator
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import ValidationError

from hil.campaign.engines import Engine, EngineError, Interrupted, check_options, open_engine
from hil.campaign.metrics import METRICS, compute_metrics, score
from hil.campaign.model import CampaignConfig, CampaignResult, CellResult, CellSpec, RuleResult
from hil.campaign.warm import WARM, CellHandle, WorkerDied
from hil.config import ConfigError, SessionConfig, load_model, load_session, one_line, read_file_bytes

RESULT = "result.json"
CAMPAIGN_JSON = "campaign.json"
MAX_RESULTS_BYTES = 64 << 20  # campaign.json and result.json are read only up to this size
P = TypeVar("P")
STOP_GRACE_S = 60.0  # a stopped cell's session has this long to wind down before it is killed


class CampaignError(ValueError):
    """Bad campaign input or output directory (one line)."""


class CampaignInterrupted(KeyboardInterrupt):
    """A campaign stopped by SIGINT or SIGTERM (``signum``), its finished cells on disk in ``out_dir``: ``done``
    the cells ``resume`` keeps, ``cut_short`` those running when the signal came, ``to_run`` what ``resume``
    runs; ``total`` cells in all. ``exit_code``: 130 for SIGINT, 143 for SIGTERM."""

    def __init__(self, config: CampaignConfig, out_dir: Path, signum: int, done: list[str],
                 cut_short: list[str]) -> None:
        self.signal = signal.Signals(signum).name
        super().__init__(f"{config.name}: interrupted by {self.signal}")
        self.config, self.out_dir, self.signum = config, out_dir, int(signum)
        self.done, self.cut_short = done, cut_short
        self.to_run = [s.cell_id for s in config.cells() if s.cell_id not in set(done)]
        self.total = len(done) + len(self.to_run)
        self.exit_code = 128 + self.signum


class _LiveCells:
    """The cells running in this process, by campaign directory, with their `hil run` processes: a campaign that
    stops passes its signal on to them, and starts none once it is stopping."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._cells: dict[tuple[Path, str], Any] = {}  # a cell's process (send_signal), None before it starts
        self._stopping: set[Path] = set()

    @contextlib.contextmanager
    def cell(self, out_dir: Path, cell_id: str) -> Iterator[bool]:
        """Hold the cell as running while in the block; False (not held) if its campaign is stopping."""
        key = (out_dir.absolute(), cell_id)
        with self._cond:
            held = key[0] not in self._stopping
            if held:
                self._cells[key] = None
        try:
            yield held
        finally:
            if held:
                with self._cond:
                    self._cells.pop(key, None)
                    self._cond.notify_all()

    def start(self, out_dir: Path, cell_id: str, start: Callable[[], P]) -> P | None:
        """Start a held cell's process (``start()``: a `hil run` process or a warm worker lent to the cell, anything
        with ``send_signal``); None if its campaign is stopping."""
        key = (out_dir.absolute(), cell_id)
        with self._cond:
            if key[0] in self._stopping:
                return None
            proc = start()
            self._cells[key] = proc
            return proc

    def running(self, out_dir: Path) -> list[str]:
        where = out_dir.absolute()
        with self._cond:
            return [cell_id for (d, cell_id) in self._cells if d == where]

    def reset(self, out_dir: Path) -> None:
        """A new run of the campaign in ``out_dir``: its cells may start."""
        with self._cond:
            self._stopping.discard(out_dir.absolute())

    def stop(self, out_dir: Path, signum: int) -> None:
        """No cell of the campaign starts any more; ``signum`` to those running (SIGKILL: killed)."""
        where = out_dir.absolute()
        with self._cond:
            self._stopping.add(where)
            procs = [p for (d, _), p in self._cells.items() if d == where and p is not None]
        for proc in procs:
            with contextlib.suppress(OSError):  # it has just ended
                proc.send_signal(signum)

    def wait(self, out_dir: Path, timeout_s: float) -> bool:
        """True once no cell of the campaign runs here; False after ``timeout_s``."""
        where = out_dir.absolute()
        with self._cond:
            return self._cond.wait_for(lambda: all(d != where for d, _ in self._cells), timeout=timeout_s)


_LIVE = _LiveCells()


def load_campaign(path: str | Path) -> CampaignConfig:
    try:
        return load_model(CampaignConfig, path)
    except ConfigError as exc:
        raise CampaignError(str(exc)) from None


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in extra.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _base_session(config: CampaignConfig) -> SessionConfig:
    try:
        return load_session(config.session)
    except ConfigError as exc:
        raise CampaignError(f"session: {exc}") from None


def cell_session(config: CampaignConfig, spec: CellSpec, cell_dir: Path, hardware: bool = False, *,
                 base: SessionConfig | None = None, clock: str = "sim") -> dict[str, Any]:
    """The session file of one cell: the base session with the campaign's overrides and the cell's
    profile, controller and seed (paths absolute, so the file stands on its own), validated.

    A password written in the session file is refused (the cell's file would hold it in clear text:
    give it as ``mqtt.password_env`` or ``mqtt.password_file``).

    ``clock`` (loopback cells): ``sim`` (default: boards and plant in the cell's process) or ``lockstep`` (the
    full protocol over ptys); both give the same logs."""
    base = base if base is not None else _base_session(config)
    data = _merge(base.model_dump(mode="json", exclude_none=True), config.overrides)
    for key in ("logging", "emulator", "host"):  # sections the cell sets fields of
        if not isinstance(data.get(key, {}), dict):
            raise CampaignError(f"overrides: {key}: not a mapping ({type(data[key]).__name__})")
    data.update(name=spec.cell_id, seed=spec.seed, controller={"name": spec.controller.name,
                                                               "params": spec.controller.params},
                profile=str(spec.profile.path), logging={**data.get("logging", {}), "dir": str(cell_dir)})
    if config.duration_s is not None:
        data["duration_s"] = config.duration_s
    if not hardware:  # lockstep cells run side by side (``jobs``): CPU placement is for one realtime loop
        data["emulator"] = {**data.get("emulator", {}), "clock": clock, "cpu": None}
        data["host"] = {**data.get("host", {}), "loop_cpu": None}
    try:
        session = SessionConfig.model_validate(data)
    except ValidationError as exc:
        raise CampaignError(one_line(f"cell {spec.cell_id}", exc)) from None
    secrets = session.hexapod.secret_options()
    if secrets:
        raise CampaignError(f"cell {spec.cell_id}: hexapod.{secrets[0]}: each cell's session file would hold it in "
                            "clear text; give the driver its secret through the environment or a file it reads")
    if session.mqtt is not None and session.mqtt.password is not None:
        raise CampaignError(f"cell {spec.cell_id}: mqtt.password: each cell's session file would hold it in clear "
                            "text; give it as mqtt.password_env or mqtt.password_file")
    return data


def _check(config: CampaignConfig, spec: CellSpec, result: CellResult) -> CellResult:
    failures = list(result.failures)
    for metric, threshold in config.thresholds.items():
        if (why := threshold.check(metric, result.metrics.get(metric, float("nan")))) is not None:
            failures.append(why)
    return result.model_copy(update={"failures": failures})


def _not_run(config: CampaignConfig, spec: CellSpec, status: str, why: str, wall_s: float = 0.0) -> CellResult:
    result = CellResult(cell_id=spec.cell_id, profile=spec.profile.label, controller=spec.controller.label,
                        controller_name=spec.controller.name, seed=spec.seed, status=status, exit_code=-1,
                        message=why, failures=[why], wall_s=wall_s)
    return _check(config, spec, result)


def run_cell(config: CampaignConfig, spec: CellSpec, out_dir: Path, *, hardware: bool = False,
             timeout_s: float | None = None, session: dict[str, Any] | None = None, warm: bool = True) -> CellResult:
    """Run one cell in a process of its own: a `hil run` process, or (``warm``, a cell on the sim clock) a warm
    worker (:mod:`hil.campaign.warm`) that runs the same session code without starting an interpreter; its log,
    session file and result.json go to ``out_dir/cells/ID``. ``session``: the cell's session from
    :func:`cell_session` (built here if not given). A cell of a campaign that is stopping
    (:class:`CampaignInterrupted`) does not start: it comes back ``interrupted``."""
    with _LIVE.cell(out_dir, spec.cell_id) as held:
        if not held:
            return _not_run(config, spec, "interrupted", "the campaign was stopped before the cell started")
        return _run_cell(config, spec, out_dir, hardware=hardware, timeout_s=timeout_s, session=session, warm=warm)


def _run_cell(config: CampaignConfig, spec: CellSpec, out_dir: Path, *, hardware: bool,
              timeout_s: float | None, session: dict[str, Any] | None, warm: bool) -> CellResult:
    cell_dir = out_dir / "cells" / spec.cell_id
    data = session if session is not None else cell_session(config, spec, cell_dir, hardware)
    if cell_dir.exists():
        shutil.rmtree(cell_dir)  # a cell that did not finish starts again from nothing
    cell_dir.mkdir(parents=True)
    session_file = cell_dir / "session.yaml"
    session_file.write_text(yaml.safe_dump(data, sort_keys=False))
    duration = float(data["duration_s"])
    timeout = timeout_s or 120.0 + 30.0 * duration
    t0 = time.monotonic()
    base = {"cell_id": spec.cell_id, "profile": spec.profile.label, "controller": spec.controller.label,
            "controller_name": spec.controller.name, "seed": spec.seed}
    try:
        if warm and not hardware and data.get("emulator", {}).get("clock") == "sim":
            summary = _warm_run(out_dir, spec.cell_id, session_file, cell_dir, timeout, config=config)
        else:
            cmd = [sys.executable, "-m", "hil", "run", str(session_file), "--json", "--out", str(cell_dir)]
            summary = _hil_run(out_dir, spec.cell_id, [*cmd, *([] if hardware else ["--loopback"])], cell_dir,
                               timeout)
    except subprocess.TimeoutExpired:
        result = CellResult(**base, status="error", exit_code=-1, message="timed out",
                            failures=["the session did not finish in time"], wall_s=time.monotonic() - t0)
    else:
        if summary is None:
            result = _not_run(config, spec, "interrupted", "the campaign was stopped before the cell started")
            (cell_dir / RESULT).write_text(result.model_dump_json(indent=2))
            return result
        log = Path(summary["log"]) if summary.get("log") else None
        metrics: dict[str, float] = {}
        failures: list[str] = []
        if summary.get("status") != "completed":
            failures.append(f"session {summary.get('status')}: {summary.get('message', '')}".rstrip(": "))
        if "metrics" in summary or "metrics_error" in summary:  # worked out where the cell ran
            metrics = dict(summary.get("metrics") or {})
            if summary.get("metrics_error"):
                failures.append(summary["metrics_error"])
        elif log is not None and log.exists():
            try:
                computed = compute_metrics(log, config.analysis, config.settle_s)
                metrics = {k: v for k, v in computed.items() if math.isfinite(v)}
            except (ValueError, KeyError, OSError) as exc:
                failures.append(f"metrics: {exc}")
        result = CellResult(**base, status=summary.get("status", "error"), exit_code=int(summary["exit_code"]),
                            message=str(summary.get("message") or ""),
                            log=str(log.relative_to(out_dir)) if log is not None and log.is_relative_to(out_dir)
                            else (str(log) if log else None),
                            metrics=metrics, failures=failures, wall_s=time.monotonic() - t0,
                            health=summary.get("health"))
    result = _check(config, spec, result)
    (cell_dir / RESULT).write_text(result.model_dump_json(indent=2))
    return result


def _last_line(text: str) -> str:
    return (text.strip().splitlines() or ["no output"])[-1]


def _hil_run(out_dir: Path, cell_id: str, cmd: list[str], cell_dir: Path, timeout_s: float) -> dict[str, Any] | None:
    """``cmd`` (a `hil run` asked for its JSON record) for a held cell, its process known to ``_LIVE`` so a
    campaign's stop reaches it: the JSON it printed (or an error record with its exit status and last line on
    stderr), its stderr in ``cell_dir/stderr.txt``. None: the campaign is stopping, nothing started.
    TimeoutExpired after ``timeout_s``, the process killed."""
    env = {**os.environ, "COLUMNS": "200"}
    proc = _LIVE.start(out_dir, cell_id, lambda: subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                                                 text=True, env=env))
    if proc is None:
        return None
    with proc:
        try:
            stdout, stderr = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise
    (cell_dir / "stderr.txt").write_text(stderr)
    try:
        summary = json.loads(stdout)
    except json.JSONDecodeError:
        return {"status": "error", "exit_code": proc.returncode, "message": _last_line(stderr)}
    return {"exit_code": proc.returncode, **summary}


def _warm_run(out_dir: Path, cell_id: str, session_file: Path, cell_dir: Path, timeout_s: float, *,
              config: CampaignConfig) -> dict[str, Any] | None:
    """The cell's session in a warm worker lent for it (:data:`hil.campaign.warm.WARM`), known to ``_LIVE`` while it
    runs: the JSON record `hil run` would print with the campaign's metrics (worked out in the worker), its
    stderr in ``cell_dir/stderr.txt``. None: the campaign is stopping. TimeoutExpired after ``timeout_s``, the
    worker killed."""
    handle: CellHandle | None = _LIVE.start(out_dir, cell_id, lambda: WARM.lend().begin())
    if handle is None:
        return None
    worker = handle.worker
    stderr = cell_dir / "stderr.txt"
    try:
        return worker.run(session_file, cell_dir, stderr, timeout_s, analysis=config.analysis,
                          settle_s=config.settle_s)
    except WorkerDied as exc:
        last = _last_line(stderr.read_text(errors="replace")) if stderr.exists() else "no output"
        return {"status": "error", "exit_code": exc.returncode if exc.returncode is not None else -1,
                "message": f"{exc}; {last}"}
    finally:
        WARM.give_back(worker)


def judge(config: CampaignConfig, cells: list[CellResult]) -> list[RuleResult]:
    """Every acceptance rule on every profile and seed. A magnitude metric (a lag) is compared by its absolute
    value (hil.campaign.metrics.score): a lead is never "lower" than a lag of the same size."""
    by_key = {(c.profile, c.controller, c.seed): c for c in cells}
    out = []
    for rule in config.acceptance:
        ok, details = True, []
        by_size = METRICS[rule.metric].magnitude or METRICS[rule.reference_metric].magnitude
        for profile in rule.profiles or [p.label for p in config.profiles]:
            for seed in config.seeds:
                better, than = by_key.get((profile, rule.better, seed)), by_key.get((profile, rule.than, seed))
                b = better.metrics.get(rule.metric) if better and better.status == "completed" else None
                a = than.metrics.get(rule.reference_metric) if than and than.status == "completed" else None
                sa = math.nan if a is None else score(rule.reference_metric, a)
                sb = math.nan if b is None else score(rule.metric, b)
                if a is None or b is None or math.isnan(sa) or math.isnan(sb) or sa <= 0:
                    ok = False
                    details.append(f"{profile}, seed {seed}: not available")
                    continue
                gain = 100.0 * (sa - sb) / sa
                holds = gain >= rule.by_pct and sb < sa
                ok &= holds
                ref = rule.than if rule.reference_metric == rule.metric else rule.reference_metric
                what = rule.better if rule.reference_metric == rule.metric else rule.metric
                details.append(f"{profile}, seed {seed}: {ref} {a:.4g} -> {what} {b:.4g} "
                               f"({gain:+.1f} %{' by magnitude' if by_size else ''}){'' if holds else '  FAILS'}")
        out.append(RuleResult(rule=rule.describe(), passed=ok, details=details))
    return out


def _write_json(path: Path, text: str) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def load_results(out_dir: Path) -> CampaignResult:
    path = out_dir / CAMPAIGN_JSON
    if not path.exists():
        raise CampaignError(f"{out_dir}: no {CAMPAIGN_JSON} (not a campaign directory)")
    try:
        return CampaignResult.model_validate_json(read_file_bytes(path, MAX_RESULTS_BYTES))
    except ValueError as exc:  # not a regular file, too large, not UTF-8 (ValidationError is a ValueError too)
        raise CampaignError(one_line(str(path), exc) if isinstance(exc, ValidationError) else str(exc)) from None


def cell_sessions(config: CampaignConfig, out_dir: Path, hardware: bool = False,
                  clock: str = "sim") -> dict[str, dict[str, Any]]:
    """Every cell's session (:func:`cell_session`), by cell id: all of them validated, nothing written."""
    base = _base_session(config)
    return {spec.cell_id: cell_session(config, spec, out_dir / "cells" / spec.cell_id, hardware, base=base,
                                       clock=clock)
            for spec in config.cells()}


@dataclasses.dataclass
class CellOutput:
    """What a cell run elsewhere sends back: its result, and its directory's files either as ``files``
    (relative path, bytes) or as ``path``, the directory on a filesystem this process shares with the worker.
    Neither: the cell never ran to the end (its worker failed)."""

    result: CellResult
    files: list[tuple[str, bytes]] | None = None
    path: str | None = None


def _worker_tmp() -> str | None:
    """The dask worker's own scratch directory (removed with the worker), else the system's temp directory."""
    with contextlib.suppress(ImportError, ValueError, AttributeError):
        from distributed import get_worker  # noqa: PLC0415  (heavy and optional: only the dask engine needs it)

        return str(get_worker().local_directory)
    return None


def run_cell_remote(config: CampaignConfig, hardware: bool, shared: str | None, warm: bool,
                    item: tuple[CellSpec, dict[str, Any]]) -> CellOutput:
    """On a worker: :func:`run_cell` for ``item`` (the cell's spec and session) into a directory of its own,
    then the cell's files as bytes, or (``shared``: a directory the campaign's process sees too) left under
    ``shared`` with their path. Every attempt has its own directory, so a retried cell never meets the files
    of an attempt whose worker died."""
    spec, session = item
    if shared is not None:
        base = Path(shared) / f"{spec.cell_id}-{uuid.uuid4().hex[:12]}"
        result = run_cell(config, spec, base, hardware=hardware, session=session, warm=warm)
        return CellOutput(result=result, path=str(base / "cells" / spec.cell_id))
    base = Path(tempfile.mkdtemp(prefix="hil-cell-", dir=_worker_tmp()))
    try:
        result = run_cell(config, spec, base, hardware=hardware, session=session, warm=warm)
        cell_dir = base / "cells" / spec.cell_id
        files = [(path.relative_to(cell_dir).as_posix(), path.read_bytes())
                 for path in sorted(cell_dir.rglob("*")) if path.is_file() and path.name != RESULT]
        return CellOutput(result=result, files=files)
    finally:
        shutil.rmtree(base, ignore_errors=True)


def _lost_cell(config: CampaignConfig, spec: CellSpec, exc: BaseException) -> CellOutput:
    why = " ".join(f"{type(exc).__name__}: {exc}".split())[:300]
    result = CellResult(cell_id=spec.cell_id, profile=spec.profile.label, controller=spec.controller.label,
                        controller_name=spec.controller.name, seed=spec.seed, status="error", exit_code=-1,
                        message=why, failures=[f"the cell's worker failed: {why}"])
    return CellOutput(result=_check(config, spec, result))


def _store(out: CellOutput, out_dir: Path, spec: CellSpec, session: dict[str, Any]) -> CellResult:
    """Put a cell run elsewhere where the local engine puts it, ``out_dir/cells/ID``; result.json last."""
    cell_dir = out_dir / "cells" / spec.cell_id
    if cell_dir.exists():
        shutil.rmtree(cell_dir)
    cell_dir.mkdir(parents=True)
    if out.files is not None:
        for rel, data in out.files:
            target = cell_dir / rel
            if Path(rel).is_absolute() or ".." in Path(rel).parts or rel == RESULT:
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
    elif out.path is not None:
        source = Path(out.path)
        for path in sorted(source.rglob("*")):
            if path.is_file() and path.name != RESULT:
                target = cell_dir / path.relative_to(source)
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(path, target)
        shutil.rmtree(source.parent.parent, ignore_errors=True)  # the attempt's directory
    else:
        (cell_dir / "session.yaml").write_text(yaml.safe_dump(session, sort_keys=False))
    (cell_dir / RESULT).write_text(out.result.model_dump_json(indent=2))
    return out.result


def _run_here(config: CampaignConfig, out_dir: Path, hardware: bool, warm: bool,
              item: tuple[CellSpec, dict[str, Any]]) -> CellResult:
    spec, session = item
    return run_cell(config, spec, out_dir, hardware=hardware, session=session, warm=warm)


def iter_cells(config: CampaignConfig, out_dir: Path, specs: list[CellSpec], engine: Engine, *,
               sessions: dict[str, dict[str, Any]], hardware: bool = False,
               warm: bool = True) -> Generator[CellResult, None, None]:
    """Run ``specs`` on ``engine`` (an open :class:`hil.campaign.engines.Engine`); yield each cell's result as it
    completes, its directory in place under ``out_dir/cells/ID`` whichever engine ran it. ``sessions``: every
    cell's session by id (:func:`cell_sessions`). A cell whose worker failed (every retry used) comes back as an
    ``error`` result; on the local engine an exception raised by a cell is raised here."""
    items = [(spec, sessions[spec.cell_id]) for spec in specs]
    if not engine.remote:
        for _, result in engine.map_cells(functools.partial(_run_here, config, out_dir, hardware, warm), items,
                                          key=lambda item: item[0].cell_id):
            yield result
        return
    staging = None
    if engine.shared_dir is not None:  # this run's corner of the shared directory; each attempt has its own
        staging = Path(engine.shared_dir) / f".hil-{config.name}-{uuid.uuid4().hex[:8]}"
        staging.mkdir(parents=True)
    fn = functools.partial(run_cell_remote, config, hardware, None if staging is None else str(staging), warm)
    try:
        for (spec, session), out in engine.map_cells(fn, items, key=lambda item: item[0].cell_id,
                                                     on_error=lambda item, exc: _lost_cell(config, item[0], exc)):
            yield _store(out, out_dir, spec, session)
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)


@contextlib.contextmanager
def _engine(engine: str | Engine, jobs: int, scheduler: str | None, workers: int | None,
            shared_dir: str | Path | None) -> Iterator[Engine]:
    """The named engine, started here and closed at the end; an Engine given is used as it is (its owner
    closes it)."""
    if not isinstance(engine, str):
        yield engine.open()
        return
    try:
        started = open_engine(engine, jobs=jobs, scheduler=scheduler, workers=workers, shared_dir=shared_dir).open()
    except EngineError as exc:
        raise CampaignError(str(exc)) from None
    try:
        yield started
    finally:
        started.close()


def kept_cells(config: CampaignConfig, out_dir: Path) -> dict[str, CellResult]:
    """The cells ``resume`` keeps, by id: those whose ``result.json`` says completed, their thresholds judged
    again against ``config``."""
    kept: dict[str, CellResult] = {}
    for spec in config.cells():
        path = out_dir / "cells" / spec.cell_id / RESULT
        if path.exists():
            try:
                cell = CellResult.model_validate_json(read_file_bytes(path, MAX_RESULTS_BYTES))
            except ValueError:  # unreadable or not a result: the cell runs again
                continue
            if cell.status == "completed":
                run_failures = [f for f in cell.failures if f.split(" ", 1)[0] not in METRICS]
                kept[spec.cell_id] = _check(config, spec, cell.model_copy(update={"failures": run_failures}))
    return kept


def interrupted(config: CampaignConfig, out_dir: Path, signum: int, cut_short: Collection[str] = (),
                kept: Collection[str] | None = None) -> CampaignInterrupted:
    """The :class:`CampaignInterrupted` for the campaign in ``out_dir`` as it stands on disk (``kept``: the ids of
    :func:`kept_cells`, if already read). A cell of ``cut_short`` that completed all the same is done."""
    kept = kept_cells(config, out_dir) if kept is None else kept
    ids = [s.cell_id for s in config.cells()]
    return CampaignInterrupted(config, out_dir, signum, done=[i for i in ids if i in kept],
                               cut_short=[i for i in ids if i in cut_short and i not in kept])


def _stop_cells(out_dir: Path, signum: int, grace_s: float = STOP_GRACE_S) -> None:
    """Pass ``signum`` on to the campaign's cells running here (a second signal too) and wait until each has written
    its result; one still running after ``grace_s`` is killed."""
    _LIVE.stop(out_dir, signum)
    deadline = time.monotonic() + grace_s
    killed = False
    while True:
        try:
            if _LIVE.wait(out_dir, max(0.0, deadline - time.monotonic())) or killed:
                return
            _LIVE.stop(out_dir, signal.SIGKILL)
            killed, deadline = True, time.monotonic() + 10.0
        except KeyboardInterrupt as again:
            _LIVE.stop(out_dir, getattr(again, "signum", signal.SIGINT))


def run_campaign(config: CampaignConfig, out_dir: Path, *, jobs: int = 1, resume: bool = False,
                 hardware: bool = False, on_cell: Callable[[CellResult], None] | None = None,
                 sessions: dict[str, dict[str, Any]] | None = None, engine: str | Engine = "local",
                 scheduler: str | None = None, workers: int | None = None,
                 shared_dir: str | Path | None = None, warm: bool = True) -> CampaignResult:
    """Run (or finish) every cell; returns the campaign's result, also written to ``out_dir/campaign.json``.
    Every cell is validated before anything is written (``sessions``: from :func:`cell_sessions`, if the
    caller already built them), so a campaign with a bad cell leaves nothing behind.

    ``engine``: ``local`` (``jobs`` cells at a time in this machine's processes), ``dask`` (on a dask.distributed
    cluster: ``scheduler`` an existing one's address, else a LocalCluster of ``workers`` (default ``jobs``)
    worker processes started here; ``shared_dir`` a directory the workers and this process share, else the cells'
    files come back as bytes), or an open :class:`hil.campaign.engines.Engine`. The engine is started (or the
    scheduler reached) before anything is written.

    ``on_cell``: called with each cell's result as it finishes; an exception it raises stops the campaign (the
    cells still running are stopped as by Ctrl-C, no other starts) and propagates.

    ``warm`` (default): the cells on the sim clock run in warm workers (:mod:`hil.campaign.warm`), the same
    session code without an interpreter's start per cell; False: each cell is a `hil run` process.

    A KeyboardInterrupt (or :class:`hil.campaign.engines.Interrupted` for SIGTERM) stops the cells running here
    with that signal, waits until they have ended, writes ``campaign.json`` and raises :class:`CampaignInterrupted`:
    the finished cells stay, and ``resume`` runs the rest."""
    if jobs < 1:
        raise CampaignError(f"jobs={jobs}: need at least 1")
    if hardware:
        jobs = 1  # one lab
    try:
        check_options(engine, hardware=hardware, scheduler=scheduler, workers=workers, shared_dir=shared_dir)
    except EngineError as exc:
        raise CampaignError(str(exc)) from None
    specs = config.cells()
    if sessions is None:
        sessions = cell_sessions(config, out_dir, hardware)
    done: dict[str, CellResult] = {}
    if (out_dir / CAMPAIGN_JSON).exists() or (out_dir / "cells").exists():
        if not resume:
            raise CampaignError(f"out={str(out_dir)!r}: already holds a campaign; pass resume=True to finish it, "
                                "or choose another directory")
        done = kept_cells(config, out_dir)
    _LIVE.reset(out_dir)
    t0 = time.monotonic()
    results = dict(done)
    slots = jobs

    def snapshot(complete: bool) -> CampaignResult:
        cells = [results[s.cell_id] for s in specs if s.cell_id in results]
        return CampaignResult(config=config, cells=cells, acceptance=judge(config, cells), jobs=slots,
                              wall_s=time.monotonic() - t0, complete=complete)

    running: Generator[CellResult, None, None] | None = None
    try:
        with _engine(engine, jobs, scheduler, workers, shared_dir) as runner:
            slots = runner.slots
            out_dir.mkdir(parents=True, exist_ok=True)
            (out_dir / "campaign.yaml").write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
            t0 = time.monotonic()
            for cell in done.values():
                if on_cell is not None:
                    on_cell(cell)
            todo = [s for s in specs if s.cell_id not in done]
            running = iter_cells(config, out_dir, todo, runner, sessions=sessions, hardware=hardware, warm=warm)
            for cell in running:
                results[cell.cell_id] = cell
                _write_json(out_dir / CAMPAIGN_JSON, snapshot(False).model_dump_json(indent=2))
                if on_cell is not None:
                    try:
                        on_cell(cell)
                    except Exception:  # the caller has seen enough (a pruned trial): stop the cells still running
                        _stop_cells(out_dir, signal.SIGINT)
                        running.close()
                        raise
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        cut_short = {*(exc.running if isinstance(exc, Interrupted) else ()), *_LIVE.running(out_dir)}
        _stop_cells(out_dir, signum)
        if running is not None:
            running.close()  # its cells have ended: nothing to wait for
        kept = kept_cells(config, out_dir)
        if (out_dir / "cells").is_dir():
            results.update(kept)
            _write_json(out_dir / CAMPAIGN_JSON, snapshot(False).model_dump_json(indent=2))
        raise interrupted(config, out_dir, signum, cut_short, kept) from None
    final = snapshot(len(results) == len(specs))
    _write_json(out_dir / CAMPAIGN_JSON, final.model_dump_json(indent=2))
    return final
