"""Who may do what (docs/service.md, "Tokens and roles"): beyond localhost only with a token file; viewers read
and watch, operators submit, lease, stop and abort; a WebSocket authenticates by query token or cookie; a token
never appears in a log, a record or an error."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import pytest
import websockets
import websockets.exceptions

from hil.service import BenchError
from tests.factories import short_session
from tests.service.conftest import Service, free_port

REPO = Path(__file__).resolve().parents[2]
OPERATOR = "op-7f3a9c2e5b1d4e8f"
VIEWER = "view-2b8e6d4f1a3c5e7d"


def serve(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", "serve", *args], capture_output=True, text=True,
                          timeout=120, cwd=REPO, check=False)


def test_beyond_localhost_without_a_token_file_the_service_refuses_to_start(tmp_path: Path) -> None:
    run = serve("--loopback", "--host", "0.0.0.0", "--port", str(free_port()), "--state-dir", str(tmp_path))
    assert run.returncode == 2
    assert run.stderr.strip().startswith("error: --host 0.0.0.0: serving beyond this machine needs --token-file")
    assert not (tmp_path / "service.sqlite3").exists()


def test_a_bad_token_file_is_one_line_naming_the_file_and_field_never_the_token(tmp_path: Path) -> None:
    bad = tmp_path / "tokens.yaml"
    bad.write_text("tokens:\n  - {user: ana, role: admin, token: sixteen-chars-ok-123}\n")
    run = serve("--loopback", "--token-file", str(bad), "--port", str(free_port()), "--state-dir", str(tmp_path))
    assert run.returncode == 2 and str(bad) in run.stderr and "tokens.0.role" in run.stderr
    short = tmp_path / "short.yaml"
    short.write_text("tokens:\n  - {user: ana, role: operator, token: tiny-secret}\n")
    run = serve("--loopback", "--token-file", str(short), "--port", str(free_port()), "--state-dir", str(tmp_path))
    assert run.returncode == 2 and "tokens.0.token" in run.stderr and "tiny-secret" not in run.stderr


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    root = tmp_path_factory.mktemp("guarded")
    tokens = root / "tokens.yaml"
    tokens.write_text(f"tokens:\n  - {{user: olga, role: operator, token: {OPERATOR}}}\n"
                      f"  - {{user: vic, role: viewer, token: {VIEWER}}}\n")
    svc = Service(root / "state", args=("--loopback", "--token-file", str(tokens)), token=OPERATOR).start()
    yield svc
    svc.stop()


@pytest.mark.slow
def test_roles_viewers_watch_and_operators_act(guarded: Service, tmp_path: Path) -> None:
    with pytest.raises(BenchError) as err:
        guarded.bench(token="").status()
    assert err.value.status == 401 and "token" in str(err.value)
    with pytest.raises(BenchError) as err:
        guarded.bench(token="not-a-token-of-this-service").status()
    assert err.value.status == 401 and "not-a-token" not in str(err.value)
    viewer = guarded.bench(user="whoever", token=VIEWER)
    assert viewer.status()["you"] == {"user": "vic", "role": "viewer"}  # the token names the user, not the header
    for action in (lambda: viewer.add(short_session(tmp_path, 1.0)), lambda: viewer.lease(60),
                   viewer.stop, viewer.abort):
        with pytest.raises(BenchError) as err:
            action()
        assert err.value.status == 403 and "operator" in str(err.value)
    operator = guarded.bench(user="whoever", token=OPERATOR)
    result = operator.run(short_session(tmp_path, 1.0, name="by-olga"), out=tmp_path)
    assert result.status == "completed"
    assert viewer.history(limit=1)[0]["user"] == "olga"


def test_a_websocket_authenticates_by_header_or_cookie_never_the_url(guarded: Service) -> None:
    async def first_message(url: str, **kw: object) -> dict:
        async with websockets.connect(url, open_timeout=30, **kw) as ws:
            return json.loads(await asyncio.wait_for(ws.recv(), 30))

    base = guarded.url.replace("http", "ws") + "/ws"
    with pytest.raises(websockets.exceptions.ConnectionClosed) as in_url:
        asyncio.run(first_message(f"{base}?token={VIEWER}"))
    assert in_url.value.rcvd is not None and in_url.value.rcvd.code == 4401
    assert "never in the URL" in in_url.value.rcvd.reason
    status = asyncio.run(first_message(base, additional_headers={"Authorization": f"Bearer {VIEWER}"}))
    assert status["type"] == "status" and status["you"]["role"] == "viewer"
    status = asyncio.run(first_message(base, additional_headers={"Cookie": f"hil_token={OPERATOR}"}))
    assert status["you"]["role"] == "operator"
    with pytest.raises(websockets.exceptions.ConnectionClosed) as closed:
        asyncio.run(first_message(base))
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 4401


def test_tokens_are_written_nowhere(guarded: Service, tmp_path: Path) -> None:
    if not any(guarded.state_dir.parent.rglob("*.h5")):  # a session ran, so its log and records are there to read
        ran = guarded.bench(user="whoever", token=OPERATOR).run(short_session(tmp_path, 1.0, name="by-olga"),
                                                                out=tmp_path)
        assert ran.status == "completed", ran.message
    files = [p for p in guarded.state_dir.parent.rglob("*") if p.is_file() and p.name != "tokens.yaml"]
    assert any(p.suffix == ".h5" for p in files) and any(p.name.endswith(".sqlite3") for p in files)
    for path in files:
        data = path.read_bytes()
        assert OPERATOR.encode() not in data and VIEWER.encode() not in data, path
