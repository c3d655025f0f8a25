"""The simulator side, in layers (each imports only those before it; tests/test_layering.py):

    world/     the simulated world: dynamics, physics, wind, estimator, faults, carrier,
               autopilot model, radio model
    scenario   the config root (sim_bridge/scenario.py): loading and feasibility
    reports/   the recorder, typed results, metrics, figures, summaries, launch studies
    sitl/      the MAVLink SITL (it records with reports/)
    runs/      the harnesses: headless runner, sweep, fleet, fuzz, run directories

numba's on-disk cache checks only the source file of the function it compiled, not the
files of the kernels that function calls: after an edit to a controller in
companion/control, the cached physics loop in sim_bridge/world/physics.py would silently keep
the old controller. So the cache lives in a directory named by a hash of every source
file that compiled code can come from; any edit starts a fresh cache. A user's own
NUMBA_CACHE_DIR is respected.
"""
from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path


def _numba_cache_dir() -> Path:
    here = Path(__file__).resolve().parent
    h = hashlib.sha1()
    files = [f for f in sorted(here.rglob("*.py")) if "__pycache__" not in f.parts]
    files += sorted((here.parent / "companion" / "control").glob("*.py"))
    for f in files:
        h.update(str(f.relative_to(here.parent)).encode())
        h.update(f.read_bytes())
    name = f"numba-{h.hexdigest()[:12]}"
    local = here / "__pycache__"
    if os.access(local if local.exists() else here, os.W_OK):
        return local / name
    return Path.home() / ".cache" / "swarmdrop" / name


if "NUMBA_CACHE_DIR" not in os.environ:
    os.environ["NUMBA_CACHE_DIR"] = str(_numba_cache_dir())
    if "numba" in sys.modules:  # imported before us: its config has read the environment already
        sys.modules["numba"].config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
