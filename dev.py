#!/usr/bin/env python3
"""One entry point that sets itself up: `python3 dev.py demo` and `python3 dev.py test`.

Creates `.venv` beside this file on first use (and again whenever pyproject.toml changes),
installs the project into it, then runs the command. Needs only python3 >= 3.11; no root.

    python3 dev.py demo            the loopback demo (README's main command)
    python3 dev.py test [ARGS]     mosquitto, chromium, ruff, lint-imports, mypy, then the whole suite (ARGS: pytest's)
    python3 dev.py test --fast     the same checks and the fast lane: every test not marked slow or browser (minutes)
    python3 dev.py bench           the benchmarks in benchmarks/ (results: docs/performance.md)
    python3 dev.py hil ARGS        any `hil` command inside the environment
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / "python"
STAMP = VENV / ".hil-installed"


def say(msg: str) -> None:
    print(f"[dev.py] {msg}", flush=True)


def run(cmd: list[str | Path], **kw) -> int:
    return subprocess.call([str(c) for c in cmd], cwd=ROOT, **kw)


def ensure_env() -> None:
    if sys.version_info < (3, 11):  # noqa: UP036  (this file must run on an old python3 to say so)
        sys.exit(f"[dev.py] Python >= 3.11 is needed; this is {sys.version.split()[0]}. Use python3.11 or newer.")
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if PY.exists() and STAMP.exists() and STAMP.read_text().strip() == want:
        return
    if not PY.exists():
        say(f"creating virtual environment in {VENV}")
        if run([sys.executable, "-m", "venv", VENV]) != 0:
            sys.exit("[dev.py] `python3 -m venv` failed. On Debian/Ubuntu: apt-get install python3-venv")
    say("installing the project and its test tools into .venv (first run only, about a minute)")
    pip = [PY, "-m", "pip", "install", "--quiet", "--disable-pip-version-check"]
    log = VENV / "pip-install.log"  # the build backend's chatter goes here; it is shown only if pip fails
    with log.open("w") as out:
        ok = run([*pip, "--upgrade", "pip"], stdout=out, stderr=subprocess.STDOUT) == 0 and run(
            [*pip, "-e", ".[test]"], stdout=out, stderr=subprocess.STDOUT) == 0
    if not ok:
        print(log.read_text()[-8000:], file=sys.stderr)
        sys.exit(f"[dev.py] pip install failed (above; the whole output is in {log}); fix it and run the same "
                 "command again")
    warm_plant()
    STAMP.write_text(want + "\n")


def warm_plant() -> None:
    """Compile the emulated plant's kernel once (numba caches the machine code in firmware_stub/__pycache__), so
    the first demo or test does not pause for it."""
    say("compiling the emulated plant's kernel (numba; ~10 s once, then cached)")
    code = ("from firmware_stub.plant import DEFAULT_PLANT_CONFIG, CarrierMotion, Plant, load_plant_config\n"
            "p = Plant(load_plant_config(DEFAULT_PLANT_CONFIG), 0)\n"
            "p.step_tick(0, 0, CarrierMotion.at_rest()); p.truth(); p.miss_px()\n"
            "import numpy as np; p.run(np.zeros(2), np.zeros(2), np.zeros((2, 18)))\n")
    if run([PY, "-c", code]) != 0:
        say("the plant kernel did not compile (above); the emulator will try again when it starts")


def ensure_debian_package(package: str, present: list[str], needed_by: str, otherwise: str) -> None:
    """Best effort: install Debian's ``package`` when none of ``present`` exists and we are root with apt-get;
    otherwise (or if that fails) say what the tests do instead (``otherwise``)."""
    if any(shutil.which(p) or Path(p).exists() for p in present):
        return
    if not hasattr(os, "geteuid") or os.geteuid() != 0 or not shutil.which("apt-get"):
        say(f"{package} not found and not root: {otherwise}")
        return
    say(f"installing {package} for {needed_by} (best effort)")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": env}
    try:
        ok = subprocess.call(["apt-get", "update", "-qq"], timeout=300, **quiet) == 0 and subprocess.call(
            ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *package.split()], timeout=600,
            **quiet) == 0
    except subprocess.TimeoutExpired:
        ok = False
    if not ok:
        say(f"{package} install failed: {otherwise}")


def ensure_test_services() -> None:
    """The telemetry tests want a real MQTT broker (else they start amqtt, pure Python and slower); the live
    page's tests want Debian's headless Chromium and its driver (else they are skipped, and say so)."""
    ensure_debian_package("mosquitto", ["mosquitto", "/usr/sbin/mosquitto"], "the telemetry tests",
                          "the telemetry tests will use amqtt")
    ensure_debian_package("chromium chromium-driver", ["chromedriver", "/usr/bin/chromedriver"],
                          "the live page's browser tests", "the browser tests will be skipped")


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(__doc__)
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd not in ("demo", "test", "bench", "hil"):
        print(__doc__)
        print(f"[dev.py] unknown command {cmd!r}")
        return 2
    ensure_env()
    if cmd == "demo":
        return run([BIN / "hil", "demo", *rest])
    if cmd == "hil":
        return run([BIN / "hil", *rest])
    if cmd == "bench":
        rc = 0
        for script in sorted((ROOT / "benchmarks").glob("bench_*.py")):
            say(f"running {script.relative_to(ROOT)}")
            rc |= run([PY, script, *rest])
        return rc
    fast = "--fast" in rest
    rest = [a for a in rest if a != "--fast"]
    ensure_test_services()
    say("ruff check")
    if run([PY, "-m", "ruff", "check", "."]) != 0:
        say("ruff found problems (above); `.venv/bin/ruff check --fix .` fixes most")
        return 1
    say("lint-imports (the layers in pyproject.toml, docs/architecture.md)")
    if run([BIN / "lint-imports", "--no-cache"]) != 0:  # a cache left by files edited mid-run can be stale
        say("an import breaks the bench's layers (above): move the code to the layer it belongs to")
        return 1
    say("mypy (the types of hil and firmware_stub)")
    if run([PY, "-m", "mypy"]) != 0:
        say("the type checker found problems (above)")
        return 1
    # the tests run on parallel workers (pytest-xdist), a test file to a worker: its fixtures are made once
    parallel = ["-n", str(test_workers()), "--dist", "loadfile"]
    if fast:
        say("the fast lane: tests not marked slow or browser (the whole suite: python3 dev.py test)")
        return run([PY, "-m", "pytest", *parallel, "-m", "not slow and not browser", *rest])
    return run([PY, "-m", "pytest", *parallel, *rest])


def test_workers() -> int:
    """How many test workers: ``HIL_TEST_WORKERS`` if set, else one per CPU this process may use, 2 to 4 (on two
    cores a third worker gained 9 % and crowded the realtime tests into failing; docs/architecture.md)."""
    if env := os.environ.get("HIL_TEST_WORKERS"):
        return max(1, int(env))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 2)
    return max(2, min(4, cpus))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
