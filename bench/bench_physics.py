"""Throughput of the fused physics stepper (vehicle-steps per second at 1 kHz).

``run()`` returns a dict; the caller decides where to write it. Single-threaded numba.
"""
from __future__ import annotations

import os
import platform
import time

import numpy as np

from companion.params import InnerLoopConfig, VehicleParams
from companion.state import FleetSetpoint
from sim_bridge.world.physics import Physics, hover_state

FLEET_SIZES = (40, 400, 4000)
CONTROLLERS = ("geometric", "pid")
VEHICLE_STEPS_PER_CASE = 4_000_000


def _case(controller: str, n: int, dt_s: float, vehicle_steps: int) -> dict:
    vp = VehicleParams()
    phys = Physics(vp, InnerLoopConfig(controller=controller), dt_s=dt_s)
    rng = np.random.default_rng(0)
    st = hover_state(n, vp, pos_ned_m=rng.uniform(-5, 5, (n, 3)))
    st.vel_ned_mps[:] = rng.normal(0, 1, (n, 3))
    sp = FleetSetpoint.empty(n)
    sp.pos_ned_m[:] = 0.0  # every vehicle flies a real transient, not a trivial hover
    sp.yaw_rad[:] = 0.5
    n_steps = max(1, vehicle_steps // n)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    phys.step(st, sp, n_steps=n_steps)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return {"controller": controller, "n_vehicles": n, "n_steps": n_steps, "wall_s": wall, "cpu_s": cpu,
            "vehicle_steps_per_s": n * n_steps / wall, "sim_time_s": n_steps * dt_s,
            "finite": bool(np.all(np.isfinite(st.pos_ned_m)))}


def run(vehicle_steps: int = VEHICLE_STEPS_PER_CASE, dt_s: float = 0.001) -> dict:
    """Measure vehicle-steps/s for N in FLEET_SIZES x CONTROLLERS after a warm-up call.

    Returns:
        dict with "compile_s" (first call per controller, includes numba cache load or
        JIT compile), "cases" (list of per-case dicts), "process_cpu_s" and host info.
    """
    cpu_start = time.process_time()
    compile_s = {}
    for ctrl in CONTROLLERS:  # warm-up: JIT compile (or cache load) outside the timing
        t0 = time.perf_counter()
        _case(ctrl, 1, dt_s, 1)
        compile_s[ctrl] = time.perf_counter() - t0
    cases = [_case(ctrl, n, dt_s, vehicle_steps) for ctrl in CONTROLLERS for n in FLEET_SIZES]
    return {
        "benchmark": "physics_step",
        "physics_rate_hz": 1.0 / dt_s,
        "compile_s": compile_s,
        "cases": cases,
        "process_cpu_s": time.process_time() - cpu_start,
        "host": {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count()},
        "target_vehicle_steps_per_s_at_n40_geometric": 1_000_000,
    }


if __name__ == "__main__":  # pragma: no cover - convenience only, no file output
    for c in run()["cases"]:
        print(f"{c['controller']:>9} N={c['n_vehicles']:>5}: {c['vehicle_steps_per_s'] / 1e6:6.2f} M vehicle-steps/s")
