"""The live page of `hil serve --loopback` in a real browser (Debian's headless Chromium driven by selenium,
docs/service.md, "The live page"): it shows the boards as the status says, plots the running item's live points as
they come (finite numbers, the count advancing), and its Stop button ends a session the normal way. Lenient on
timing (a loaded machine), strict on what is shown; no console error in any of it."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.factories import short_session
from tests.service.conftest import Service, wait_for

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
_missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.is_file()]
if _missing:
    pytest.skip(f"the live page's browser tests need Debian's chromium and chromium-driver ({', '.join(_missing)} "
                "missing; `python3 dev.py test` installs them where apt-get is available)", allow_module_level=True)

from selenium import webdriver  # noqa: E402  (after the skip: the browser decides whether these tests run)
from selenium.webdriver.chrome.service import Service as DriverService  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support import expected_conditions  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

START_S = 240.0  # the first session on a loaded VM may take 30 s and more to start; a browser, a few s
END_S = 240.0
SAFE = "driver disabled, servo stream idle, hexapod IDLE at home"  # the boards' rest state, measured
AXES = {"rate": ["time of day (h:m:s)", "rate error (deg/s)"], "drive": ["time of day (h:m:s)", "drive (counts)"],
        "miss": ["time of day (h:m:s)", "miss distance (px)"],
        "pose": ["time of day (h:m:s)", "position (mm)", "rotation (deg)"]}
LEGENDS = {"rate": ["el (deg/s)", "az (deg/s)"], "drive": ["el (counts)", "az (counts)"], "miss": ["x (px)", "y (px)"],
           "pose": ["x (mm)", "y (mm)", "z (mm)", "roll (deg)", "pitch (deg)", "yaw (deg)"]}
LABELS = """
const out = {};
for (const [name, u] of Object.entries(window.hilPage.charts)) {
  out[name] = {axes: u.axes.map((a) => a.label), series: u.series.slice(1).map((s) => s.label)};
}
return out;
"""

# what the charts hold now: for every series, its finite values, and anything else that is not null
CHART_VALUES = """
const out = {};
for (const [name, u] of Object.entries(window.hilPage.charts)) {
  const xs = u.data[0];
  let increasing = true;
  for (let i = 1; i < xs.length; i++) if (!(xs[i] > xs[i - 1])) increasing = false;
  out[name] = {n: xs.length, increasing, x_finite: xs.every(Number.isFinite), series: u.data.slice(1).map((col) => ({
    finite: col.filter(Number.isFinite).length,
    bad: col.filter((v) => v !== null && !Number.isFinite(v)).length}))};
}
return out;
"""
STATE = """
const p = window.hilPage;
if (!p) return null;
return {points: p.points, lastCycles: p.lastCycles, frames: p.frames, errors: p.errors, connected: p.connected,
        running: p.status && p.status.running ? p.status.running.uid : null, last: p.last ? p.last.uid : null,
        lagMs: p.lagMs.length, lagFinite: p.lagMs.every(Number.isFinite)};
"""


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[webdriver.Chrome]:
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", "--window-size=1400,1000", f"--user-data-dir={tmp_path / 'chromium'}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=DriverService(executable_path=str(CHROMEDRIVER)), options=options)
    driver.set_page_load_timeout(120)
    driver.set_script_timeout(60)
    try:
        yield driver
    finally:
        try:
            driver.save_screenshot(str(tmp_path / "page.png"))  # for whoever reads a failure
        finally:
            driver.quit()


def open_page(driver: webdriver.Chrome, service: Service) -> None:
    driver.get(service.url + "/")
    WebDriverWait(driver, 120, poll_frequency=0.2).until(lambda d: (d.execute_script(STATE) or {}).get("connected")
                                                          and d.find_element(By.ID, "conn").text == "connected")


def state(driver: webdriver.Chrome) -> dict[str, Any]:
    return driver.execute_script(STATE)  # type: ignore[no-any-return]


def severe(driver: webdriver.Chrome) -> list[dict[str, Any]]:
    return [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]


HISTORY_ROW = """
const tr = document.querySelector(`#history tr[data-uid="${arguments[0]}"]`);
if (!tr) return null;
const link = (text) => { const a = [...tr.querySelectorAll('a')].find((x) => x.textContent === text);
                         return a ? a.href : null; };
return {status: tr.dataset.status, record: link('record'), log: link('log')};
"""


def history_row(driver: webdriver.Chrome, uid: str) -> dict[str, Any]:
    """The history row of ``uid``, read in one script call (the table is redrawn every 15 s and on changes)."""
    return WebDriverWait(driver, 60, poll_frequency=0.2).until(  # type: ignore[no-any-return]
        lambda d: d.execute_script(HISTORY_ROW, uid))


BOARD_ROWS = """
const rows = {};
for (const tr of document.querySelectorAll('#boards tr[data-board]')) {
  rows[tr.dataset.board] = {port: tr.querySelector('td.port').textContent, connected: tr.dataset.connected,
                            identified: tr.dataset.identified, armed: tr.dataset.armed};
}
return rows;
"""


@pytest.mark.slow
def test_the_page_shows_the_boards_as_the_status_says_without_a_console_error(service: Service,
                                                                             browser: webdriver.Chrome) -> None:
    status = service.bench().status()
    boards = status["worker"]["boards"]
    assert boards, status
    open_page(browser, service)
    WebDriverWait(browser, 60).until(
        lambda d: len(d.find_elements(By.CSS_SELECTOR, "#boards tr[data-board]")) == len(boards))
    shown = browser.execute_script(BOARD_ROWS)  # one read: the table is redrawn as status messages arrive
    for name, board in boards.items():
        row = shown[name]
        assert row["port"] == board["port"], (name, row)
        for field in ("connected", "identified", "armed"):
            assert row[field] == str(board[field]).lower(), (name, field)
    assert browser.find_element(By.ID, "worker-state").text == "ready"
    assert SAFE in browser.find_element(By.ID, "safe").text
    assert browser.find_element(By.ID, "you").text == "you: local (operator)"  # a browser on localhost
    assert "No item running" in browser.find_element(By.ID, "running-card").text
    assert not browser.find_element(By.ID, "stop").is_displayed()  # nothing to stop
    labels = browser.execute_script(LABELS)  # every axis and every legend entry says its unit
    assert {name: chart["axes"] for name, chart in labels.items()} == AXES
    assert {name: chart["series"] for name, chart in labels.items()} == LEGENDS
    legend = browser.find_element(By.ID, "charts-card").text
    assert all(label in legend for names in LEGENDS.values() for label in names), legend
    assert browser.execute_script("return document.querySelectorAll('#charts-card .uplot canvas').length") >= 4
    assert state(browser)["errors"] == []
    assert severe(browser) == []


@pytest.mark.slow
def test_the_running_items_points_are_plotted_as_they_come(service: Service, browser: webdriver.Chrome,
                                                           tmp_path: Path) -> None:
    bench = service.bench(user="ana")
    open_page(browser, service)
    uid = bench.add(short_session(tmp_path, 6.0, name="page-live"))["uid"]
    # the run's start: the page has a point of this item from a loop that cycles
    first = wait_for(lambda: (s := state(browser))["last"] == uid and s["lastCycles"] > 0 and s, START_S, 0.05)
    t0 = time.monotonic()
    assert browser.find_element(By.ID, "run-name").text == "page-live"
    assert browser.find_element(By.ID, "run-user").text == "ana"
    time.sleep(3.0)
    then = state(browser)
    took = time.monotonic() - t0
    points = then["points"] - first["points"]
    assert points > 40, f"{points} points plotted in {took:.1f} s"  # >= ~13 Hz even on a loaded machine
    assert then["lastCycles"] > first["lastCycles"] and then["frames"] > first["frames"]
    # drawn once a second, however many points came (docs/service.md, "Watching the bench")
    assert then["frames"] - first["frames"] <= took + 1, (then["frames"] - first["frames"], took)
    assert then["lagMs"] > 0 and then["lagFinite"]
    assert "cycles" in browser.find_element(By.ID, "run-progress").text
    charts = browser.execute_script(CHART_VALUES)
    assert set(charts) == {"rate", "drive", "miss", "pose"}
    for name, chart in charts.items():
        assert chart["n"] > 0 and chart["x_finite"] and chart["increasing"], (name, chart)
        assert all(s["bad"] == 0 for s in chart["series"]), (name, chart)
    for name in ("rate", "drive"):  # the loop's values are there from the loop's first cycles
        assert all(s["finite"] > 0 for s in charts[name]["series"]), (name, charts[name])
    record = wait_for(lambda: (v := bench.item(uid))["state"] == "done" and v, END_S, 0.5)
    row = history_row(browser, uid)
    assert row["status"] == record["status"]
    assert row["record"].endswith(f"/api/history/{uid}"), row
    assert state(browser)["errors"] == []
    assert severe(browser) == []


@pytest.mark.slow
def test_stop_on_the_page_ends_the_session_the_normal_way(service: Service, browser: webdriver.Chrome,
                                                          tmp_path: Path) -> None:
    bench = service.bench(user="ana")
    open_page(browser, service)
    uid = bench.add(short_session(tmp_path, 30.0, name="page-stop"))["uid"]
    wait_for(lambda: (s := state(browser))["last"] == uid and s["lastCycles"] > 0, START_S, 0.1)
    stop, abort = browser.find_element(By.ID, "stop"), browser.find_element(By.ID, "abort")
    assert stop.is_displayed() and abort.is_displayed()  # this caller is an operator (localhost)
    abort.click()  # Abort asks first; dismissed, nothing happens
    alert = WebDriverWait(browser, 10).until(expected_conditions.alert_is_present())
    assert alert.text.startswith("Abort page-stop?")
    alert.dismiss()
    assert bench.item(uid)["state"] == "running"
    stop.click()  # Stop does not ask
    WebDriverWait(browser, 60).until(lambda d: "stop asked" in d.find_element(By.ID, "action-msg").text)
    record = wait_for(lambda: (v := bench.item(uid))["state"] == "done" and v, END_S, 0.5)
    assert record["status"] == "stopped" and record["exit_code"] == 3, record
    assert record["links"]["log"] == f"/api/history/{uid}/log"
    assert "by local: from the live page" in record["message"]
    row = history_row(browser, uid)
    assert row["status"] == "stopped"
    assert row["log"].endswith(f"/api/history/{uid}/log"), row
    assert state(browser)["errors"] == []
    assert severe(browser) == []
