"""The live page's results in headless Chromium (docs/service.md, "The live page"): a finished item opens with its
plots and metrics when its history row is clicked, and two items ticked and compared show a metrics table with a
column each and every chart with each item's channels overlaid (2 items x the chart's channels), a unit on every
axis and legend entry; no console error in any of it. The browser, the service and the helpers are test_page's."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

from tests.factories import short_session
from tests.service.conftest import Service
from tests.service.test_page import browser, open_page, severe, state  # noqa: F401  (browser: a fixture; skips without Chromium)

# a click in the history, by the row's uid: one script call (the table is redrawn every 15 s and on changes)
CLICK = """
const node = document.querySelector(`#history tr[data-uid="${arguments[0]}"] ${arguments[1]}`);
if (node) node.click();
return !!node;
"""
RESULTS = """
const r = window.hilPage.results;
if (!r || !r.ready) return null;
const charts = {};
for (const [name, u] of Object.entries(r.charts)) {
  charts[name] = {axes: u.axes.map((a) => a.label), series: u.series.slice(1).map((s) => s.label),
                  points: u.data[0].length, values: u.data.slice(1).map((c) => c.filter(Number.isFinite).length)};
}
const head = [...document.querySelectorAll('#results-metrics thead th[data-uid]')].map((th) => th.dataset.uid);
const rows = [...document.querySelectorAll('#results-metrics tbody tr')].map(
  (tr) => [...tr.querySelectorAll('td')].map((td) => td.textContent));
return {uids: r.uids, charts, head, rows,
        drawn: document.querySelectorAll('#results-charts .uplot canvas').length};
"""


def results(driver: webdriver.Chrome, uids: list[str]) -> dict[str, Any]:
    """The results view once it shows ``uids``."""
    return WebDriverWait(driver, 60, poll_frequency=0.2).until(  # type: ignore[no-any-return]
        lambda d: (r := d.execute_script(RESULTS)) and r["uids"] == uids and r)


def check_charts(shown: dict[str, Any], series: list[dict[str, Any]], items: int) -> None:
    """Every chart of the items' series, with ``items`` x its channels, each axis and legend entry with its unit."""
    specs = {c["name"]: c for c in series[0]["charts"]}
    assert set(shown["charts"]) == set(specs)
    assert shown["drawn"] >= len(specs)
    for name, chart in shown["charts"].items():
        spec = specs[name]
        assert len(chart["series"]) == items * len(spec["lines"]), (name, chart["series"])
        assert chart["axes"] == [f"{spec['x']['label']} (s)"] + [f"{a['label']} ({a['unit']})" for a in spec["axes"]]
        units = [line["unit"] for line in spec["lines"]] * items
        assert all(label.endswith(f"({unit})") for label, unit in zip(chart["series"], units, strict=True)), chart
        assert chart["points"] > 0 and all(n > 0 for n in chart["values"][:2]), (name, chart["values"])


@pytest.mark.slow
def test_a_clicked_item_opens_with_its_plots_and_two_ticked_items_compare(service: Service,
                                                                         browser: webdriver.Chrome,  # noqa: F811
                                                                         tmp_path: Path) -> None:
    bench = service.bench(user="ana")
    uids = [bench.run_item(short_session(tmp_path, 2.0, name=name), out=tmp_path / name)[1]["uid"]
            for name in ("cmp-a", "cmp-b")]
    series = [bench.call("GET", f"/api/history/{uid}/series?max_points=2000") for uid in uids]
    open_page(browser, service)
    for uid in uids:
        WebDriverWait(browser, 60, poll_frequency=0.2).until(lambda d, uid=uid: d.find_elements(
            By.CSS_SELECTOR, f'#history tr[data-uid="{uid}"] input.pick:not([disabled])'))

    assert browser.execute_script(CLICK, uids[0], "td:nth-child(2)")  # the row (its name): the item's own results
    one = results(browser, uids[:1])
    assert one["head"] == uids[:1] and len(one["rows"]) >= 20
    assert all(row[2] for row in one["rows"]) and any(row[0] == "rate error el: std" for row in one["rows"])
    check_charts(one, series[:1], 1)

    compare = browser.find_element(By.ID, "compare")
    assert not compare.is_enabled()
    for uid in reversed(uids):
        assert browser.execute_script(CLICK, uid, "input.pick")
    WebDriverWait(browser, 10).until(lambda d: d.find_element(By.ID, "compare").is_enabled())
    assert compare.text == "Compare selected (2)"
    compare.click()
    both = results(browser, list(reversed(uids)))
    assert both["head"] == list(reversed(uids))  # a column each
    metrics = {row[0]: row for row in both["rows"]}
    assert metrics["rate error el: std"][1] == "deg/s" and all(metrics["rate error el: std"][2:])
    assert all(len(row) == 4 for row in both["rows"])
    check_charts(both, series, 2)
    assert state(browser)["errors"] == []
    assert severe(browser) == []
