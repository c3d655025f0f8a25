"""`make bench`: measure and write JSON figures under bench/results/.

- physics.json: vehicle-steps/s at 1 kHz for N = 40, 400, 4000 (geometric and PID);
- paper_40.json: wall time, real-time factor and CPU of the headless paper_40 run;
- sitl.json: the MAVLink SITL alone at N = 40, 100, 250;
- wire.json: the lean MAVLink codec against pymavlink (µs per message);
- tick.json: the agent's own work per tick (a real AgentNode's tick path fed datagrams by hand:
  a non-plan tick and a plan tick, thread CPU), warm on an idle machine and cold (32 MB of
  memory swept before each tick, as the fleet's other processes do between two ticks of one
  agent: closer to the in-fleet figure, in seconds), to set against the fleet's per-agent
  CPU (bench/bench_tick.py; where each part goes inside a real fleet:
  `python -m bench.agent_parts CONFIG --out DIR`, not part of `make bench`);
- fleet.json: `swarmdrop run` (SITL + one agent process per vehicle) on paper_40 in real
  time, the largest fleet that keeps real time, one agent's start-up time and PSS, and the
  machine's floor under an agent's CPU (a bare asyncio process woken 50 times a second);
- signing.json: paper_40 unsigned and with `--signing`, back to back (the CPU signing costs),
  and µs to sign and check one frame;
- sweep.json: `swarmdrop sweep` on paper_40 over 100 seeds on a local Dask cluster: wall time,
  runs per minute, parallel efficiency;
- console.json: the `swarmdrop console` page with 1,000 synthetic vehicles at 10 Hz, in Debian's
  headless Chromium: frame interval and draw time (p50, p95) read from the page (target p95 <= 50 ms).

`python -m bench.run NAME ...` runs only the named parts.
"""
from __future__ import annotations

import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def _machine() -> dict:
    return {"python": sys.version.split()[0], "platform": platform.platform(), "cpus": os.cpu_count()}


def _write(name: str, data: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    data = {"measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": _machine(), **data}
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=2))
    print(f"wrote {path}")
    return path


def bench_paper_40() -> dict:
    from sim_bridge.runs.headless import run_scenario
    from sim_bridge.scenario import load_scenario

    cfg = load_scenario(Path(__file__).resolve().parents[1] / "configs" / "paper_40.yaml")
    run_scenario(load_scenario_small(cfg), progress=False)  # compile the kernels outside the timing
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    res = run_scenario(cfg, progress=False)
    wall = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    return {
        "wall_s": wall,
        "cpu_s": cpu,
        "sim_s": res.sim_s,
        "real_time_factor": res.sim_s / wall,
        "vehicle_steps": res.vehicle_steps,
        "vehicle_steps_per_s": res.vehicle_steps / wall,
        "mission_completion_s": res.t_complete_s,
    }


def load_scenario_small(cfg):
    import dataclasses

    return dataclasses.replace(cfg, duration_s=2.0)


def main(argv: list[str] | None = None) -> int:
    parts = set(sys.argv[1:] if argv is None else argv) or {"physics", "paper_40", "sitl", "wire", "tick", "fleet", "signing",
                                                            "sweep", "console"}
    if "physics" in parts:
        from bench.bench_physics import run as run_physics

        _write("physics", run_physics())
    if "paper_40" in parts:
        _write("paper_40", bench_paper_40())
    if "sitl" in parts:
        from sim_bridge.sitl.bench import run as run_sitl

        _write("sitl", run_sitl())
    if "wire" in parts:
        from bench.bench_wire import run as run_wire

        _write("wire", run_wire())
    if "tick" in parts:
        from bench.bench_tick import run as run_tick

        _write("tick", run_tick())
    if "fleet" in parts:
        from bench.bench_fleet import run as run_fleet

        _write("fleet", run_fleet())
    if "signing" in parts:
        import tempfile

        from bench.bench_fleet import signing

        with tempfile.TemporaryDirectory(prefix="swarmdrop-bench-") as d:
            _write("signing", {"name": "signing", "description": "paper_40 fleet, unsigned vs --signing",
                               **signing(Path(d))})
    if "sweep" in parts:
        from bench.bench_sweep import run as run_sweep

        _write("sweep", run_sweep())
    if "console" in parts:
        from bench.bench_console import run as run_console

        _write("console", run_console())
    return 0


if __name__ == "__main__":
    sys.exit(main())
