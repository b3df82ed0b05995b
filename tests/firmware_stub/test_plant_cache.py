"""The plant's compiled kernel is cached on disk (numba ``cache=True``): a process after the first one loads the
machine code instead of compiling it again (docs/performance.md, "Plant v2" has the times)."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = """
import json, numpy as np
from firmware_stub.plant import DEFAULT_PLANT_CONFIG, CarrierMotion, Plant, kernel, load_plant_config
from firmware_stub.plant._kernel import _SIGNATURES
p = Plant(load_plant_config(DEFAULT_PLANT_CONFIG), 0)
p.step_tick(0, 0, CarrierMotion.at_rest()); p.truth(); p.miss_px()
p.run(np.zeros(3), np.zeros(3), np.zeros((3, 18)))
stats = {name: (disp.stats.cache_hits, disp.stats.cache_misses) for name, (disp, _) in _SIGNATURES.items()}
print(json.dumps({name: [sum(h.values()), sum(m.values())] for name, (h, m) in stats.items()}))
"""


def probe() -> dict[str, list[int]]:
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True, timeout=300)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_second_process_loads_the_kernel_from_the_cache() -> None:
    probe()  # compiles whatever this checkout's cache lacks
    used = {name: hits_misses for name, hits_misses in probe().items() if sum(hits_misses)}
    assert used, "no kernel function was used"
    assert all(misses == 0 and hits >= 1 for hits, misses in used.values()), used
