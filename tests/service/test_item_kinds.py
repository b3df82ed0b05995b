"""The other kinds of item, from the command line: `hil ident --bench` (the swept sine on the service's lab, the
fit in the record) and `hil campaign --bench` (one item, its cells run by the service, its report linked)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from hil.service import BenchError
from tests.factories import short_session
from tests.service.conftest import Service

REPO = Path(__file__).resolve().parents[2]


def hil(*args: str, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=REPO, check=False)


@pytest.mark.slow
def test_ident_on_the_bench_fits_the_plant_and_brings_the_log_back(service: Service, tmp_path: Path) -> None:
    run = hil("ident", str(short_session(tmp_path)), "--bench", service.url, "--axis", "el", "--sweep-s", "10",
              "--f-start-hz", "2", "--f-stop-hz", "40", "--amplitude-dps", "4", "--offset-dps", "5", "--no-level",
              "--out", str(tmp_path / "ident"), "--json")
    assert list((tmp_path / "ident").glob("*.h5")), run.stderr  # the log came back, whatever the fit made of it
    if run.returncode == 0:
        fit = json.loads(run.stdout)
        assert fit["axis"] == "el" and 0.005 < fit["k_m_dps2_per_count"] < 0.1  # the emulated plant's k_m: 0.023
        return
    # The service's lab runs on the realtime clock: on a loaded machine the host's stalls can leave too little
    # coherence to fit (seen beside two CPU hogs). The bench must then say so, exit 1, and the log it kept must
    # show the stalls; a quiet loop that cannot be identified fails here.
    record = json.loads(run.stdout)  # hil run's JSON record: the log's summary at its top level
    assert run.returncode == 1 and record["status"] == "fault", run.stdout[-2000:]
    assert "cannot identify" in record["message"] and ".h5" in record["message"], record["message"]
    assert record["host_stalls"] > 0 or record["late_cycles"] > 0, run.stdout[-3000:]


@pytest.mark.slow
def test_a_campaign_runs_as_one_item_and_links_its_report(service: Service, tmp_path: Path) -> None:
    run = hil("campaign", str(REPO / "profiles/campaigns/static-gyro-noise.yaml"), "--bench", service.url, "--json")
    record = json.loads(run.stdout)
    assert record["kind"] == "campaign" and record["status"] == "completed", record
    assert run.returncode == record["exit_code"] == (0 if record["summary"]["passed"] else 1)
    assert len(record["summary"]["cells"]) == 3
    assert record["report_path"].endswith("report.html")
    html = service.bench().download(record["links"]["report"], tmp_path / "report.html").read_text()
    assert "static-gyro-noise" in html or "Static gyro noise" in html
    assert html.count("data:image/png;base64,") >= 1  # one file: its plots inside


def test_a_campaign_that_leans_on_files_it_does_not_carry_is_refused_naming_the_field(service: Service) -> None:
    text = (REPO / "profiles/campaigns/static-gyro-noise.yaml").read_text()
    with pytest.raises(BenchError) as err:  # as written: its session is relative to a folder the item does not carry
        service.bench().call("POST", "/api/queue/items", {"kind": "campaign", "file_name": "c.yaml", "body": text})
    assert err.value.status == 422 and str(err.value).startswith("c.yaml: session: names ../sessions/"), err.value
    campaign = yaml.safe_load(text)
    campaign["session"] = str(REPO / "profiles/sessions/swing-1deg-1hz-eso.yaml")  # a file on the service's disk
    with pytest.raises(BenchError) as err:
        service.bench().call("POST", "/api/queue/items", {"kind": "campaign", "file_name": "c.yaml",
                                                          "body": yaml.safe_dump(campaign)})
    assert err.value.status == 422 and "outside the submitted item" in str(err.value), err.value


@pytest.mark.slow
def test_a_campaign_carries_its_own_files_and_runs_when_the_client_s_are_gone(service: Service,
                                                                              tmp_path: Path) -> None:
    campaign = yaml.safe_load((REPO / "profiles/campaigns/static-gyro-noise.yaml").read_text())
    for name in ("sessions/swing-1deg-1hz-eso.yaml", "swing/static.yaml"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / "profiles" / name, tmp_path / name)
    session = yaml.safe_load((tmp_path / "sessions/swing-1deg-1hz-eso.yaml").read_text())
    for key in ("controller", "profile", "hexapod_limits"):
        session[key] = str((REPO / "profiles/sessions" / session[key]).resolve())
    (tmp_path / "sessions/swing-1deg-1hz-eso.yaml").write_text(yaml.safe_dump(session))
    campaign.update(session="sessions/swing-1deg-1hz-eso.yaml", seeds=[1], duration_s=3.0, acceptance=[],
                    profiles=[{"label": "static", "path": "swing/static.yaml"}])
    file = tmp_path / "own-files.yaml"
    file.write_text(yaml.safe_dump(campaign))
    bench = service.bench()
    bench.stop_queue()
    try:
        item = bench.add(file, kind="campaign")  # its session and profile go with it ...
        shutil.rmtree(tmp_path / "sessions")  # ... so the client's copies may go before its turn comes
        shutil.rmtree(tmp_path / "swing")
    finally:
        bench.start()
    assert item["files"] == ["profiles/static.yaml", "session.yaml"]
    record = bench.wait(item["uid"])
    assert record["status"] == "completed" and len(record["summary"]["cells"]) == 1, record
