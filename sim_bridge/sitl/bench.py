"""SITL bench: the SITL alone at N vehicles, default stream rates, real-time pacing.

All vehicles are armed and hovering (Hold at MIS_TAKEOFF_ALT) so the physics and
controller run for everyone; telemetry goes to 127.0.0.1 ports nobody listens on.
Reports the real-time factor (sim seconds per wall second; 1.0 = keeps up) and the
CPU share of one core used by the process.
"""
from __future__ import annotations

import asyncio
import dataclasses
import time

from sim_bridge.sitl.config import SitlConfig, sitl_config
from sim_bridge.sitl.server import SitlServer
from sim_bridge.sitl.testing import local_endpoints


async def _measure(server: SitlServer, warmup_s: float, duration_s: float) -> dict:
    stats: dict = {}

    async def probe() -> None:
        await asyncio.sleep(warmup_s)
        sim0, wall0, cpu0 = server.sim_s, time.monotonic(), time.process_time()
        busy0 = server.busy_wall_s
        sent0 = sum(ep.sent for ep in server.endpoints)
        await asyncio.sleep(duration_s)
        wall = time.monotonic() - wall0
        stats.update(
            wall_s=round(wall, 3),
            real_time_factor=round((server.sim_s - sim0) / wall, 3),
            cpu_fraction_of_one_core=round((time.process_time() - cpu0) / wall, 3),
            sim_busy_fraction=round((server.busy_wall_s - busy0) / wall, 3),
            messages_sent_per_s=round((sum(ep.sent for ep in server.endpoints) - sent0) / wall, 1),
            airborne=sum(not ap.landed for ap in server.autopilots),
        )
        server.request_stop()

    await asyncio.gather(server.run(), probe())
    return stats


def bench_one(n: int, duration_s: float = 5.0, warmup_s: float = 4.0) -> dict:
    cfg = sitl_config(n, endpoints=local_endpoints(n))
    server = SitlServer(cfg)
    for ap in server.autopilots:  # arm and take off everyone before the clock starts
        ap.command_arm(1.0, 0.0, 0.0)
        ap.command_takeoff(float("nan"), server.home_alt_amsl_m, 0.0)
    for k in range(n):
        server.after_change(k)
    stats = asyncio.run(_measure(server, warmup_s, duration_s))
    return {"vehicles": n, **stats}


def run(vehicle_counts: tuple[int, ...] = (40, 100, 250), duration_s: float = 5.0) -> dict:
    """Bench figures for the lead's bench/results JSON."""
    cfg = SitlConfig()
    return {
        "name": "sitl",
        "description": "swarmdrop sitl alone, default stream rates, all vehicles hovering, speed 1",
        "tick_s": cfg.time.tick_s,
        "physics_rate_hz": cfg.time.physics_rate_hz,
        "stream_rates_hz": dataclasses.asdict(cfg.streams),
        "results": [bench_one(n, duration_s) for n in vehicle_counts],
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
