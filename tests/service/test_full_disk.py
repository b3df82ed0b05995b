"""The service's state directory on a small file system that fills while an item runs and a lease lapses
(docs/service.md, "When the store cannot write"): requests that need to write answer 507 with one line of JSON, the
running item ends as a fault with its log linked, the lapse is recorded, and once space is back the service goes on
without a restart."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.service import BenchError
from tests.factories import short_session
from tests.service.conftest import Service, wait_for

SIZE_MB = 48


@pytest.fixture
def small_fs(tmp_path: Path) -> Iterator[Path]:
    """A tmpfs of SIZE_MB MiB mounted at a fresh directory (root and mount(8) needed; skipped otherwise)."""
    where = tmp_path / "small-fs"
    where.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a small file system to fill needs root and mount(8)")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={SIZE_MB}m", "tmpfs", str(where)],
                          capture_output=True, text=True, check=False)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def fill(directory: Path) -> Path:
    """Write a file until the file system has no byte left; returns it."""
    filler = directory / "filler"
    with filler.open("wb", buffering=0) as f:
        for size in (1 << 20, 4096, 1):
            try:
                while True:
                    f.write(b"\0" * size)
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
    return filler


@pytest.mark.slow
def test_a_full_state_disk_never_wedges_the_manager(small_fs: Path, tmp_path: Path) -> None:
    svc = Service(small_fs).start()  # the state directory is the small file system (the service's own log is not)
    try:
        bench = svc.bench()
        bench.lease(ttl_s=5.0)
        long = bench.add(short_session(tmp_path, 40.0, name="long"))
        wait_for(lambda: bench.item(long["uid"]).get("cycles", 0) > 1000, timeout_s=180)
        filler = fill(small_fs)
        time.sleep(6.0)  # the lease lapses while the disk is full

        # a request that must write: 507 with one line; one that only reads still answers
        with pytest.raises(BenchError) as full:
            bench.add(short_session(tmp_path, 1.0, name="while-full"))
        assert full.value.status == 507 and "free space" in str(full.value)
        status = bench.status()
        assert status["store"]["ok"] is False and "full" in status["store"]["error"]
        # the item ends (its log cannot be written) and waits to be recorded; nothing else starts
        wait_for(lambda: long["uid"] in bench.status()["store"]["unrecorded"]
                 or bench.item(long["uid"])["state"] == "done", timeout_s=120)

        filler.unlink()  # space is back: the service goes on by itself
        record = wait_for(lambda: (view := bench.item(long["uid"]))["state"] == "done" and view, timeout_s=60)
        assert record["status"] == "fault" and record["exit_code"] == 1
        assert record["log_path"] and Path(record["log_path"]).is_file() and "log" in record["links"]
        events = bench.call("GET", "/api/lease")["events"]
        assert events[0]["event"] == "lapsed"
        wait_for(lambda: bench.status()["store"]["ok"], timeout_s=30)
        after = bench.add(short_session(tmp_path, 1.0, name="after"))
        assert bench.wait(after["uid"])["status"] == "completed"
    finally:
        svc.stop()
    text = svc.output()
    assert "Traceback" not in text.split("worker.log")[0]
    assert "cannot be written" in text and "takes writes again" in text
    json.dumps(record)
