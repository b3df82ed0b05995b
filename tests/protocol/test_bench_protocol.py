"""Smoke test for benchmarks/bench_protocol.py: it runs, decodes everything, and reports sane figures.

No timing assertions: speed targets live in docs/performance.md, not in tests.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_protocol.py"


def load_bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_protocol", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


def test_bench_protocol_small_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("pymavlink")
    bench = load_bench()
    out_json = tmp_path / "bench.json"

    result = bench.main(["--frames", "2000", "--json", str(out_json)])

    assert result["ok"], result["problems"]
    assert result["problems"] == []
    assert result["frames"] == 2000
    codecs = result["codecs"]
    assert {"hil", "pymavlink"} <= set(codecs)
    assert codecs["hil"]["frame_bytes"] == 39
    assert codecs["pymavlink"]["frame_bytes"] == 40
    for key, r in codecs.items():
        assert r["frames_decoded"] == 2000, key
        for phase in ("encode", "decode"):
            for stat in ("fps_best", "fps_median", "mbps_best", "mbps_median"):
                assert r[phase][stat] > 0, (key, phase, stat)
    for stat in ("best", "median"):
        assert result["targets"][stat]["ratio_vs_pymavlink"] > 0
    assert json.loads(out_json.read_text())["codecs"]["hil"]["frames_decoded"] == 2000
    assert "pymavlink" in capsys.readouterr().out
