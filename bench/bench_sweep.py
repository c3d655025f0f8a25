"""Sweep throughput: paper_40 over 100 seeds on a local Dask cluster (one worker per core).

Each Dask task flies a batch of up to sweep.MAX_BATCH seeds side by side
(headless.run_batch; the same results as one run at a time). Two parallel efficiencies:
- against the runs' own wall times: (sum of run wall times) / (workers x sweep wall);
  1.0 means the engine added nothing around the runs (but runs slowed down by sharing
  the cores still count as efficient);
- against serial work: (serial time per run x seeds) / (workers x sweep wall), with the
  serial time per run measured first, in-process and alone on the machine, on a batch of
  the sweep's size. This is the one that answers "how close to ideal is the sweep".
The single-run time (one seed alone, no batch) is reported too.
Per-run time includes each worker's first compile (numba cache load and the agent
kernels), which the first batch on a worker pays.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(seeds: int = 100, workers: int | None = None, config: str = "configs/paper_40.yaml") -> dict:
    import numpy as np

    from sim_bridge.runs.sweep import plan_batches, run_one, run_seeds, run_sweep

    workers = workers or os.cpu_count() or 1
    path = str(ROOT / config)
    run_one(path, 0)  # compile / load caches
    single_s = float(np.mean([run_one(path, s).wall_s for s in (1, 2)]))
    batch = plan_batches(list(range(1, seeds + 1)), workers)[0]
    serial_s = float(np.mean([r.wall_s for r in run_seeds(path, batch)]))
    t0 = time.perf_counter()
    runs = run_sweep(path, list(range(1, seeds + 1)), workers=workers, progress=False)
    wall = time.perf_counter() - t0
    per_run = np.array([r.wall_s for r in runs])
    return {
        "name": "sweep", "config": config, "seeds": seeds, "workers": workers, "wall_s": wall,
        "runs_per_minute": 60.0 * seeds / wall,
        "run_wall_s": {"mean": float(per_run.mean()), "p50": float(np.median(per_run)), "max": float(per_run.max())},
        "parallel_efficiency": float(per_run.sum() / (workers * wall)),
        "batch_size": len(batch),
        "single_run_s": single_s,
        "serial_run_s": serial_s,
        "parallel_efficiency_vs_serial": float(serial_s * seeds / (workers * wall)),
        "ideal_wall_s_from_mean_run": float(per_run.mean() * seeds / workers),
        "passed_every_check": int(sum(r.ok and r.passed for r in runs)),
        "target_met": int(sum(r.target_met for r in runs)),
        "target": "100 seeds of paper_40 in <= 180 s wall, >= 85 % parallel efficiency",
    }
