"""Hostile input against the SITL: floods, parameter churn, out-of-range setpoints.

Each test reproduces a defect found by fuzzing (issue 8) and checks the PX4-like answer.
"""
from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.config import replace  # noqa: E402
from sim_bridge.sitl.config import default_scenario, sitl_config  # noqa: E402
from sim_bridge.sitl.params_table import MAV_PARAM_TYPE_REAL32  # noqa: E402
from sim_bridge.sitl.server import SitlServer  # noqa: E402
from sim_bridge.sitl.testing import MavClient, local_endpoints, pack_frame, running_sitl, vehicle_client  # noqa: E402

N = 3


@pytest.fixture(scope="module")
def sitl():
    with running_sitl(N) as server:
        yield server


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
    c_att, c_vic = vehicle_client(sitl, attacker), vehicle_client(sitl, victim)
    try:
        frame = pack_frame(mavlink.MAVLink_param_request_list_message(attacker + 1, 1))
        blob = frame * (65000 // len(frame))
        c_att.drain()
        c_vic.drain()
        # from the client's own socket, so that the replies come back to it
        c_att.conn.port.sendto(blob, ("127.0.0.1", sitl.endpoints[attacker].link.local_port))
        gap_s, count = _max_gap_s(c_vic, "LOCAL_POSITION_NED", victim + 1, 2.0)
        assert count >= 10 and gap_s < 1.0, (gap_s, count)  # a 10 Hz stream keeps flowing (the flood stalled it for seconds)
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

    def queue_fields(self, msgid, values, addr=None, sysid=None, compid=None):
        self.out.append((msgid, values))


def test_parameter_churn_keeps_one_physics_group_per_gain_set():
    """Regression: every distinct controller gain set created a physics group that was never
    freed; a few hundred PARAM_SETs left the SITL at 0.66x real time for good."""
    server = SitlServer(sitl_config(N, endpoints=local_endpoints(N)))
    sink = _Sink()
    for i in range(300):
        msg = mavlink.MAVLink_param_set_message(1, 1, b"SD_GEO_KR", 10.0 + 0.01 * i, MAV_PARAM_TYPE_REAL32)
        server.router.handle(sink, msg, None, 0)
    assert len(sink.out) == 300  # every set is echoed
    assert math.isclose(server.params[0]["SD_GEO_KR"], 12.99, rel_tol=1e-6)
    assert len(server.fleet.physics_groups) == 2 and len(server.fleet.group_keys) == 2  # vehicle 0's gains, the others'
    assert server.fleet.group.tolist() == [1, 0, 0] or server.fleet.group.tolist() == [0, 1, 1]
    # back to the others' value: one group again
    default = server.params[1]["SD_GEO_KR"]
    server.router.handle(sink, mavlink.MAVLink_param_set_message(1, 1, b"SD_GEO_KR", default,
                                                                 MAV_PARAM_TYPE_REAL32), None, 0)
    assert len(server.fleet.physics_groups) == 1 and np.all(server.fleet.group == 0)


# ---------------------------------------------------------------------------- setpoint hygiene
def _hovering_offboard(server: SitlServer, k: int = 0):
    """Vehicle k armed, taken off, and in Offboard holding a zero-velocity setpoint."""
    ap = server.autopilots[k]
    assert ap.command_arm(1, math.nan, server.sim_s) == 0
    assert ap.command_takeoff(math.nan, server.home_alt_amsl_m, server.sim_s) == 0
    server.after_change(k)
    for _ in range(int(6.0 / server.tick_s)):
        server.step_once()
        if ap.mode.name == "HOLD":
            break
    _send(server, k, _vel_target((0.0, 0.0, 0.0)))
    assert ap.command_set_mode(1, 6, 0, server.sim_s) == 0
    server.after_change(k)
    return ap


def _send(server: SitlServer, k: int, msg) -> None:
    server.router.handle(_Sink(), msg, None, k)


def _vel_target(v, x=0.0, y=0.0, z=0.0, mask=0b110111000111):  # velocity only
    return mavlink.MAVLink_set_position_target_local_ned_message(0, k_sys(), 1, 1, mask, x, y, z, *v, 0, 0, 0, 0, 0)


def k_sys() -> int:
    return 1


def _fly(server: SitlServer, seconds: float) -> float:
    """Step the SITL; the largest horizontal and vertical speed of vehicle 0 seen."""
    top = 0.0
    for _ in range(int(seconds / server.tick_s)):
        server.step_once()
        top = max(top, float(np.hypot(*server.state.vel_ned_mps[0, :2])))
    return top


def test_nan_thrust_is_rejected_not_flown_as_zero():
    """Regression: NaN or infinite thrust in SET_ATTITUDE_TARGET was taken as 0 thrust."""
    s = SitlServer(sitl_config(1))
    ap = _hovering_offboard(s)
    z0 = s.state.pos_ned_m[0, 2]
    for thrust in (math.nan, math.inf):
        _send(s, 0, mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 0, [1, 0, 0, 0], 0, 0, 0, thrust))
        assert "thrust not finite" in s.router._last_reject[0]
    _fly(s, 0.5)
    assert s.state.pos_ned_m[0, 2] - z0 < 0.1, "it fell: the bad thrust was flown (down is +z)"
    assert ap.offb.sp.vel_ned_mps == pytest.approx([0, 0, 0])  # still the last valid setpoint


def test_body_and_yaw_rates_are_clamped():
    """Regression: body rates of 1e30 rad/s were accepted unclamped and tumbled the vehicle."""
    s = SitlServer(sitl_config(1))
    ap = _hovering_offboard(s)
    _send(s, 0, mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 128, [1, 0, 0, 0], 1e30, -1e30, 1e30, 0.5))
    lim = ap.knobs.limits()
    assert ap.offb.sp.body_rate_radps == pytest.approx([lim.roll_rate_max_radps, -lim.pitch_rate_max_radps,
                                                      lim.yaw_rate_max_radps])
    _send(s, 0, _vel_target((0, 0, 0), mask=0b010111000111))  # velocity + yaw rate
    msg = mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, 1, 0b010111000111, 0, 0, 0, 0, 0, 0,
                                                                 0, 0, 0, 0, 1e30)
    _send(s, 0, msg)
    assert ap.offb.sp.yaw_rate_radps == pytest.approx(lim.yaw_rate_max_radps)


def test_velocity_and_far_position_targets_respect_px4_speed_limits():
    """Regression: velocity or position targets of 1e30 were flown with no speed limit
    (PX4 caps them with MPC_XY_VEL_MAX and MPC_Z_VEL_MAX_UP/DN)."""
    s = SitlServer(sitl_config(1, params={"MPC_XY_VEL_MAX": 5.0}))
    ap = _hovering_offboard(s)
    _send(s, 0, _vel_target((1e30, 1e30, -1e30)))
    assert np.hypot(*ap.offb.sp.vel_ned_mps[:2]) == pytest.approx(5.0)
    assert ap.offb.sp.vel_ned_mps[2] == pytest.approx(-3.0)  # MPC_Z_VEL_MAX_UP
    assert _fly(s, 3.0) < 5.0 * 1.1
    pos_only = 0b110111111000
    _send(s, 0, _vel_target((0, 0, 0), x=1e30, y=0.0, z=float(s.state.pos_ned_m[0, 2]), mask=pos_only))
    assert _fly(s, 6.0) < 5.0 * 1.15
    assert np.isfinite(s.state.pos_ned_m).all()


def test_partial_nan_position_is_invalid_and_stops_the_vehicle():
    """Regression: a position target with some axes NaN was flown; PX4's position controller
    treats it as invalid ("invalid setpoints") and stops."""
    s = SitlServer(sitl_config(1, params={"COM_OBL_RC_ACT": 5}))  # Hold on offboard loss (stock 0 descends, drifting)
    ap = _hovering_offboard(s)
    _send(s, 0, _vel_target((3.0, 0.0, 0.0)))
    assert _fly(s, 2.0) > 2.0
    _send(s, 0, _vel_target((0, 0, 0), x=50.0, y=math.nan, z=-5.0, mask=0b110111111000))
    assert s.router._last_reject[0] == "invalid setpoints"
    _fly(s, 3.0)  # (PX4's velocity loop, MPC_XY_VEL_P_ACC 1.8, takes about 3 s to stop from 3 m/s)
    assert np.hypot(*s.state.vel_ned_mps[0, :2]) < 0.3
    assert ap.mode.name == "HOLD"  # no valid setpoint for COM_OF_LOSS_T: the offboard-loss failsafe


def test_unknown_incompat_flags_are_dropped():
    """The reference C parser drops frames with incompat flags other than signing (0x01)."""
    from companion.link.framing import FrameError
    from companion.link.msgdef import swarmdrop
    from companion.link.wire import Codec

    codec = Codec(mavlink, swarmdrop)
    good = bytearray(pack_frame(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3)))
    assert codec.decode(bytes(good)).get_type() == "HEARTBEAT"
    good[2] |= 0x02
    with pytest.raises(FrameError):
        codec.decode(bytes(good))


# ---------------------------------------------------------------------------- the agent's own hygiene
def test_clamp_tilt_keeps_heading_and_limits_tilt():
    from companion.frames import euler_zyx_to_quat_wxyz, quat_wxyz_to_euler_zyx, quat_wxyz_to_rot
    from companion.link.limits import clamp_tilt

    q = euler_zyx_to_quat_wxyz(math.radians(70.0), 0.0, math.radians(30.0))
    out = clamp_tilt(q, math.radians(45.0))
    rot = quat_wxyz_to_rot(out)
    assert math.degrees(math.acos(rot[2, 2])) == pytest.approx(45.0, abs=1e-6)
    assert math.degrees(quat_wxyz_to_euler_zyx(out)[2]) == pytest.approx(30.0, abs=1e-6)
    small = euler_zyx_to_quat_wxyz(0.1, -0.2, 1.0)
    assert clamp_tilt(small, math.radians(45.0)) == pytest.approx(small)
    flipped = clamp_tilt(euler_zyx_to_quat_wxyz(math.pi, 0.0, 0.0), math.radians(45.0))
    assert math.degrees(math.acos(quat_wxyz_to_rot(flipped)[2, 2])) == pytest.approx(45.0, abs=1e-6)


def test_fence_keeps_setpoints_inside_and_stops_outward_motion():
    from companion.link.limits import SetpointLimits, clamp_velocity, fence_trajectory

    lo, hi = (-10.0, -10.0, -20.0), (10.0, 10.0, 0.0)
    p, v, a = fence_trajectory((50.0, 0.0, -5.0), (3.0, -1.0, 0.0), (1.0, 0.0, 0.0), lo, hi, own=(10.5, 0.0, -5.0))
    assert p == (10.0, 0.0, -5.0) and v == (0.0, -1.0, 0.0) and a == (0.0, 0.0, 0.0)
    p, v, a = fence_trajectory((math.nan,) * 3, (-2.0, 0.0, 0.0), (0.0,) * 3, lo, hi, own=(0.0, 0.0, -5.0))
    assert v == (-2.0, 0.0, 0.0)  # inside: untouched
    assert clamp_velocity(30.0, 40.0, -10.0, SetpointLimits()) == pytest.approx((7.2, 9.6, -3.0))
    assert clamp_velocity(0.0, 0.0, 9.0, SetpointLimits())[2] == pytest.approx(1.5)


def test_geofence_config_is_validated():
    from pathlib import Path

    import yaml

    from companion.config import ConfigError
    from companion.node.config import load_mission_file
    root = Path(__file__).resolve().parents[1]
    data = yaml.safe_load((root / "configs" / "small_6.yaml").read_text())
    data["mission"]["geofence"] = {"min_ned_m": [0, 0, 0], "max_ned_m": [10, -5, 1]}
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "m.yaml"
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(ConfigError, match="geofence"):
            load_mission_file(path)


def test_sitl_wind_pushes_a_hovering_vehicle_through_drag():
    """Wind configured in the SITL acts as headless: a steady 4 m/s east wind on a vehicle holding
    position tilts it into the wind (thrust balances drag c * 4 m/s)."""
    from companion.params import VehicleParams
    from sim_bridge.world.physics import WindConfig

    vp = VehicleParams(drag_coeff_n_per_mps=0.0065)
    sc = default_scenario()
    sc = replace(sc, vehicle=vp, physics=replace(sc.physics, wind=WindConfig(steady_ned_mps=(0.0, 4.0, 0.0))))
    s = SitlServer(sitl_config(1, scenario=sc, params={"COM_OBL_RC_ACT": 5}))  # the loss ends in Hold, holding position
    _hovering_offboard(s)
    _send(s, 0, _vel_target((0, 0, 0)))
    _fly(s, 6.0)
    r = s.state.rot_body_to_ned[0]
    # thrust direction -b3 leans west (against the wind): its east component is about -c v / (m g)
    lean = -r[1, 2]
    assert lean == pytest.approx(-0.0065 * 4.0 / (vp.mass_kg * 9.80665), rel=0.2)
