"""A third autopilot from two new files (issue 17): a toy dialect for the companion and a
toy behaviour for the SITL (tests/toy_autopilot/), registered by being imported, and the
unmodified agent flies it through the SITL: HEARTBEAT picks the dialect, the agent reads
the toy's own parameters, arms, takes off with the toy's command, switches to its
offboard mode and flies to its slot."""
from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.link.dialects import DIALECTS, Mode, dialect_for_autopilot
from companion.mission import GeodeticOrigin, formation_offsets_ned_m
from companion.node.config import NodeConfig, load_mission_file
from companion.node.runner import AgentNode, ExitCode
from sim_bridge.sitl.autopilots import AUTOPILOTS
from sim_bridge.sitl.background import BackgroundSitl
from sim_bridge.sitl.config import EndpointConfig, MediumConfig, SitlConfig, TimeConfig, sitl_config
from sim_bridge.sitl.testing import free_udp_base_port
from tests.toy_autopilot import dialect as toy_dialect
from tests.toy_autopilot import sitl as toy_sitl

ORIGIN = {"lat_deg": 47.397742, "lon_deg": 8.545594, "alt_amsl_m": 488.0}
EPOCH_UNIX_S = 1767225600.0


def test_two_files_register_a_third_autopilot_on_both_sides():
    assert isinstance(DIALECTS["toy"], toy_dialect.Toy)
    assert isinstance(AUTOPILOTS["toy"], toy_sitl.ToyBehaviour)
    assert dialect_for_autopilot(int(toy_dialect.Toy.autopilot_id)).name == "toy"
    assert {"px4", "ardupilot", "toy"} <= set(AUTOPILOTS) <= set(DIALECTS)
    cfg = SitlConfig(dialect="toy")  # the SITL's config takes it by name
    assert cfg.dialect == "toy"


@pytest.mark.timeout(120)
def test_the_unmodified_agent_flies_the_toy_autopilot_through_the_sitl(tmp_path: Path):
    mission = {"name": "toy_1", "seed": 3, "mission": {
        "n_vehicles": 1, "formation": {"radius_m": 2.0}, "waypoints_ned_m": [[3.0, 1.0, -4.0]],
        "launch": "ground", "takeoff_alt_m": 2.5, "origin": ORIGIN}}
    path = tmp_path / "toy_1.yaml"
    path.write_text(yaml.safe_dump(mission))
    mf = load_mission_file(path)
    slot = formation_offsets_ned_m(mf.mission.formation, 1)[0] + np.array(mf.mission.waypoints_ned_m[-1])
    base = free_udp_base_port(3)
    ap_port, swarm_port, radio_port = base, base + 1, base + 2
    sitl_cfg = sitl_config(
        1, seed=3, launch="ground", origin=GeodeticOrigin(**ORIGIN), dialect="toy",
        endpoints=EndpointConfig(remote_host="127.0.0.1", remote_base_port=ap_port, bind_host="127.0.0.1",
                                 local_base_port=0),
        time=TimeConfig(lockstep=True, epoch_unix_s=EPOCH_UNIX_S),
        medium=MediumConfig(enabled=True, port=radio_port, agent_base_port=swarm_port))
    node_cfg = NodeConfig(vehicle_id=0, autopilot_url=f"udpin://127.0.0.1:{ap_port}", mission=mf,
                          swarm_bind=("127.0.0.1", swarm_port), swarm_peers=[("127.0.0.1", radio_port)],
                          launch="ground", takeoff_alt_m=2.5, lockstep=True, setup_timeout_s=20.0)
    bg = BackgroundSitl(sitl_cfg)
    server = bg.start()
    modes_seen: set[Mode] = set()
    try:
        ap = server.autopilots[0]
        assert ap.params.index_of("TOY_SP_TIMEOUT") is not None and ap.params.index_of("COM_OF_LOSS_T") is None
        node = AgentNode(node_cfg)

        async def fly() -> ExitCode:
            run = asyncio.ensure_future(node.run(handle_signals=False))
            deadline = time.monotonic() + 90.0
            while time.monotonic() < deadline and not run.done():
                modes_seen.add(ap.mode)
                p, v = server.state.pos_ned_m[0].copy(), server.state.vel_ned_mps[0].copy()
                if np.linalg.norm(p - slot) < 0.05 and np.linalg.norm(v) < 0.05:
                    break
                await asyncio.sleep(0.05)  # polling the simulated vehicle with a deadline
            node.request_stop()
            return await asyncio.wait_for(run, 15.0)

        code = asyncio.run(fly())
        p = server.state.pos_ned_m[0]
        assert code == ExitCode.OK
        assert node.vehicle.dialect is not None and node.vehicle.dialect.name == "toy"
        assert math.dist(p, slot) < 0.05, (p, slot)
        assert {Mode.TAKEOFF, Mode.OFFBOARD} <= modes_seen and ap.mode == Mode.OFFBOARD and ap.armed
    finally:
        bg.stop()
