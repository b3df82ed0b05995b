"""One run of the bench: the session, its 1 kHz control loop and the clocks it runs on (docs/architecture.md).

- :class:`Session` (``_session``): connect to the four boards, configure, arm, run the loop for the session's
  duration, wind down safely, log every channel; :class:`ControlLoop` is the per-sample step it runs.
- The realtime clock's loop thread (``_loop_thread``: :class:`LoopThread`, :class:`DriveWriter`) with its
  :class:`Watchdog` (``_watchdog``) and the loop's CPU placement (``_host``).
- :func:`run` / :func:`run_async` (``_run``): one session as ``hil run`` runs it, the emulated lab started if asked,
  returning a :class:`RunResult`; campaigns, tuning and fitting run their sessions through it.
- The emulated lab: :class:`EmulatorProcess` (``_loopback``, the emulator in its own process on ptys, realtime or
  lockstep) and the ``sim`` clock in this process (``_sim``: :func:`run_sim_session`, :class:`PlantTruth`).
- The labs a session runs on (``_lab``: :class:`Lab`, one backend each, named in :data:`LABS`: the hardware, the
  emulator process, the in-process ``sim`` lab; :class:`BenchLab`, the ports `hil serve`'s worker holds), passed
  to :func:`run` as ``lab=`` or chosen by :func:`lab_for` from ``loopback`` and ``clock``.
- Is the hardware ready (``_doctor``: :func:`check_hardware`, ``hil doctor``): the ports' checks, the boards', the
  wire's delay and the host's realtime scheduling.

Import from here; the underscored modules are this package's own.
"""

from hil.session._control_loop import LATE_NS, ControlLoop, LoopStats, TrackJudge
from hil.session._doctor import check_hardware
from hil.session._host import SERVICE_RT_PRIORITY, fifo_refusal
from hil.session._lab import LABS, BenchLab, EmulatorLab, HardwareLab, InProcessLab, Lab, LabRun, lab_for
from hil.session._loop_thread import DriveWriter, LoopThread, link_fd
from hil.session._loopback import DEFAULT_EMULATOR, EmulatorProcess, emulator_for_plant
from hil.session._provenance import collect_provenance
from hil.session._run import (
    CLOCKS,
    Clock,
    Progress,
    RunResult,
    as_session_config,
    prepare_run,
    read_log,
    require_log_room,
    run,
    run_async,
    run_coroutine,
)
from hil.session._session import (
    EXIT_LOST_TARGET,
    EXIT_STOPPED,
    HOST_ALIVE_S,
    LINKS,
    Session,
    SessionResult,
    capture_for_session,
)
from hil.session._sim import PlantTruth, SimLab, SimLink, TruthLog, run_sim_session, sim_ports
from hil.session._watchdog import EventLoopWatchdog, Watchdog
from hil.session._wind_down import TickWindDown

__all__ = [
    "CLOCKS",
    "DEFAULT_EMULATOR",
    "EXIT_LOST_TARGET",
    "EXIT_STOPPED",
    "HOST_ALIVE_S",
    "LABS",
    "LATE_NS",
    "LINKS",
    "SERVICE_RT_PRIORITY",
    "BenchLab",
    "Clock",
    "ControlLoop",
    "DriveWriter",
    "EmulatorLab",
    "EmulatorProcess",
    "EventLoopWatchdog",
    "HardwareLab",
    "InProcessLab",
    "Lab",
    "LabRun",
    "LoopStats",
    "LoopThread",
    "PlantTruth",
    "Progress",
    "RunResult",
    "Session",
    "SessionResult",
    "SimLab",
    "SimLink",
    "TickWindDown",
    "TrackJudge",
    "TruthLog",
    "Watchdog",
    "as_session_config",
    "capture_for_session",
    "check_hardware",
    "collect_provenance",
    "emulator_for_plant",
    "fifo_refusal",
    "lab_for",
    "link_fd",
    "prepare_run",
    "read_log",
    "require_log_room",
    "run",
    "run_async",
    "run_coroutine",
    "run_sim_session",
    "sim_ports",
]
