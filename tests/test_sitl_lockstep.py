"""Lockstep: sim time waits for every Offboard vehicle's setpoint; same seed -> same trajectory."""
from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from sim_bridge.sitl.background import BackgroundSitl  # noqa: E402
from sim_bridge.sitl.config import (
    TimeConfig,  # noqa: E402
    sitl_config,  # noqa: E402
)
from sim_bridge.sitl.testing import MavClient, local_endpoints  # noqa: E402

N = 2
STEPS = 120
VEL_MASK = 2503  # velocity + yaw
ACC_MASK = 3135  # acceleration only


def _setpoint(c: MavClient, k: int, i: int) -> None:
    if k == 0:
        c.mav.set_position_target_local_ned_send(0, 1, 1, 1, VEL_MASK, 0, 0, 0, 0.5 * math.sin(i / 10), 0.3, -1.0,
                                                 0, 0, 0, 0.2, 0)
    else:
        c.mav.set_position_target_local_ned_send(0, 2, 1, 1, ACC_MASK, 0, 0, 0, 0, 0, 0,
                                                 0.5, -0.2 * math.cos(i / 7), -0.8, 0, 0)


def _fly(seed: int) -> tuple[np.ndarray, list[int]]:
    cfg = sitl_config(N, seed=seed, endpoints=local_endpoints(N), time=TimeConfig(lockstep=True))
    bg = BackgroundSitl(cfg)
    server = bg.start()
    clients = []
    try:
        for k in range(N):
            c = MavClient(cfg.endpoints.remote_base_port + k)
            assert c.wait("HEARTBEAT", timeout_s=5) is not None
            clients.append(c)
        for k, c in enumerate(clients):  # Offboard while disarmed: a vehicle at rest is not stepped
            assert c.command(k + 1, 511, 32, cfg.time.tick_s * 1e6).result == mavlink.MAV_RESULT_ACCEPTED
            _setpoint(c, k, 0)
            assert c.command(k + 1, 176, 1, 6, 0).result == mavlink.MAV_RESULT_ACCEPTED
        # the clock stalls: both vehicles are in Offboard and nobody sent a setpoint since the last tick
        deadline = time.monotonic() + 3
        while not server.lockstep_waiting() and time.monotonic() < deadline:
            clients[0].wait("HEARTBEAT", timeout_s=0.05)  # bounded poll of the server's condition
        assert server.lockstep_waiting()
        for k, c in enumerate(clients):  # arm while the clock stands still
            assert c.command(k + 1, 400, 1).result == mavlink.MAV_RESULT_ACCEPTED
        t_stalled = server.sim_s
        t0_ms = round(t_stalled * 1000)
        assert clients[0].wait("LOCAL_POSITION_NED", lambda m: m.time_boot_ms > t0_ms, 0.3) is None
        assert server.sim_s == t_stalled
        assert clients[0].wait("HEARTBEAT", timeout_s=2) is not None  # heartbeats stay on wall clock
        last = [t0_ms] * N
        traj = np.zeros((STEPS, N, 6))
        times = []
        for i in range(STEPS):
            for k, c in enumerate(clients):
                _setpoint(c, k, i)
            for k, c in enumerate(clients):
                m = c.wait("LOCAL_POSITION_NED", lambda m, k=k: m.time_boot_ms > last[k], 3)
                assert m is not None, f"step {i} vehicle {k}: no telemetry"
                last[k] = m.time_boot_ms
                traj[i, k] = (m.x, m.y, m.z, m.vx, m.vy, m.vz)
            times.append(last[0] - t0_ms)
        return traj, times
    finally:
        for c in clients:
            c.close()
        bg.stop()


@pytest.mark.timeout(60)
def test_lockstep_is_deterministic_and_gated():
    a, ta = _fly(seed=7)
    b, tb = _fly(seed=7)
    # one tick per setpoint round, and identical trajectories
    assert ta == tb == [10 * (i + 1) for i in range(STEPS)]
    assert np.array_equal(a, b)
    assert a[-1, 0, 2] < -0.5 and a[-1, 1, 0] - a[0, 1, 0] > 0.05  # they really flew
