"""Two machines: the service bound to a network address (with tokens), and a second host (a network namespace with
its own address, joined by a veth pair) whose client and browser see the same queue, the same live run and the same
history as a client on the service's own machine (docs/service.md). Skipped where network namespaces cannot be
made (not root, no iproute2) or without Debian's chromium."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.factories import short_session
from tests.service.conftest import Service, wait_for

REPO = Path(__file__).resolve().parents[2]
OPERATOR = "remote-op-4c1f9a7e2d"
VIEWER = "remote-view-8b3e5d0a6f"
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")


def sh(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, capture_output=True, text=True, timeout=30, check=False)


@pytest.fixture
def other_host() -> Iterator[tuple[str, str]]:
    """(namespace, the service's address as the other host sees it): 10.213.N.1 here, 10.213.N.2 there."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("a second host needs network namespaces: root and iproute2")
    n = os.getpid() % 250
    ns, here, there = f"hilhost{os.getpid()}", f"hv{os.getpid() % 100000}a", f"hv{os.getpid() % 100000}b"
    made = sh("ip", "netns", "add", ns)
    if made.returncode != 0:
        pytest.skip(f"cannot make a network namespace: {made.stderr.strip()}")
    try:
        for cmd in (("ip", "link", "add", here, "type", "veth", "peer", "name", there),
                    ("ip", "link", "set", there, "netns", ns),
                    ("ip", "addr", "add", f"10.213.{n}.1/24", "dev", here), ("ip", "link", "set", here, "up"),
                    ("ip", "netns", "exec", ns, "ip", "addr", "add", f"10.213.{n}.2/24", "dev", there),
                    ("ip", "netns", "exec", ns, "ip", "link", "set", there, "up"),
                    ("ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up")):
            done = sh(*cmd)
            if done.returncode != 0:
                pytest.skip(f"cannot join the namespaces ({' '.join(cmd)}): {done.stderr.strip()}")
        yield ns, f"10.213.{n}.1"
    finally:
        sh("ip", "link", "del", here)
        sh("ip", "netns", "del", ns)


# run on the other host: a client's view, and a browser's, of the run the local client started
REMOTE = textwrap.dedent('''
    import json, sys, time
    from pathlib import Path
    from hil.service import Bench
    url, token, uid, chromium, chromedriver, profile, ready = sys.argv[1:8]
    bench = Bench(url, token=token, user="elsewhere")
    out = {"you": bench.status()["you"]}
    deadline = time.monotonic() + 240
    driver = None
    if chromium:  # the page is open, and has its first status, before the run starts
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
        options = webdriver.ChromeOptions()
        options.binary_location = chromium
        for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                     "--disable-background-networking", "--no-first-run", "--user-data-dir=" + profile):
            options.add_argument(flag)
        driver = webdriver.Chrome(service=Service(executable_path=chromedriver), options=options)
        driver.get(url + "/?token=" + token)
        while time.monotonic() < deadline and not driver.execute_script(
                "return !!(window.hilPage && window.hilPage.status)"):
            time.sleep(0.2)
    Path(ready).touch()
    try:
        while time.monotonic() < deadline and (bench.status()["running"] or {}).get("uid") != uid:
            time.sleep(0.1)
        out["running"] = (bench.status()["running"] or {}).get("uid")
        out["queue"] = [i["uid"] for i in bench.queue()["items"]]
        if driver is not None:
            page = None
            while time.monotonic() < deadline:
                page = driver.execute_script(
                    "const p = window.hilPage; return p && p.status ? {points: p.points, running: "
                    "p.status.running ? p.status.running.uid : null} : null")
                if page and page["points"] > 20 and page["running"] == uid:
                    break
                time.sleep(0.2)
            out["page"] = page
    finally:
        if driver is not None:
            driver.quit()
    record = bench.wait(uid)
    out["record"] = {"uid": record["uid"], "status": record["status"], "user": record["user"]}
    out["history"] = [r["uid"] for r in bench.history(limit=10)]
    print(json.dumps(out))
''')


@pytest.mark.slow
@pytest.mark.browser
@pytest.mark.realtime
def test_a_client_and_a_browser_on_another_host_see_the_same_queue_live_run_and_history(
        other_host: tuple[str, str], tmp_path: Path) -> None:
    ns, address = other_host
    tokens = tmp_path / "tokens.yaml"
    tokens.write_text(f"tokens:\n  - {{user: olga, role: operator, token: {OPERATOR}}}\n"
                      f"  - {{user: vic, role: viewer, token: {VIEWER}}}\n")
    svc = Service(tmp_path / "state", args=("--loopback", "--host", address, "--token-file", str(tokens)),
                  token=OPERATOR, host=address).start()
    try:
        local = svc.bench(user="olga")
        local.stop_queue()
        item = local.add(short_session(tmp_path, 8.0, name="shared-run"))
        waiting = local.add(short_session(tmp_path, 1.0, name="next-run"))
        browser = CHROMIUM.is_file() and CHROMEDRIVER.is_file()
        ready = tmp_path / "remote-ready"
        remote = subprocess.Popen(
            ["ip", "netns", "exec", ns, sys.executable, "-c", REMOTE, svc.url, VIEWER, item["uid"],
             str(CHROMIUM) if browser else "", str(CHROMEDRIVER), str(tmp_path / "chromium"), str(ready)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
        # the run starts once the other host's page is open: a browser that starts slowly on a busy machine
        # must not miss an 8 s run
        wait_for(lambda: ready.exists() or remote.poll() is not None, timeout_s=300)
        local.start()
        wait_for(lambda: (local.status()["running"] or {}).get("uid") == item["uid"], timeout_s=240)
        local_queue = [i["uid"] for i in local.queue()["items"]]
        out, err = remote.communicate(timeout=600)
        assert remote.returncode == 0, err[-3000:]
        seen = json.loads(out)
        local.wait(waiting["uid"])
        local_history = [r["uid"] for r in local.history(limit=10)]
    finally:
        svc.stop()
    assert seen["you"] == {"user": "vic", "role": "viewer"}
    assert seen["running"] == item["uid"] and seen["queue"] == local_queue == [item["uid"], waiting["uid"]]
    if browser:
        assert seen["page"]["running"] == item["uid"] and seen["page"]["points"] > 20
    assert seen["record"] == {"uid": item["uid"], "status": "completed", "user": "olga"}
    # the same history: seen just after the shared run ended, the next one perhaps not yet done
    assert local_history[:2] == [waiting["uid"], item["uid"]]
    assert seen["history"] in (local_history, local_history[1:])
