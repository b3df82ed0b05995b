"""A client owns its item (docs/service.md, "Clients"): Ctrl-C at `hil run|ident|campaign --bench` takes a waiting
item off the queue, stops a running one the normal way, aborts it at the second Ctrl-C and leaves at the third,
the client still waiting for the end and bringing the log back; a waiting client sees its real place and who holds
the lease; a uid is taken by its first characters; `hil bench status` shows the boards' measured rest state; and
`hil queue` / `hil bench` load the client alone. Against a real `hil serve --loopback`, the client a real process
sent SIGINT."""

from __future__ import annotations

import getpass
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import pytest

from hil.cli._bench import waiting_line
from hil.service import Bench
from tests.factories import short_session
from tests.service.conftest import Service, wait_for

REPO = Path(__file__).resolve().parents[2]
USER = getpass.getuser()  # who the command line's items are for (X-Hil-User)
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


class Client:
    """A `hil ...` command line in its own session (as a terminal's foreground job would get Ctrl-C), its output
    read as it comes (a progress bar's redraws too, which end in no newline)."""

    def __init__(self, *args: str, env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "hil", *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, cwd=REPO, start_new_session=True,
                                     env={**os.environ, **(env or {})})
        self.out: list[bytes] = []
        self.err: list[bytes] = []
        self.readers = [threading.Thread(target=self._read, args=(self.proc.stdout, self.out), daemon=True),
                        threading.Thread(target=self._read, args=(self.proc.stderr, self.err), daemon=True)]
        for reader in self.readers:
            reader.start()

    @staticmethod
    def _read(stream, into: list[bytes]) -> None:  # type: ignore[no-untyped-def]
        while chunk := os.read(stream.fileno(), 1 << 16):
            into.append(chunk)

    def stdout(self) -> str:
        return ANSI.sub("", b"".join(self.out).decode(errors="replace"))

    def stderr(self) -> str:
        """What it wrote on stderr as lines of text: each redraw of a progress line (after a carriage return) a
        line of its own, the terminal's control sequences left out."""
        return ANSI.sub("", b"".join(self.err).decode(errors="replace").replace("\r", "\n"))

    def wait_for_err(self, text: str, timeout_s: float = 120.0) -> None:
        wait_for(lambda: text in self.stderr() or self.proc.poll() is not None, timeout_s)
        assert text in self.stderr(), self.stderr()[-3000:]

    def ctrl_c(self) -> None:
        self.proc.send_signal(signal.SIGINT)

    def finish(self, timeout_s: float = 180.0) -> int:
        code = self.proc.wait(timeout_s)
        for reader in self.readers:
            reader.join(10)
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


@pytest.fixture
def clients() -> Iterator[list[Client]]:
    started: list[Client] = []
    yield started
    for client in started:
        client.kill()


def queued(bench: Bench, name: str) -> dict:
    """The item of the queue named ``name`` (waited for)."""
    return wait_for(lambda: next((i for i in bench.queue()["items"] if i["name"] == name), None), timeout_s=60)


def running_client(service: Service, tmp_path: Path, clients: list[Client], name: str,
                   *extra: str) -> tuple[Client, str]:
    """`hil run --bench` of a 20 s session named ``name`` (its log into ``tmp_path/out``), and its item's uid, once
    that item has run 1000 cycles."""
    run = Client("run", str(short_session(tmp_path, 20.0, name=name)), "--bench", service.url,
                 "--out", str(tmp_path / "out"), *extra)
    clients.append(run)
    bench = service.bench()
    uid = queued(bench, name)["uid"]
    wait_for(lambda: bench.item(uid).get("cycles", 0) > 1000, timeout_s=180)
    return run, uid


def lines_with(text: str, output: str) -> list[str]:
    return [line for line in output.splitlines() if text in line]


@pytest.mark.slow
def test_a_waiting_item_knows_its_place_who_runs_before_it_and_the_lease(service: Service, tmp_path: Path) -> None:
    bo, cy, ana = service.bench(user="bo"), service.bench(user="cy"), service.bench(user="ana")
    bo.stop_queue()
    try:
        a, b, c, d = (who.add(short_session(tmp_path, 1.0, name=f"place-{n}"))
                      for n, who in zip("abcd", (bo, cy, ana, bo), strict=True))
        view = bo.item(b["uid"])
        assert (view["state"], view["place"], view["waiting"], view["ahead"]) == ("queued", 2, 4, 1)
        assert view["lease_holder"] is None and view["queue_stopped"] == "stopped by bo; 4 items wait"
        ana.lease(ttl_s=120)
        view = bo.item(b["uid"])  # held back: a before it, and ana's c after it, run first
        assert (view["place"], view["waiting"], view["ahead"], view["lease_holder"]) == (2, 4, 2, "ana")
        assert 100 < view["lease_remaining_s"] <= 120
        view = ana.item(c["uid"])  # the holder's own: only her items before it run first (none)
        assert (view["place"], view["ahead"], view["lease_holder"]) == (3, 0, None)
        view = bo.item(d["uid"])
        assert (view["place"], view["ahead"], view["lease_holder"]) == (4, 3, "ana")
        assert bo.item(a["uid"])["ahead"] == 1  # ana's c runs before it
        assert waiting_line("place-b.yaml", service.url, bo.item(b["uid"])) == (
            f"place-b.yaml: waiting in {service.url}'s queue: 2nd of 4, 2 items to run before it; the lease is "
            f"ana's (2 min left); the queue is stopped (stopped by bo; 4 items wait): `hil queue start --bench "
            f"{service.url}` starts it")
    finally:
        ana.lease(ttl_s=30)  # the lease holder clears every user's waiting items
        ana.clear()
        ana.release()
        bo.start()


def test_ctrl_c_while_a_lease_holds_the_run_back_takes_it_off_the_queue(service: Service, tmp_path: Path,
                                                                        clients: list[Client]) -> None:
    ana, bo = service.bench(user="ana"), service.bench(user="bo")
    ana.lease(ttl_s=250)
    try:
        first = bo.add(short_session(tmp_path, 1.0, name="held-first"))
        # the progress line drawn as on a terminal, wide enough to be read whole
        run = Client("run", str(short_session(tmp_path, 2.0, name="held-mine")), "--bench", service.url,
                     "--out", str(tmp_path / "out"),
                     env={"TTY_COMPATIBLE": "1", "TTY_INTERACTIVE": "1", "COLUMNS": "400"})
        clients.append(run)
        mine = queued(bo, "held-mine")
        last = bo.add(short_session(tmp_path, 1.0, name="held-last"))
        view = bo.item(mine["uid"])
        assert (view["place"], view["waiting"], view["ahead"], view["lease_holder"]) == (2, 3, 1, "ana")
        run.wait_for_err(f"held-mine.yaml: waiting in {service.url}'s queue: 2nd of 3; the lease is ana's "
                         "(4 min left)")
        run.ctrl_c()
        assert run.finish() == 130
        said = lines_with("Ctrl-C", run.stderr())
        assert said == [f"held-mine.yaml: Ctrl-C: took item {mine['uid'][:12]} off the queue before it ran"]
        assert "removed: taken off the queue before it ran: Ctrl-C at the client" in run.stdout()
        assert [i["uid"] for i in bo.queue()["items"]] == [first["uid"], last["uid"]]
        assert all(r["uid"] != mine["uid"] for r in bo.history(limit=50))  # it never ran: no record
        assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())
    finally:
        bo.clear()
        ana.release()


@pytest.mark.parametrize("kind", ["ident", "campaign"])
def test_ctrl_c_at_ident_and_campaign_while_waiting_takes_the_item_off_the_queue(
        service: Service, tmp_path: Path, clients: list[Client], kind: str) -> None:
    bench = service.bench()
    bench.stop_queue()
    try:
        if kind == "ident":
            file, name = short_session(tmp_path, 2.0, name="ident-waits"), "ident-waits"
            args = ["ident", str(file), "--bench", service.url, "--out", str(tmp_path / "ident")]
        else:
            file = REPO / "profiles/campaigns/static-gyro-noise.yaml"
            args, name = ["campaign", str(file), "--bench", service.url], None
        client = Client(*args)
        clients.append(client)
        item = wait_for(lambda: next((i for i in bench.queue()["items"] if i["kind"] == kind
                                      and (name is None or i["name"] == name)), None), timeout_s=60)
        time.sleep(0.5)  # it follows its item now
        client.ctrl_c()
        assert client.finish() == 130
        assert lines_with("Ctrl-C", client.stderr()) == [
            f"{file.name}: Ctrl-C: took item {item['uid'][:12]} off the queue before it ran"]
        assert bench.queue()["items"] == []
    finally:
        bench.clear()
        bench.start()


@pytest.mark.slow
def test_ctrl_c_while_it_runs_stops_it_and_the_log_comes_back(service: Service, tmp_path: Path,
                                                              clients: list[Client]) -> None:
    bench = service.bench()
    out = tmp_path / "out"
    run, uid = running_client(service, tmp_path, clients, "stop-me")
    # while it runs, the boards its loop drives are armed, and the status says so in words
    wait_for(lambda: bench.status()["worker"]["boards"]["driver"]["armed"], timeout_s=30)
    status = subprocess.run([sys.executable, "-m", "hil", "bench", "status", "--bench", service.url],
                            capture_output=True, text=True, timeout=60, cwd=REPO, check=False)
    assert status.returncode == 0, status.stderr
    assert "True" not in status.stdout and "False" not in status.stdout and "connected" not in status.stdout
    boards = {line.split()[0]: line for line in status.stdout.splitlines() if line.startswith("  ") and
              line.split()[0] in ("servo", "driver", "image", "hexapod")}
    assert boards["driver"].endswith("; armed") and boards["servo"].endswith("; armed"), status.stdout
    assert "armed" not in boards["image"] and "at rest" not in status.stdout
    assert f"running: stop-me (session, {USER})" in status.stdout
    after = bench.add(short_session(tmp_path, 1.0, name="after-stop"))  # it waits behind the running one
    view = bench.item(after["uid"])
    assert (view["place"], view["waiting"], view["ahead"], view["lease_holder"]) == (1, 1, 1, None)

    run.ctrl_c()
    assert run.finish() == 3, run.stderr()[-3000:]
    assert lines_with("Ctrl-C", run.stderr()) == [
        f"stop-me.yaml: Ctrl-C: stopping item {uid[:12]} the normal way (the swing stops while the loop stabilizes, "
        "then the driver is disabled); Ctrl-C again aborts it"]
    record = bench.wait(uid)
    assert record["status"] == "stopped" and record["exit_code"] == 3, record
    assert f"Ctrl-C at the client ({USER})" in record["message"]
    assert 1000 < record["summary"]["cycles"] < 20_000  # ended well before its 20 s
    stdout = run.stdout()
    assert f"stopped: {record['message']}" in " ".join(stdout.split())
    log = out / Path(record["log_path"]).name
    assert log.is_file() and str(log) in stdout.replace("\n", "")
    with h5py.File(log, "r") as f:
        events = [bytes(k).decode() for k in f["events/kind"][:]]
    assert "signal" not in events  # the normal wind-down, not the abort's path
    assert bench.wait(after["uid"])["status"] == "completed"  # a stop lets the queue go on


@pytest.mark.slow
def test_a_second_ctrl_c_aborts_it_and_the_client_still_brings_the_log_back(service: Service, tmp_path: Path,
                                                                           clients: list[Client]) -> None:
    bench = service.bench()
    out = tmp_path / "out"
    run, uid = running_client(service, tmp_path, clients, "abort-me", "--json")
    try:
        run.ctrl_c()
        run.wait_for_err("Ctrl-C again aborts it")
        run.ctrl_c()
        assert run.finish() == 130, run.stderr()[-3000:]
        assert lines_with("Ctrl-C", run.stderr())[1] == (
            f"abort-me.yaml: Ctrl-C again: aborting item {uid[:12]} (the driver disabled first); waiting for its end "
            "(Ctrl-C once more leaves without it)")
        assert len(lines_with("Ctrl-C", run.stderr())) == 2
        record = bench.wait(uid)
        assert record["status"] == "aborted", record
        printed = json.loads(run.stdout())  # hil run's JSON record, its log the copy in --out
        assert printed["status"] == "aborted" and printed["exit_code"] == 130
        log = Path(printed["log"])
        assert log.parent == out and log.name == Path(record["log_path"]).name and log.is_file()
        with h5py.File(log, "r") as f:
            events = [bytes(k).decode() for k in f["events/kind"][:]]
        assert "signal" in events  # the abort's path: the driver disabled first
        assert bench.queue()["stopped"].startswith(f"aborted by {USER}: Ctrl-C at the client ({USER}), a second time")
    finally:
        bench.start()


@pytest.mark.slow
def test_a_third_ctrl_c_leaves_at_once_and_the_item_goes_on_without_it(service: Service, tmp_path: Path,
                                                                       clients: list[Client]) -> None:
    bench = service.bench()
    out = tmp_path / "out"
    run, uid = running_client(service, tmp_path, clients, "leave-it")
    try:
        run.ctrl_c()
        run.wait_for_err("Ctrl-C again aborts it")
        run.ctrl_c()
        time.sleep(0.2)  # the abort asked for; the item winds down for longer than this
        run.ctrl_c()
        t0 = time.monotonic()
        assert run.finish() == 130
        assert time.monotonic() - t0 < 5.0
        assert lines_with("Ctrl-C", run.stderr())[2] == (
            f"leave-it.yaml: Ctrl-C a third time: leaving now; item {uid[:12]} goes on without this client (its record "
            f"and log stay in {service.url}'s history)")
        record = bench.wait(uid)  # the abort it asked for before it left still ends the item
        assert record["status"] == "aborted" and record["links"]["log"]
        assert not out.exists() or not list(out.glob("*.h5"))  # it did not wait for the log
    finally:
        bench.start()


@pytest.mark.slow
def test_bench_run_in_a_notebook_stops_its_item_on_keyboard_interrupt(service: Service, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    bench = service.bench(user="nb")
    interrupted: list[int] = []

    def on_view(view: dict) -> None:  # the notebook's interrupt, arriving while the run is followed
        if view["state"] == "running" and view.get("cycles", 0) > 1000 and not interrupted:
            interrupted.append(view["cycles"])
            raise KeyboardInterrupt

    result = bench.run(short_session(tmp_path, 20.0, name="notebook"), out=tmp_path / "logs", on_view=on_view)
    assert interrupted and result.status == "stopped" and result.exit_code == 3, result
    assert "Ctrl-C at the client (nb)" in result.message
    assert result.log_path is not None and result.log_path.parent == tmp_path / "logs"
    assert interrupted[0] < len(result.log.loop) < 20_000
    said = [line for line in capsys.readouterr().err.splitlines() if "Ctrl-C" in line]
    assert len(said) == 1 and said[0].startswith("notebook.yaml: Ctrl-C: stopping item ")


@pytest.mark.slow
def test_a_uid_is_taken_by_its_first_characters(service: Service, tmp_path: Path) -> None:
    bench = service.bench(user=getpass.getuser())  # the items are the command line's user's own to move and remove

    def hil(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "hil", *args, "--bench", service.url], capture_output=True,
                              text=True, timeout=60, cwd=REPO, check=False)

    bench.stop_queue()
    try:
        a, b = (bench.add(short_session(tmp_path, 1.0, name=n)) for n in ("prefix-a", "prefix-b"))
        moved = hil("queue", "move", a["uid"][:12], "1")
        assert moved.returncode == 0 and moved.stdout.strip() == f"moved {a['uid'][:12]} (prefix-a) to 1"
        assert [i["uid"] for i in bench.queue()["items"]] == [b["uid"], a["uid"]]
        removed = hil("queue", "remove", b["uid"][:6].upper())
        assert removed.returncode == 0, removed.stderr
        assert removed.stdout.strip() == f"removed {b['uid'][:12]} (session prefix-b, user {getpass.getuser()})"
        for args, line in (
                (("queue", "remove", a["uid"][:5]),
                 f"item {a['uid'][:5]!r}: give at least 6 characters of its uid (`hil queue list` shows 12)"),
                (("queue", "move", "zzzzzz", "0"),
                 "item 'zzzzzz': no item in the queue has a uid that starts with it (`hil queue list` shows them)"),
                (("bench", "stop", "--item", a["uid"][:8]), "no item is running")):
            refused = hil(*args)
            assert refused.returncode == 2 and refused.stderr.strip() == f"error: {line}", refused.stderr
        bench.start()
        record = bench.wait(a["uid"])
        ended = hil("queue", "remove", a["uid"][:10])
        assert ended.returncode == 2 and ended.stderr.strip() == (
            f"error: item {a['uid'][:10]!r}: not in the queue; it ended {record['status']} at {record['ended_at']}")
    finally:
        bench.clear()
        bench.start()


def test_bench_status_between_items_shows_ports_identities_and_the_measured_rest_state(service: Service) -> None:
    status = wait_for(lambda: (s := service.bench().status())["worker"]["rest"] and s, timeout_s=60)
    run = subprocess.run([sys.executable, "-m", "hil", "bench", "status", "--bench", service.url],
                         capture_output=True, text=True, timeout=60, cwd=REPO, check=False)
    assert run.returncode == 0, run.stderr
    text = run.stdout
    assert "True" not in text and "False" not in text and "connected" not in text and "armed" not in text
    lines = {line.split()[0]: line for line in text.splitlines() if line.startswith("  ")}
    ports = status["worker"]["ports"]
    rest = status["worker"]["rest"]["boards"]
    for board in ("servo", "driver", "image", "hexapod"):
        finding = next(f for f in status["worker"]["doctor"]["findings"]
                       if f["link"] == board and f["check"] == "ident")
        firmware, serial = finding["values"]["firmware_version"], finding["values"]["serial_number"]
        assert ports[board] in lines[board] and f"identified (firmware {firmware}, serial {serial})" in lines[board]
    assert lines["driver"].endswith("; at rest: disabled") and rest["driver"] == "disabled"
    assert lines["servo"].endswith("; at rest: stream idle")
    assert re.search(r"; at rest: (IDLE|LOADED) at home$", lines["hexapod"]), lines["hexapod"]
    assert "at rest" not in lines["image"]  # the rest check does not listen to the image board
    assert re.search(r"^  between items: at rest \(measured \d+ (s|min) ago, after \d+\.\d s\)$", text, re.M), text


LIGHT = """
import json, sys
from hil.cli import main
try:
    main(sys.argv[1:])
except SystemExit:
    pass
print(json.dumps(sorted(sys.modules)), file=sys.stderr)
"""
HEAVY = ("numpy", "h5py", "yaml", "starlette", "uvicorn", "asyncio", "hil.config", "hil.api", "hil.session",
         "hil.campaign", "hil.service._manager", "hil.service._items")


@pytest.mark.parametrize("command", [["queue", "list"], ["queue", "list", "--json"], ["bench", "status"],
                                     ["bench", "status", "--json"]])
def test_queue_and_bench_commands_load_the_client_alone(service: Service, command: list[str]) -> None:
    run = subprocess.run([sys.executable, "-c", LIGHT, *command, "--bench", service.url], capture_output=True,
                         text=True, timeout=60, cwd=REPO, check=False)
    loaded = set(json.loads(run.stderr.strip().splitlines()[-1]))
    assert "hil.service._client" in loaded and run.stdout.strip(), run.stderr[-2000:]
    assert sorted(m for m in HEAVY if m in loaded) == []
