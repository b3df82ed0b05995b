#!/usr/bin/env python3
"""Starlette or FastAPI for the service's manager: the same two endpoints on each, measured side by side.

    python benchmarks/bench_http.py [--requests 3000] [--repeat 5] [--json PATH]

Both apps serve ``GET /status`` (a small JSON document, what 50 clients poll at 10 Hz) and ``POST /queue`` (a JSON
body of an item checked against a pydantic model, answered 201, or 422 for a bad one) on uvicorn on localhost,
one at a time, alternating round by round. Measured per framework: the import time of the app module in a fresh
interpreter (the manager's start-up), the modules it loads, and the median request latency and requests/s of
one keep-alive client (http.client). FastAPI also writes the OpenAPI document from the endpoints' types; with
Starlette it would be written by hand. Results and the choice: docs/service.md ("Why FastAPI").
Needs ``pip install fastapi uvicorn`` (Starlette comes with FastAPI).
"""

from __future__ import annotations

import argparse
import http.client
import json
import socket
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from tempfile import TemporaryDirectory

APPS = {
    "starlette": textwrap.dedent("""
        from pydantic import BaseModel, ValidationError
        from starlette.applications import Starlette
        from starlette.requests import Request
        from starlette.responses import JSONResponse
        from starlette.routing import Route

        class Item(BaseModel):
            kind: str
            file_name: str
            body: str

        STATUS = {"boards": {"servo": "connected", "driver": "connected"}, "queue": 3, "running": None}

        async def status(request: Request) -> JSONResponse:
            return JSONResponse(STATUS)

        async def add(request: Request) -> JSONResponse:
            try:
                item = Item.model_validate(await request.json())
            except ValidationError as exc:
                return JSONResponse({"detail": str(exc)}, status_code=422)
            return JSONResponse({"name": item.file_name}, status_code=201)

        app = Starlette(routes=[Route("/status", status), Route("/queue", add, methods=["POST"])])
    """),
    "fastapi": textwrap.dedent("""
        from fastapi import FastAPI
        from pydantic import BaseModel

        class Item(BaseModel):
            kind: str
            file_name: str
            body: str

        STATUS = {"boards": {"servo": "connected", "driver": "connected"}, "queue": 3, "running": None}
        app = FastAPI()

        @app.get("/status")
        async def status() -> dict:
            return STATUS

        @app.post("/queue", status_code=201)
        async def add(item: Item) -> dict:
            return {"name": item.file_name}
    """),
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def import_cost(directory: Path, name: str, repeat: int) -> dict[str, float]:
    """Best-of wall time to import the app module in a fresh interpreter, and the modules it loads."""
    code = (f"import sys, time; t = time.perf_counter(); import app_{name}; "
            "print(time.perf_counter() - t, len(sys.modules))")
    best, modules = float("inf"), 0
    for _ in range(repeat):
        out = subprocess.run([sys.executable, "-c", code], cwd=directory, capture_output=True, text=True, check=True)
        seconds, count = out.stdout.split()
        best, modules = min(best, float(seconds)), int(count)
    return {"import_ms": best * 1000, "modules": modules}


def serve(directory: Path, name: str) -> tuple[subprocess.Popen[bytes], int]:
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", f"app_{name}:app", "--port", str(port),
                             "--log-level", "warning"], cwd=directory)
    give_up = time.monotonic() + 30
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return proc, port
        except OSError:
            if time.monotonic() > give_up:
                proc.kill()
                raise RuntimeError(f"{name}: uvicorn did not start") from None
            time.sleep(0.05)


def requests(port: int, n: int) -> dict[str, float]:
    """``n`` GET /status and ``n // 10`` POST /queue on one keep-alive connection."""
    conn = http.client.HTTPConnection("127.0.0.1", port)
    body = json.dumps({"kind": "session", "file_name": "s.yaml", "body": "name: s\n"})
    lat = []
    t0 = time.perf_counter()
    for _ in range(n):
        t = time.perf_counter()
        conn.request("GET", "/status")
        resp = conn.getresponse()
        resp.read()
        lat.append(time.perf_counter() - t)
        assert resp.status == 200
    wall = time.perf_counter() - t0
    post = []
    for k in range(max(1, n // 10)):
        t = time.perf_counter()
        conn.request("POST", "/queue", body=body if k % 2 else "{}", headers={"Content-Type": "application/json"})
        resp = conn.getresponse()
        resp.read()
        post.append(time.perf_counter() - t)
        assert resp.status == (201 if k % 2 else 422), resp.status
    conn.close()
    return {"get_median_us": statistics.median(lat) * 1e6, "get_per_s": n / wall,
            "post_median_us": statistics.median(post) * 1e6}


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=3000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args(argv)
    rounds: dict[str, list[dict[str, float]]] = {name: [] for name in APPS}
    with TemporaryDirectory() as tmp:
        directory = Path(tmp)
        for name, source in APPS.items():
            (directory / f"app_{name}.py").write_text(source)
        results = {name: import_cost(directory, name, args.repeat) for name in APPS}
        for _ in range(args.repeat):
            for name in APPS:
                proc, port = serve(directory, name)
                try:
                    rounds[name].append(requests(port, args.requests))
                finally:
                    proc.terminate()
                    proc.wait(10)
    for name, rs in rounds.items():
        for key in rs[0]:
            results[name][key] = statistics.median(r[key] for r in rs)
    print(f"{'':10s} {'import ms':>10s} {'modules':>8s} {'GET us':>8s} {'GET/s':>8s} {'POST us':>8s}")
    for name, r in results.items():
        print(f"{name:10s} {r['import_ms']:10.0f} {r['modules']:8.0f} {r['get_median_us']:8.0f} "
              f"{r['get_per_s']:8.0f} {r['post_median_us']:8.0f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
