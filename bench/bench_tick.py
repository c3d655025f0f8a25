"""The agent's own work per tick, warm, on an idle machine: a real `AgentNode` (paper_40's
vehicle 7, PX4 dialect, acceleration output) whose `TickPath.on_autopilot` is called by hand
after each LOCAL_POSITION_NED + ATTITUDE_QUATERNION datagram (one datagram, as the SITL
packs a tick) and, every 5th tick, the radio's batch of the 39 other vehicles' states.

Measured in the calling thread's CPU clock: a non-plan tick (read the autopilot, build and
send the setpoint) and a plan tick (the same, then read the neighbours, Agent.step, publish).
Set against the fleet bench's per-agent CPU this separates the agent's own work from what
the machine adds on each wake-up (docs: README "Performance"). No SITL, no event loop
waiting: the datagrams are on the socket before each call.

Measured twice: warm (the tick path alone, its code and data in the caches), and cold: before
each tick the bench sweeps COLD_EVICT_MB of memory, as the SITL and 39 other agents do between
two ticks of one agent in the fleet, so the tick starts with its code and data evicted from
the core's caches. The cold figure comes closer to the in-fleet one than the warm figure does,
in seconds instead of a 4-minute fleet run and without 40 processes and a SITL sharing 2
cores. Like the fleet's, it moves with the machine's state (1.16-1.43 % of a core at 50 Hz
in one session here, against 1.84-2.17 % per agent in that session's fleet runs).
"""
from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path

import numpy as np

from companion.link.dialects import Mode, dialect_named
from companion.link.endpoints import MavEndpoint, UdpLink
from companion.link.enums import MavAutopilot, MavLandedState, MavModeFlag, MavState, MavType, MsgId
from companion.link.msgdef import swarmdrop as md
from companion.link.wire import Codec
from companion.node.config import NodeConfig, load_mission_file
from companion.node.runner import AgentNode

ROOT = Path(__file__).resolve().parents[1]
VEHICLE = 7
EPOCH_US = 1_767_225_600_000_000
COLD_EVICT_MB = 32
"""Memory swept between two cold ticks, MB: more than a core's L2 (2 MB here), as the fleet's
other processes touch between two ticks of one agent."""


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _measure(ticks: int, evict_mb: int = 0) -> dict:
    """The tick path's thread CPU over `ticks` ticks; with evict_mb > 0, that much memory is
    swept before each tick (outside the measured call)."""
    sweep = np.ones(evict_mb * (1 << 20) // 8) if evict_mb > 0 else None
    ap_port, sw_port, radio_port = _free_port(), _free_port(), _free_port()
    mf = load_mission_file(ROOT / "configs" / "paper_40.yaml")
    node = AgentNode(NodeConfig(vehicle_id=VEHICLE, autopilot_url=f"udpin://127.0.0.1:{ap_port}", mission=mf,
                                swarm_bind=("127.0.0.1", sw_port), swarm_peers=[("127.0.0.1", radio_port)]))
    codec = Codec(md)
    ap = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=("127.0.0.1", ap_port), learn_remote=False), codec,
                     VEHICLE + 1, 1)
    radio = MavEndpoint(UdpLink(bind=("127.0.0.1", radio_port), remote=None, learn_remote=False), codec, 250, 191)
    lpn, att = codec.builder(MsgId.LOCAL_POSITION_NED), codec.builder(MsgId.ATTITUDE_QUATERNION)
    hb, ess, st = codec.builder(MsgId.HEARTBEAT), codec.builder(MsgId.EXTENDED_SYS_STATE), \
        codec.builder(MsgId.SWARMDROP_STATE)
    heartbeat = hb(type=int(MavType.MAV_TYPE_QUADROTOR), autopilot=int(MavAutopilot.MAV_AUTOPILOT_PX4),
                   base_mode=int(MavModeFlag.MAV_MODE_FLAG_SAFETY_ARMED | MavModeFlag.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                   custom_mode=dialect_named("px4").custom_mode(Mode.OFFBOARD),
                   system_status=int(MavState.MAV_STATE_ACTIVE), mavlink_version=3)
    m = node.mission
    slot = m.offsets_ned_m + np.asarray(m.cfg.waypoints_ned_m[0])
    try:
        # What set-up would have learnt: the autopilot (HEARTBEAT, in the air), its clock, the epoch.
        ap.queue_fields(MsgId.EXTENDED_SYS_STATE, ess(vtol_state=0,
                                                      landed_state=int(MavLandedState.MAV_LANDED_STATE_IN_AIR)))
        ap.queue_fields(MsgId.HEARTBEAT, heartbeat)
        ap.flush()
        await asyncio.sleep(0.01)
        node.tick.on_autopilot()
        node.vehicle.unix_offset_us = EPOCH_US
        node.swarm.set_epoch(EPOCH_US * 1e-6)
        node.tick.attach(EPOCH_US, 0.5, None)
        plan_us: list[float] = []
        tick_us: list[float] = []
        for k in range(1, ticks + 1):
            t_ms = 100_000 + 20 * k
            p = slot[VEHICLE]
            ap.queue_fields(MsgId.LOCAL_POSITION_NED, lpn(time_boot_ms=t_ms, x=float(p[0]) + 0.01, y=float(p[1]),
                                                          z=float(p[2]), vx=0.0, vy=0.0, vz=0.0))
            ap.queue_fields(MsgId.ATTITUDE_QUATERNION, att(time_boot_ms=t_ms, q1=1.0, q2=0.0, q3=0.0, q4=0.0,
                                                           rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0,
                                                           repr_offset_q=[0.0] * 4))
            if k % 50 == 0:
                ap.queue_fields(MsgId.HEARTBEAT, heartbeat)
            ap.flush()
            if k % 5 == 0:  # the radio's batch: the 39 others, stamped now
                for j in range(m.n):
                    if j != VEHICLE:
                        q = slot[j]
                        radio.queue_fields(MsgId.SWARMDROP_STATE, st(
                            time_usec=EPOCH_US + t_ms * 1000, t_go_usec=0, x=float(q[0]), y=float(q[1]),
                            z=float(q[2]), vx=0.0, vy=0.0, vz=0.0, q=[1.0, 0.0, 0.0, 0.0], phase=2, flags=7,
                            vehicle_id=j, plan_seq=0), ("127.0.0.1", sw_port), sysid=j + 1)
                radio.flush()
            time.sleep(0.0005)  # (the datagrams' way through the loopback: the agent reads what is there)
            if sweep is not None:  # read and write every cache line: the tick's code and data leave the caches
                sweep[::8] += 1.0
            plans_before = node.tick.counters.step.n  # (one count per Agent.step)
            t0 = time.thread_time_ns()
            node.tick.on_autopilot()
            dt_us = (time.thread_time_ns() - t0) / 1e3
            (plan_us if node.tick.counters.step.n != plans_before else tick_us).append(dt_us)
            ap.link.recv()  # what the agent sent: read and dropped
            radio.link.recv()
        c = node.tick.counters
        if c.setpoints_sent < ticks // 2:
            raise RuntimeError(f"the agent sent {c.setpoints_sent} setpoints in {ticks} ticks: not flying")
    finally:
        for ep in (ap, radio, node.ap_ep, node.sw_ep):
            ep.close()
    tick, plan = np.array(tick_us[50:]), np.array(plan_us[10:])  # (warm: the first second left out)
    per_s = 50.0 * float(tick.sum() + plan.sum()) / (len(tick) + len(plan))  # µs of CPU a second at 50 Hz
    return {
        "vehicle": VEHICLE, "phase": node.tick.phase.name, "neighbours": m.n - 1,
        "tick_us": {"median": float(np.median(tick)), "mean": float(np.mean(tick)), "n": len(tick)},
        "plan_tick_us": {"median": float(np.median(plan)), "mean": float(np.mean(plan)), "n": len(plan)},
        "cpu_fraction_of_core_at_50hz": per_s / 1e6,
        "note": "thread CPU of TickPath.on_autopilot, warm, idle machine: the agent's own work without the "
                "wake-up (no event loop waiting) and without a busy machine's cold caches",
    }


def run(ticks: int = 3000) -> dict:
    """Fly `ticks` ticks (60 s of 50 Hz) through one AgentNode, warm and then cold; see the
    module docstring."""
    warm = asyncio.run(_measure(ticks))
    cold = asyncio.run(_measure(ticks, COLD_EVICT_MB))
    cold["note"] = (f"the same, with {COLD_EVICT_MB} MB of memory swept before each tick (outside the measured call): "
                    "the tick starts with cold caches, as in a fleet of 40 agents and a SITL on 2 cores")
    return {"name": "tick", "description": "swarmdrop agent's tick path warm on an idle machine, and cold "
                                           "(paper_40 vehicle 7, 39 neighbours)", **warm, "cold": cold}


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))
