"""What each autopilot does when its companion falls silent: the dialects' LossBehaviour
(companion/link/dialects/) and the headless runner's AutopilotModel that acts it out
(sim_bridge/world/autopilot_model.py), step by step (issue 18)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.link.dialects import Mode, dialect_named
from companion.link.dialects.base import AfterLoss, CarryOn
from companion.state import FleetSetpoint, FleetState
from sim_bridge.world.autopilot_model import (
    AP_DESCEND,
    AP_FALL,
    AP_HOLD,
    AP_LAND,
    AP_LOST,
    AP_OFFBOARD,
    AutopilotModel,
    hold_point,
)

PX4, ARDUPILOT = dialect_named("px4"), dialect_named("ardupilot")


# ---------------------------------------------------------------------------- the dialects
@pytest.mark.parametrize("action, rc, then, mode", [
    (0, False, AfterLoss.DESCEND, Mode.POSITION), (1, False, AfterLoss.DESCEND, Mode.POSITION),
    (2, False, AfterLoss.DESCEND, Mode.MANUAL), (0, True, AfterLoss.PILOT, Mode.POSITION),
    (2, True, AfterLoss.PILOT, Mode.MANUAL), (3, False, AfterLoss.RETURN, Mode.RETURN),
    (4, False, AfterLoss.LAND, Mode.LAND), (5, False, AfterLoss.HOLD, Mode.HOLD), (5, True, AfterLoss.HOLD, Mode.HOLD),
    (6, False, AfterLoss.MOTORS_OFF, Mode.HOLD), (7, False, AfterLoss.MOTORS_OFF, Mode.HOLD),
])
def test_px4_offboard_loss_per_com_obl_rc_act(action, rc, then, mode):
    lb = PX4.loss_behaviour({"COM_OF_LOSS_T": 0.8, "COM_OBL_RC_ACT": action, "MPC_LAND_SPEED": 0.5}, rc=rc)
    assert (lb.timeout_s, lb.carry_on, lb.then, lb.mode) == (0.8, CarryOn.SETPOINT, then, mode)
    assert lb.descent_speed_mps == (0.5 if then in (AfterLoss.DESCEND, AfterLoss.LAND, AfterLoss.RETURN) else 0.0)
    assert PX4.loss_drifts({"COM_OBL_RC_ACT": action}, rc=rc) == (then == AfterLoss.DESCEND) == lb.drifts


def test_px4_stock_parameters_drift_without_rc_and_missing_or_bad_values_are_the_defaults():
    lb = PX4.loss_behaviour({})
    assert (lb.timeout_s, lb.then, lb.mode, lb.descent_speed_mps) == (1.0, AfterLoss.DESCEND, Mode.POSITION, 0.7)
    assert PX4.loss_drifts({}) and not PX4.loss_drifts({}, rc=True)
    assert not PX4.loss_drifts({"COM_OBL_RC_ACT": 5}) and not PX4.loss_drifts({"COM_OBL_RC_ACT": 4})
    assert PX4.loss_behaviour({"COM_OF_LOSS_T": math.nan}).timeout_s == 1.0
    assert set(PX4.loss_params) >= {"COM_OF_LOSS_T", "COM_OBL_RC_ACT", "MPC_LAND_SPEED"}


def test_ardupilot_guided_moves_on_until_guid_timeout_then_holds_in_guided_whatever_rc():
    for rc in (False, True):
        lb = ARDUPILOT.loss_behaviour({"GUID_TIMEOUT": 2.0}, rc=rc)
        assert (lb.timeout_s, lb.carry_on, lb.then, lb.mode, lb.descent_speed_mps) == (
            2.0, CarryOn.VELOCITY_ACCELERATION, AfterLoss.HOLD, Mode.OFFBOARD, 0.0)
    assert ARDUPILOT.loss_behaviour({}).timeout_s == 3.0 and not ARDUPILOT.loss_drifts({})
    assert "GUID_TIMEOUT" in ARDUPILOT.loss_params


def test_every_sitl_autopilot_describes_its_loss_from_its_own_table():
    from companion.params import InnerLoopConfig
    from sim_bridge.sitl.autopilots import autopilot_named
    from sim_bridge.sitl.params_table import ParamTable

    for name in ("px4", "ardupilot"):
        b = autopilot_named(name)
        table = ParamTable(b.param_specs(InnerLoopConfig(), 1, 0.5))
        assert all(table.index_of(n) is not None for n in b.dialect.loss_required_params)
        lb = b.loss_behaviour(table)
        assert lb.timeout_s == (1.0 if name == "px4" else 3.0)
        if name == "px4":
            assert table.set("COM_OBL_RC_ACT", 5) and b.loss_behaviour(table).then == AfterLoss.HOLD


# ---------------------------------------------------------------------------- the headless model
DT = 0.02


def _flying(n: int, loss) -> tuple[AutopilotModel, FleetState]:
    """n vehicles released, recovered (level, at rest at 10 m) and flying the agents' setpoints."""
    ap = AutopilotModel.docked(n, 0.0, loss)
    st = FleetState.zeros(n)
    st.pos_ned_m[:] = (0.0, 0.0, -10.0)
    ap.release(np.arange(n), st)
    sp = _agent_sp(n, 0.0)
    ap.setpoint(st, sp, 0.0)  # recovered: Hold
    ap.setpoint(st, sp, DT)  # the agents speak: offboard
    assert (ap.mode == AP_OFFBOARD).all()
    return ap, st


def _agent_sp(n: int, t: float, silent=()) -> FleetSetpoint:
    """Each agent's pos + vel + acc: moving north at 1 m/s, accelerating at 0.5 m/s^2."""
    sp = FleetSetpoint.empty(n)
    sp.pos_ned_m[:] = (t, 0.0, -10.0)
    sp.vel_ned_mps[:] = (1.0, 0.0, 0.0)
    sp.acc_ned_mps2[:] = (0.5, 0.0, 0.0)
    sp.yaw_rad[:] = 0.0
    for k in silent:
        for f in ("pos_ned_m", "vel_ned_mps", "acc_ned_mps2", "yaw_rad"):
            getattr(sp, f)[k] = np.nan
    return sp


def _lose(ap: AutopilotModel, st: FleetState, t_last: float, until: float):
    """Vehicle 0's agent falls silent after t_last; yields (t, that tick's setpoint) until `until`."""
    t = t_last
    while t < until - 1e-9:
        t = round(t + DT, 9)
        st.vel_ned_mps[0] = (0.8, 0.0, 0.0)
        yield t, ap.setpoint(st, _agent_sp(2, t, silent=(0,)), t)


def test_headless_px4_flies_the_last_setpoint_as_it_was_then_descends_drifting_by_default():
    ap, st = _flying(2, PX4.loss_behaviour({}))
    t_last = 1.0
    ap.setpoint(st, _agent_sp(2, t_last), t_last)
    for t, sp in _lose(ap, st, t_last, t_last + 3.0):
        if t - t_last <= 1.0 + 1e-9:  # COM_OF_LOSS_T: the last setpoint, unmoved
            assert ap.mode[0] == AP_LOST and ap.ready[0]
            assert sp.pos_ned_m[0] == pytest.approx([t_last, 0.0, -10.0]) and sp.vel_ned_mps[0, 0] == 1.0
            assert sp.acc_ned_mps2[0, 0] == 0.5
        else:  # then: descend at MPC_LAND_SPEED, no horizontal control (level: zero horizontal acceleration)
            assert ap.mode[0] == AP_DESCEND
            assert np.isnan(sp.pos_ned_m[0]).all() and sp.acc_ned_mps2[0, :2] == pytest.approx([0.0, 0.0])
            assert sp.vel_ned_mps[0, 2] == 0.7 and np.isnan(sp.vel_ned_mps[0, :2]).all()
        assert ap.mode[1] == AP_OFFBOARD and sp.pos_ned_m[1, 0] == pytest.approx(t)  # the other flies on


def test_headless_px4_hold_holds_for_ever_and_land_lands():
    for action, mode in ((5, AP_HOLD), (4, AP_LAND)):
        ap, st = _flying(2, PX4.loss_behaviour({"COM_OBL_RC_ACT": action, "COM_OF_LOSS_T": 0.5}))
        ap.setpoint(st, _agent_sp(2, 1.0), 1.0)
        st.pos_ned_m[0] = (1.2, 0.0, -10.0)
        modes = [(t, int(ap.mode[0]), sp) for t, sp in _lose(ap, st, 1.0, 100.0)]
        first = next(t for t, m, _ in modes if m != AP_LOST)
        assert first == pytest.approx(1.52)  # the first tick past COM_OF_LOSS_T
        assert all(m == mode for t, m, _ in modes if t >= first) and ap.mode[1] == AP_OFFBOARD
        stop = hold_point(np.array([1.2, 0.0, -10.0]), np.array([0.8, 0.0, 0.0]))  # where it comes to rest
        sp = modes[-1][2]
        if mode == AP_HOLD:  # still holding 98 s later: PX4's Hold never lands
            assert sp.pos_ned_m[0] == pytest.approx(stop) and np.isnan(sp.vel_ned_mps[0]).all()
        else:
            assert sp.pos_ned_m[0, :2] == pytest.approx(stop[:2]) and sp.vel_ned_mps[0, 2] == 0.7


def test_headless_motors_off_falls():
    ap, st = _flying(2, PX4.loss_behaviour({"COM_OBL_RC_ACT": 7, "COM_OF_LOSS_T": 0.2}))
    ap.setpoint(st, _agent_sp(2, 1.0), 1.0)
    *_, (t, sp) = _lose(ap, st, 1.0, 1.5)
    assert ap.mode[0] == AP_FALL and sp.thrust_norm[0] == 0.0 and np.isfinite(sp.att_q_wxyz[0]).all()


def test_headless_ardupilot_moves_the_target_on_until_guid_timeout_then_holds_where_it_stopped():
    ap, st = _flying(2, ARDUPILOT.loss_behaviour({"GUID_TIMEOUT": 3.0}))
    t_last = 1.0
    ap.setpoint(st, _agent_sp(2, t_last), t_last)
    for t, sp in _lose(ap, st, t_last, t_last + 60.0):
        tau = t - t_last
        if tau <= 3.0 + 1e-9:  # the target moves on: p + v tau + a tau^2 / 2, v + a tau
            assert ap.mode[0] == AP_LOST
            assert sp.pos_ned_m[0, 0] == pytest.approx(t_last + tau + 0.25 * tau * tau)
            assert sp.vel_ned_mps[0, 0] == pytest.approx(1.0 + 0.5 * tau) and sp.acc_ned_mps2[0, 0] == 0.5
        else:  # stopped where it had moved on to, held for ever
            assert ap.mode[0] == AP_HOLD
            assert sp.pos_ned_m[0] == pytest.approx([t_last + 3.0 + 0.25 * 9.0, 0.0, -10.0])
            assert np.isnan(sp.vel_ned_mps[0]).all() and np.isnan(sp.acc_ned_mps2[0]).all()


def test_headless_an_agent_that_speaks_again_is_flown_again():
    ap, st = _flying(2, PX4.loss_behaviour({"COM_OBL_RC_ACT": 5, "COM_OF_LOSS_T": 0.5}))
    ap.setpoint(st, _agent_sp(2, 1.0), 1.0)
    for _ in _lose(ap, st, 1.0, 2.0):
        pass
    assert ap.mode[0] == AP_HOLD
    sp = ap.setpoint(st, _agent_sp(2, 2.02), 2.02)
    assert ap.mode[0] == AP_OFFBOARD and sp.pos_ned_m[0, 0] == pytest.approx(2.02)


def test_headless_ardupilot_zeroes_a_velocity_target_at_guid_timeout_braking_to_rest():
    """A velocity-only target (no position) is zeroed at GUID_TIMEOUT and brought to rest at
    WPNAV_ACCEL (the LossBehaviour's brake), holding no position: as the SITL does."""
    lb = ARDUPILOT.loss_behaviour({"GUID_TIMEOUT": 1.0, "WPNAV_ACCEL": 200.0})
    assert lb.brake_hor_mps2 == 2.0
    ap, st = _flying(1, lb)
    sp = FleetSetpoint.empty(1)
    sp.vel_ned_mps[0], sp.yaw_rad[0] = (1.0, 0.0, 0.0), 0.0
    ap.setpoint(st, sp, 1.0)
    silent = FleetSetpoint.empty(1)
    for k in range(1, 120):
        t = round(1.0 + k * DT, 9)
        out = ap.setpoint(st, silent, t)
        if t - 1.0 <= 1.0 + 1e-9:
            assert ap.mode[0] == AP_LOST and out.vel_ned_mps[0, 0] == 1.0
        else:
            brake_s = t - 2.0
            assert ap.mode[0] == AP_HOLD and np.isnan(out.pos_ned_m[0]).all()
            assert out.vel_ned_mps[0, 0] == pytest.approx(max(0.0, 1.0 - 2.0 * brake_s))
            assert out.acc_ned_mps2[0, 0] == (-2.0 if 2.0 * brake_s < 1.0 else 0.0)
