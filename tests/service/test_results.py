"""Results come back whole (docs/service.md, "Results"), on a real `hil serve --loopback`: every file an item
wrote is listed and served from its own directory and nowhere else (``..``, an absolute path, a symlink leading
out, a missing file: 404, one line of JSON); a session's report is linked from its record and readable; its
log's charts come as decimated series with their units; and `--out` brings every file back for each kind: a
session's log and report, an ident's pass logs, Bode plot and fit, a campaign's cells."""

from __future__ import annotations

import http.client
import json
import urllib.parse
from pathlib import Path
from typing import Any

import pytest
import yaml

from hil.service import BenchError
from tests.factories import short_session
from tests.service.conftest import Service
from tests.service.test_item_kinds import REPO, hil

CHARTS = {"rate", "drive", "miss", "gyro", "pose"}


def raw_get(service: Service, path: str) -> tuple[int, str, bytes]:
    """GET ``path`` exactly as written (no client normalizes its ``..`` away): status, content type, body."""
    conn = http.client.HTTPConnection(service.host, service.port, timeout=60)
    try:
        conn.request("GET", path, headers={"X-Hil-User": "tester"})
        answer = conn.getresponse()
        return answer.status, answer.getheader("content-type", ""), answer.read()
    finally:
        conn.close()


def local_files(directory: Path) -> dict[str, int]:
    return {p.relative_to(directory).as_posix(): p.stat().st_size for p in directory.rglob("*") if p.is_file()}


def listed(service: Service, uid: str) -> dict[str, dict[str, Any]]:
    return {f["path"]: f for f in service.bench().call("GET", f"/api/history/{uid}/files")["files"]}


@pytest.fixture(scope="module")
def session_item(service: Service, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    """A 2 s session run through the client into an ``out`` directory: its record and that directory."""
    tmp = tmp_path_factory.mktemp("session")
    result, record = service.bench().run_item(short_session(tmp, 2.0, name="whole"), out=tmp / "out")
    assert result.status == "completed" and result.log_path is not None, result.message
    assert result.log_path.parent == tmp / "out"
    return record, tmp / "out"


@pytest.mark.slow
def test_a_sessions_files_are_listed_served_and_brought_back(service: Service,
                                                            session_item: tuple[dict[str, Any], Path]) -> None:
    record, out = session_item
    uid = record["uid"]
    assert record["links"]["files"] == f"/api/history/{uid}/files"
    files = listed(service, uid)
    assert local_files(out) == {path: f["size"] for path, f in files.items()}  # every file, its relative path kept
    log = Path(record["log_path"]).name
    assert files[log]["kind"] == "log" and files[log]["media_type"] == "application/x-hdf5"
    report = f"{Path(log).stem}-report"
    for name, media in (("report.html", "text/html"), ("report.md", "text/markdown"), ("rate.png", "image/png")):
        assert files[f"{report}/{name}"]["media_type"] == media
    status, kind, body = raw_get(service, f"/api/history/{uid}/files/{report}/report.md")
    assert status == 200 and kind.startswith("text/markdown") and body == (out / report / "report.md").read_bytes()


def test_a_sessions_report_is_linked_from_its_record_and_readable(service: Service, tmp_path: Path,
                                                                 session_item: tuple[dict[str, Any], Path]) -> None:
    record, _out = session_item
    assert record["links"]["report"] == f"/api/history/{record['uid']}/report"
    assert record["report_path"].endswith("-report/report.html")
    page = service.bench().download(record["links"]["report"], tmp_path / "report.html").read_text()
    assert "<h1>Session whole</h1>" in page and "<script" not in page
    assert "rate error el: std" in page and "deg/s" in page and "counts" in page and "px" in page
    assert page.count("data:image/png;base64,") == len(CHARTS)  # one file: its plots inside
    assert f"Service item {record['uid']} (session) ended completed" in page


def test_the_series_of_a_log_are_decimated_with_their_units(service: Service,
                                                           session_item: tuple[dict[str, Any], Path]) -> None:
    record, _out = session_item
    bench = service.bench()
    series = bench.call("GET", f"{record['links']['series']}?max_points=300")
    assert series["uid"] == record["uid"] and series["max_points"] == 300
    charts = {c["name"]: c for c in series["charts"]}
    assert set(charts) == CHARTS
    for name, chart in charts.items():
        assert 0 < len(chart["t"]) <= 300 < chart["rows"] or len(chart["t"]) == chart["rows"], name
        assert set(chart["columns"]) == {line["column"] for line in chart["lines"]}
        assert all(len(col) == len(chart["t"]) for col in chart["columns"].values())
        assert chart["x"]["unit"] == "s" and all(a["unit"] for a in chart["axes"])
        assert all(line["unit"] and 0 <= line["axis"] < len(chart["axes"]) for line in chart["lines"])
    assert {a["unit"] for a in charts["pose"]["axes"]} == {"mm", "deg"}
    metrics = {m["metric"]: m for m in series["metrics"]}
    assert metrics["rate error el: std"]["unit"] == "deg/s" and float(metrics["rate error el: std"]["value"]) > 0
    with pytest.raises(BenchError) as err:
        bench.call("GET", f"{record['links']['series']}?max_points=lots")
    assert err.value.status == 422 and str(err.value) == "max_points: not an integer"


def test_nothing_outside_the_items_directory_is_served(service: Service, tmp_path: Path,
                                                      session_item: tuple[dict[str, Any], Path]) -> None:
    record, _out = session_item
    uid = record["uid"]
    run_dir = service.state_dir / "runs" / uid
    secret = tmp_path / "secret.txt"
    secret.write_text("not the item's")
    (run_dir / "outside.txt").symlink_to(secret)
    (run_dir / "outside-dir").symlink_to(tmp_path, target_is_directory=True)
    (run_dir / "loop.txt").symlink_to(run_dir / "loop.txt")
    base = f"/api/history/{uid}/files"
    try:
        assert not {"outside.txt", "outside-dir/secret.txt", "loop.txt"} & set(listed(service, uid))
        for path in ("../../service.sqlite3", "%2e%2e/%2e%2e/service.sqlite3", "..%2f..%2fservice.sqlite3",
                     "/etc/passwd", "%2Fetc%2Fpasswd", urllib.parse.quote(str(secret)), "outside.txt",
                     "outside-dir/secret.txt", "loop.txt", "no-such-file.h5", "a%00b", ""):
            status, kind, body = raw_get(service, f"{base}/{path}")
            assert status == 404 and kind == "application/json", (path, status, kind, body[:200])
            answer = json.loads(body)
            assert list(answer) == ["detail"] and "\n" not in answer["detail"] and b"not the item's" not in body
        status, kind, body = raw_get(service, "/api/history/0123456789abcdef0123456789abcdef/files/x.h5")
        assert status == 404 and kind == "application/json" and "0123456789abcdef" in json.loads(body)["detail"]
    finally:
        for name in ("outside.txt", "outside-dir", "loop.txt"):
            (run_dir / name).unlink()


@pytest.mark.slow
def test_ident_out_brings_back_every_pass_log_the_bode_plot_and_the_fit(service: Service, tmp_path: Path) -> None:
    out = tmp_path / "ident"
    run = hil("ident", str(short_session(tmp_path, name="ident-out")), "--bench", service.url, "--axis", "el",
              "--sweep-s", "4", "--f-start-hz", "2", "--f-stop-hz", "40", "--amplitude-dps", "4", "--offset-dps", "5",
              "--out", str(out), "--json")
    record = next(r for r in service.bench().history(limit=20) if r["kind"] == "ident")
    files = listed(service, record["uid"])
    assert local_files(out) == {path: f["size"] for path, f in files.items()}, run.stderr[-2000:]
    logs = [p for p in files if p.endswith(".h5")]
    assert logs and record["links"]["report"], record
    if run.returncode == 0:  # fitted: every pass of the levelling logged, the Bode plot and the fit beside them
        passes = record["summary"]["ident"]["passes"]
        assert len(logs) == len(passes) >= 1
        assert {"bode-el.png", "ident-el.json"} <= set(files)
        assert json.loads((out / "ident-el.json").read_text())["axis"] == "el"
        report = (out / record["report_path"].split(f"/{record['uid']}/", 1)[1]).read_text()
        assert "Identification" in report and report.count("data:image/png;base64,") >= 4
    else:  # the realtime lab on a loaded machine may leave too little coherence to fit: its logs came back
        assert run.returncode == 1 and record["status"] == "fault", run.stdout[-2000:]


@pytest.mark.slow
def test_campaign_out_brings_back_its_cells_and_its_report(service: Service, tmp_path: Path) -> None:
    campaign = yaml.safe_load((REPO / "profiles/campaigns/static-gyro-noise.yaml").read_text())
    campaign.update(session=str(REPO / "profiles/sessions/swing-1deg-1hz-eso.yaml"), seeds=[1], duration_s=3.0,
                    acceptance=[], profiles=[{"label": "static", "path": str(REPO / "profiles/swing/static.yaml")}])
    file = tmp_path / "one-cell.yaml"
    file.write_text(yaml.safe_dump(campaign))
    out = tmp_path / "campaign-out"
    run = hil("campaign", str(file), "--bench", service.url, "--out", str(out), "--json")
    record = json.loads(run.stdout)
    assert record["kind"] == "campaign" and record["status"] == "completed", run.stderr[-2000:]
    assert sorted(record["files"]) == sorted(str(out / p) for p in local_files(out))
    assert local_files(out) == {path: f["size"] for path, f in listed(service, record["uid"]).items()}
    cells = list((out / "campaign" / "cells").glob("*/*.h5"))
    assert len(cells) == 1 and cells[0].parent.name.startswith("static--")
    assert (out / "campaign" / "campaign.json").is_file() and (out / "campaign" / "report" / "report.html").is_file()
    assert (out / "item" / "session.yaml").is_file()
