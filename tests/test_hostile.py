"""Hostile input against the SITL: floods, parameter churn, out-of-range setpoints.

Each test reproduces a defect found by fuzzing (issue 8) and checks the PX4-like answer.
"""
from __future__ import annotations

import math
import os
import socket
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from sim_bridge.sitl.config import SitlConfig  # noqa: E402
from sim_bridge.sitl.params_table import MAV_PARAM_TYPE_REAL32  # noqa: E402
from sim_bridge.sitl.server import BackgroundSitl, SitlServer  # noqa: E402
from sim_bridge.sitl.testing import MavClient, local_endpoints  # noqa: E402

N = 3


@pytest.fixture(scope="module")
def sitl():
    cfg = SitlConfig(vehicles=N, endpoints=local_endpoints(N))
    bg = BackgroundSitl(cfg)
    server = bg.start()
    yield server
    bg.stop()


def client_for(server, k: int) -> MavClient:
    c = MavClient(server.cfg.endpoints.remote_base_port + k)
    assert c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == k + 1, 5.0) is not None
    return c


def _frame(msg, sysid=255, seq=0) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
    mav.seq = seq & 0xFF
    return msg.pack(mav)


def _max_gap_s(client: MavClient, msg_type: str, sysid: int, duration_s: float) -> tuple[float, int]:
    """Largest gap between consecutive msg_type messages of sysid over duration_s (and the count)."""
    t_end = time.monotonic() + duration_s
    last, gap, count = time.monotonic(), 0.0, 0
    while time.monotonic() < t_end:
        m = client.conn.recv_match(type=msg_type, blocking=True, timeout=0.05)
        now = time.monotonic()
        if m is not None and m.get_srcSystem() == sysid:
            gap, last, count = max(gap, now - last), now, count + 1
    return max(gap, time.monotonic() - last), count


def test_param_list_flood_is_paced_and_spares_other_vehicles(sitl):
    """Regression: one 64 KB datagram of PARAM_REQUEST_LIST frames queued ~112,000 replies and
    stalled every vehicle's telemetry for seconds. Now a repeated request restarts the one
    paced listing: the flooder gets the table once, and another vehicle's stream keeps flowing."""
    attacker, victim = 0, 1
    c_att, c_vic = client_for(sitl, attacker), client_for(sitl, victim)
    try:
        frame = _frame(mavlink.MAVLink_param_request_list_message(attacker + 1, 1))
        blob = frame * (65000 // len(frame))
        c_att.drain()
        c_vic.drain()
        # from the client's own socket, so that the replies come back to it
        c_att.conn.port.sendto(blob, ("127.0.0.1", sitl.endpoints[attacker].link.local_port))
        gap_s, count = _max_gap_s(c_vic, "LOCAL_POSITION_NED", victim + 1, 2.0)
        assert count >= 15 and gap_s < 0.5, (gap_s, count)  # a 10 Hz stream keeps flowing
        values = []
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            m = c_att.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.2)
            if m is not None:
                values.append(m.param_index)
        n_params = len(sitl.params[attacker])
        assert sorted(set(values)) == list(range(n_params))
        assert len(values) <= 2 * n_params, f"{len(values)} PARAM_VALUEs for a {n_params}-entry table"
    finally:
        c_att.close()
        c_vic.close()


class _Sink:
    """Stands in for an endpoint: keeps what the router queues."""

    def __init__(self):
        self.out = []

    def queue(self, msg, addr=None, sysid=None, compid=None):
        self.out.append(msg)


def test_parameter_churn_keeps_one_physics_group_per_gain_set():
    """Regression: every distinct controller gain set created a physics group that was never
    freed; a few hundred PARAM_SETs left the SITL at 0.66x real time for good."""
    server = SitlServer(SitlConfig(vehicles=N, endpoints=local_endpoints(N)))
    sink = _Sink()
    for i in range(300):
        msg = mavlink.MAVLink_param_set_message(1, 1, b"SD_GEO_KX", 10.0 + 0.01 * i, MAV_PARAM_TYPE_REAL32)
        server.router.handle(sink, msg, None, 0)
    assert len(sink.out) == 300  # every set is echoed
    assert math.isclose(server.params[0]["SD_GEO_KX"], 12.99, rel_tol=1e-6)
    assert len(server._physics) == 2 and len(server._group_keys) == 2  # vehicle 0's gains, the others'
    assert server._group.tolist() == [1, 0, 0] or server._group.tolist() == [0, 1, 1]
    # back to the others' value: one group again
    default = server.params[1]["SD_GEO_KX"]
    server.router.handle(sink, mavlink.MAVLink_param_set_message(1, 1, b"SD_GEO_KX", default,
                                                                 MAV_PARAM_TYPE_REAL32), None, 0)
    assert len(server._physics) == 1 and np.all(server._group == 0)
