"""Fleet bench: the MAVLink fleet (`swarmdrop run`) in real time, and one agent's start-up.

* `paper_40`: the whole paper scenario, SITL + 40 agent processes, real time: real-time
  factor, setpoint deadline misses, agent latency (telemetry received to setpoint sent),
  CPU per agent and of the SITL (measured after 10 s of simulated time), PSS, swarm-link
  bytes per vehicle, plus the paper metrics.
* `capacity`: 30 s of the paper scenario at several fleet sizes (every vehicle released
  within the first 22.5 s, assembling at the first waypoint): the largest that still holds a
  real-time factor of 0.99.
* `wakeup_floor_50hz`: a bare asyncio process woken by a UDP datagram 50 times a second,
  which reads it and answers (bench/bench_floor.py): the machine's own cost of an agent's
  control ticks before any of the agent's work, to read its CPU against.
* `agent_startup`: one agent process against a one-vehicle SITL on a quiet machine: time
  from process start to a constructed node (imports, mission, sockets), setup time, PSS.
"""
from __future__ import annotations

import copy
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from companion.config import read_yaml

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper_40.yaml"


def _fleet_figures(report) -> dict:
    """The bench's figures from a FleetReport (JSON-ready)."""
    from dataclasses import asdict

    fl, m = report.fleet, report.metrics
    if m is None:
        raise RuntimeError("the fleet run recorded nothing")
    return {
        "real_time_factor": m.performance.real_time_factor,
        "sim_s": m.performance.sim_s,
        "setpoint_deadline_misses": asdict(fl.setpoint_deadline_misses),
        "agent_latency_ms": asdict(fl.agent_latency_ms),
        "agent_cpu_fraction_of_core": asdict(fl.agent_cpu_fraction_of_core),
        "sitl_cpu_fraction_of_core": fl.sitl_cpu_fraction_of_core,
        "agent_pss_mb": asdict(fl.agent_pss_mb),
        "agent_startup_s_in_fleet": asdict(fl.agent_startup_s),
        "swarm_link_bytes_per_s_per_vehicle": fl.swarm_link_bytes_per_s_per_vehicle,
        "dead_agents": fl.dead_agents,
        "checks": m.checks,
        "final_max_deviation_m": m.formation_deviation.final_max_m,
        "min_separation_m": m.separation.min_pair_distance_m,
        "min_obstacle_clearance_m": m.obstacles.min_clearance_m,
        "mission_completion_s": m.mission.completion_time_s,
    }


def fleet(config: Path, out: Path, **options) -> dict:
    from sim_bridge.runs.fleet import FleetOptions, run_fleet

    report, _ = run_fleet(config, FleetOptions(out_dir=out, progress=False, figures=False, **options))
    return _fleet_figures(report)


def paper_40(tmp: Path) -> dict:
    t0 = time.perf_counter()
    figures = fleet(PAPER, tmp / "paper_40")
    return {"config": "configs/paper_40.yaml", "wall_s": time.perf_counter() - t0, **figures}


def _per_frame_us() -> dict:
    """Signing and checking one SET_POSITION_TARGET_LOCAL_NED frame, µs (CPython, this machine)."""
    import os

    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import common as mavlink

    from companion.link.signing import Signing
    from companion.link.wire import Codec

    codec = Codec(mavlink)
    tx = Signing("require", bytes(32), crc_extra=codec.crc_extra)
    rx = Signing("require", bytes(32), crc_extra=codec.crc_extra)
    frame = codec.encode(mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 0, 0), 2, 191, 0)
    n = 20000
    t0 = time.perf_counter()
    signed = [tx.sign(frame) for _ in range(n)]
    t1 = time.perf_counter()
    ok = sum(rx.check(f) for f in signed)
    t2 = time.perf_counter()
    assert ok == n
    return {"sign_us": (t1 - t0) / n * 1e6, "check_us": (t2 - t1) / n * 1e6, "bytes_added": 13}


def signing(tmp: Path) -> dict:
    """paper_40 in real time unsigned and with `--signing` (required on every link), back to back:
    the same checks must pass, and the difference in agent and SITL CPU is signing's cost."""
    plain = fleet(PAPER, tmp / "plain")
    signed = fleet(PAPER, tmp / "signed", signing=True)
    cpu = lambda r: r["agent_cpu_fraction_of_core"]["mean"]  # noqa: E731
    return {
        "config": "configs/paper_40.yaml", "per_frame": _per_frame_us(),
        "unsigned": plain, "signed": signed,
        "same_checks": plain["checks"] == signed["checks"],
        "agent_cpu_added_fraction_of_core": (cpu(signed) - cpu(plain)) if cpu(signed) and cpu(plain) else None,
        "sitl_cpu_added_fraction_of_core": (signed["sitl_cpu_fraction_of_core"] - plain["sitl_cpu_fraction_of_core"])
        if signed["sitl_cpu_fraction_of_core"] and plain["sitl_cpu_fraction_of_core"] else None,
    }


def capacity(tmp: Path, sizes=(40, 60, 80, 100), sim_s: float = 30.0) -> dict:
    base = read_yaml(PAPER)
    rows = []
    for n in sizes:
        cfg = copy.deepcopy(base)
        cfg["mission"]["n_vehicles"] = n
        cfg["duration_s"] = sim_s
        # Every vehicle released and flying within the window, and no centre path to fly: a run
        # the scenario checks accept as one that can end within sim_s (docs/scenario.md).
        cfg["carrier"]["release_interval_s"] = min(cfg["carrier"].get("release_interval_s", 1.0), 0.75 * sim_s / n)
        cfg["mission"]["waypoints_ned_m"] = cfg["mission"]["waypoints_ned_m"][:1]
        cfg["name"] = f"capacity_{n}"
        path = tmp / f"capacity_{n}.yaml"
        path.write_text(yaml.safe_dump(cfg))
        try:
            f = fleet(path, tmp / f"capacity_{n}")
        except Exception as err:  # e.g. the machine refused so many processes
            rows.append({"vehicles": n, "error": str(err)})
            continue
        rows.append({"vehicles": n, "real_time_factor": f["real_time_factor"],
                     "deadline_miss_fraction": f["setpoint_deadline_misses"]["fraction"],
                     "agent_cpu_mean": f["agent_cpu_fraction_of_core"]["mean"],
                     "sitl_cpu": f["sitl_cpu_fraction_of_core"]})
    ok = [r["vehicles"] for r in rows if (r.get("real_time_factor") or 0) >= 0.99]
    return {"simulated_s_each": sim_s, "runs": rows, "largest_with_rtf_0p99": max(ok) if ok else None}


def agent_startup(tmp: Path) -> dict:
    """One SITL vehicle and one agent, nothing else running."""
    from sim_bridge.sitl.testing import free_udp_base_port

    base = free_udp_base_port(3)
    mission = read_yaml(PAPER)
    mission["mission"]["n_vehicles"] = 1
    cfg = tmp / "one.yaml"
    cfg.write_text(yaml.safe_dump(mission))
    sitl_log = tmp / "sitl.log"
    with open(sitl_log, "w") as log:
        sitl = subprocess.Popen([sys.executable, "-m", "sim_bridge.sitl", "--scenario", str(cfg),
                                 "--remote-base-port", str(base), "--local-base-port", str(base + 1),
                                 "--medium-port", str(base + 2)], stdout=log, stderr=subprocess.STDOUT)
    stats = tmp / "agent.json"
    agent = None
    try:
        # The SITL's own start-up (imports, physics compile) must not overlap the agent's.
        deadline = time.monotonic() + 60
        while "SITL READY" not in sitl_log.read_text():
            if sitl.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the SITL did not start:\n" + sitl_log.read_text()[-2000:])
            time.sleep(0.05)  # polling a condition with a deadline
        agent = subprocess.Popen([sys.executable, "-m", "swarmdrop.cli", "agent", "--vehicle-id", "0",
                                  "--autopilot", f"udpin://127.0.0.1:{base}", "--mission", str(cfg),
                                  "--swarm-peer", f"127.0.0.1:{base + 2}", "--stats", str(stats),
                                  # the SITL's PX4 boots with stock COM_OBL_RC_ACT 0, which the agent refuses
                                  "--set-loss-action", "hold", "--no-stderr-log"])
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (stats.exists() and "setup_s" in stats.read_text()):
            time.sleep(0.2)
        time.sleep(6.0)  # a measurement window, not synchronisation: PSS once the agent has flown a while
        from sim_bridge.runs.procs import pss_mb

        pss = pss_mb(agent.pid)
        s = json.loads(stats.read_text())
        return {"startup_s": s.get("startup_s"), "setup_s": s.get("setup_s"), "pss_mb": pss,
                "note": "startup = process start to a constructed node (imports, mission file, sockets); "
                        "setup = then to flying (streams, clock, EKF origin, parameters)"}
    finally:
        from sim_bridge.runs.procs import terminate_all

        terminate_all((agent, sitl))


def wakeup_floor() -> dict:
    from bench.bench_floor import run as floor

    return floor(rate_hz=50.0)


def run(capacity_sizes=(40, 60, 80, 100)) -> dict:
    with tempfile.TemporaryDirectory(prefix="swarmdrop-bench-") as d:
        tmp = Path(d)
        return {
            "name": "fleet",
            "description": "swarmdrop run: the MAVLink SITL plus one swarmdrop agent process per vehicle, real time",
            "agent_startup": agent_startup(tmp),
            # before the fleet, on the quiet machine: what waking 50 times a second costs here
            "wakeup_floor_50hz": wakeup_floor(),
            "paper_40": paper_40(tmp),
            "capacity": capacity(tmp, capacity_sizes),
        }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
