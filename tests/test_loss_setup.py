"""What each autopilot does if its companion stops (the dialects' LossBehaviour), and the
agent's set-up check of it (companion.node.setup.Setup.verify_loss) against an autopilot
that answers PARAM_REQUEST_READ and PARAM_SET on a real UDP link, as PX4 and ArduPilot do
(bytewise and C-cast integers; no answer at all for a parameter it does not have)."""
from __future__ import annotations

import asyncio
import dataclasses
import logging
from pathlib import Path

import pytest

from companion.link.dialects import Mode, dialect_named
from companion.link.dialects.base import AfterLoss, CarryOn
from companion.link.endpoints import MavEndpoint, UdpLink
from companion.link.enums import MavParamType, MavState, MavType, MsgId
from companion.link.msgdef import swarmdrop as md
from companion.link.params import decode_param_value, encode_param_value, param_name
from companion.link.wire import Codec
from companion.mission import LossEnvelope
from companion.node.config import NodeConfig, load_mission_file
from companion.node.exits import ExitCode, NodeFailure
from companion.node.setup import Setup
from companion.node.vehicle import VehicleLink

ROOT = Path(__file__).resolve().parents[1]
SMALL6 = ROOT / "configs" / "small_6.yaml"
INT32, REAL32 = MavParamType.MAV_PARAM_TYPE_INT32, MavParamType.MAV_PARAM_TYPE_REAL32
PX4_STOCK = {"COM_OF_LOSS_T": (1.0, REAL32), "COM_OBL_RC_ACT": (0, INT32), "MPC_LAND_SPEED": (0.7, REAL32),
             "MPC_ACC_HOR": (3.0, REAL32), "MPC_ACC_UP_MAX": (4.0, REAL32), "MPC_ACC_DOWN_MAX": (3.0, REAL32),
             "MPC_JERK_AUTO": (4.0, REAL32)}
"""PX4 v1.16's defaults of the parameters that decide its offboard-loss behaviour."""
ARDUPILOT_STOCK = {"GUID_TIMEOUT": (3.0, REAL32), "WPNAV_ACCEL": (250.0, REAL32), "WPNAV_ACCEL_Z": (100.0, REAL32),
                   "PSC_JERK_XY": (5.0, REAL32), "PSC_JERK_Z": (5.0, REAL32)}


# ---------------------------------------------------------------------------- the dialects
@pytest.mark.parametrize("value,then", [
    (0, AfterLoss.DESCEND), (1, AfterLoss.DESCEND), (2, AfterLoss.DESCEND), (3, AfterLoss.RETURN),
    (4, AfterLoss.LAND), (5, AfterLoss.HOLD), (6, AfterLoss.MOTORS_OFF), (7, AfterLoss.MOTORS_OFF),
    (8, AfterLoss.DESCEND)])  # any other value is Position's (failsafe.cpp's default:)
def test_px4_com_obl_rc_act_without_rc(value, then):
    loss = dialect_named("px4").loss_behaviour({"COM_OBL_RC_ACT": value, "COM_OF_LOSS_T": 0.8})
    assert loss.then == then and loss.timeout_s == 0.8 and loss.carry_on == CarryOn.SETPOINT
    assert loss.safe == (then in (AfterLoss.HOLD, AfterLoss.LAND))
    assert loss.drifts == (then == AfterLoss.DESCEND)
    assert loss.lands == (then in (AfterLoss.LAND, AfterLoss.DESCEND, AfterLoss.MOTORS_OFF))
    assert loss.deciding() == f"COM_OBL_RC_ACT = {value}"


def test_px4_braking_limits_come_from_its_parameters():
    loss = dialect_named("px4").loss_behaviour({"COM_OBL_RC_ACT": 5, "MPC_ACC_HOR": 2.0, "MPC_ACC_UP_MAX": 5.0,
                                               "MPC_ACC_DOWN_MAX": 2.5, "MPC_JERK_AUTO": 8.0})
    assert (loss.brake_hor_mps2, loss.brake_ver_mps2, loss.jerk_hor_mps3, loss.jerk_ver_mps3, loss.stop_lead_s) == (
        2.0, 2.5, 8.0, 8.0, 0.6)
    assert loss.value("MPC_ACC_HOR") == 2.0 and "MPC_JERK_AUTO 8" in loss.describe()
    stock = dialect_named("px4").loss_behaviour({})
    assert (stock.then, stock.brake_hor_mps2, stock.brake_ver_mps2, stock.jerk_hor_mps3) == (
        AfterLoss.DESCEND, 3.0, 3.0, 4.0)  # PX4's stock COM_OBL_RC_ACT 0, without RC


def test_ardupilot_guided_coasts_on_velocity_and_acceleration_then_holds_for_ever():
    loss = dialect_named("ardupilot").loss_behaviour({"GUID_TIMEOUT": 1.5, "WPNAV_ACCEL": 400.0, "PSC_JERK_Z": 7.0})
    assert (loss.then, loss.carry_on, loss.mode, loss.timeout_s) == (
        AfterLoss.HOLD, CarryOn.VELOCITY_ACCELERATION, Mode.OFFBOARD, 1.5)
    assert (loss.brake_hor_mps2, loss.brake_ver_mps2, loss.jerk_hor_mps3, loss.jerk_ver_mps3) == (4.0, 1.0, 5.0, 7.0)
    assert loss.safe and not loss.lands and "never lands" in loss.describe()


def test_the_loss_fix_per_autopilot():
    px4, ardupilot = dialect_named("px4"), dialect_named("ardupilot")
    assert px4.loss_fix(AfterLoss.HOLD) == {"COM_OBL_RC_ACT": 5} and px4.loss_fix(AfterLoss.LAND) == {"COM_OBL_RC_ACT": 4}
    assert ardupilot.loss_fix(AfterLoss.HOLD) == {}
    with pytest.raises(ValueError, match="cannot"):
        ardupilot.loss_fix(AfterLoss.LAND)
    assert set(px4.loss_required_params) == {"COM_OF_LOSS_T", "COM_OBL_RC_ACT"}
    assert ardupilot.loss_required_params == ("GUID_TIMEOUT",)


# ---------------------------------------------------------------------------- set-up, on the wire
class ParamAutopilot:
    """An autopilot that sends one HEARTBEAT and answers parameter reads and writes from a
    table (name -> (value, MAV_PARAM_TYPE)); silent about any other name, as PX4 is."""

    def __init__(self, dialect: str, table: dict[str, tuple[float, int]]):
        self.d = dialect_named(dialect)
        self.table = dict(table)
        self.sets: list[tuple[str, float]] = []
        self.ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=True), Codec(md), 1, 1)
        self._value = self.ep.codec.builder(MsgId.PARAM_VALUE)

    def heartbeat_to(self, port: int) -> None:
        self.ep.link.remote = ("127.0.0.1", port)
        self.ep.queue_fields(MsgId.HEARTBEAT, self.ep.codec.builder(MsgId.HEARTBEAT)(
            type=MavType.MAV_TYPE_QUADROTOR, autopilot=self.d.autopilot_id, base_mode=self.d.base_mode(Mode.HOLD, True),
            custom_mode=self.d.custom_mode(Mode.HOLD), system_status=MavState.MAV_STATE_ACTIVE))
        self.ep.flush()

    def serve(self) -> None:
        """Answer whatever has come (called by the event loop when the socket is readable)."""
        for msg, _ in self.ep.poll():
            t = msg.get_type()
            if t not in ("PARAM_REQUEST_READ", "PARAM_SET"):
                continue
            name = param_name(msg.param_id)
            if name not in self.table:
                continue  # no reply: PX4 and ArduPilot do not answer for a parameter they lack
            if t == "PARAM_SET":
                ptype = self.table[name][1]
                value = decode_param_value(msg.param_value, msg.param_type, self.d.param_encoding)
                self.table[name] = (value, ptype)
                self.sets.append((name, value))
            value, ptype = self.table[name]
            self.ep.queue_fields(MsgId.PARAM_VALUE, self._value(
                param_id=name.encode(), param_value=encode_param_value(value, ptype, self.d.param_encoding),
                param_type=ptype, param_count=len(self.table), param_index=list(self.table).index(name)))
        self.ep.flush()


async def _verify(dialect: str, table: dict, envelope: LossEnvelope | None = None, **cfg_kw):
    """Run Setup.verify_loss against a ParamAutopilot, with small_6's mission (its loss
    envelope replaced if given); returns (result or the NodeFailure, autopilot)."""
    loop = asyncio.get_running_loop()
    ap = ParamAutopilot(dialect, table)
    ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=("127.0.0.1", ap.ep.link.local_port), learn_remote=False),
                     Codec(md), 1, 191)
    mf = load_mission_file(SMALL6)
    if envelope is not None:
        m = mf.mission
        mf = dataclasses.replace(mf, mission=dataclasses.replace(m, swarm=dataclasses.replace(m.swarm, loss=envelope)))
    cfg = NodeConfig(vehicle_id=0, autopilot_url="udpout://127.0.0.1:14550", mission=mf, **cfg_kw)
    v = VehicleLink(ep, 1, mf.mission.origin, cfg.autopilot_url)
    heard = loop.create_future()

    def read() -> None:
        for msg, _ in ep.poll():
            v.handle(msg)
        if v.dialect is not None and not heard.done():
            heard.set_result(None)

    loop.add_reader(ep.link.fileno(), read)
    loop.add_reader(ap.ep.link.fileno(), ap.serve)
    try:
        ap.heartbeat_to(ep.link.local_port)
        await asyncio.wait_for(heard, 3.0)
        setup = Setup(cfg, v, swarm=None, start_wall=0.0)  # (verify_loss does not use the swarm link)
        try:
            return await setup.verify_loss(), ap
        except NodeFailure as err:
            return err, ap
    finally:
        loop.remove_reader(ep.link.fileno())
        loop.remove_reader(ap.ep.link.fileno())
        ep.close()
        ap.ep.close()


def test_px4_stock_com_obl_rc_act_is_refused_with_the_parameter_the_behaviour_and_the_fix():
    err, ap = asyncio.run(_verify("px4", PX4_STOCK))
    assert isinstance(err, NodeFailure) and err.code == ExitCode.SETUP
    text = str(err)
    for part in ("COM_OBL_RC_ACT = 0", "descends at 0.7 m/s with no horizontal control",
                 "set COM_OBL_RC_ACT to 5 (Hold) or 4 (Land)", "--allow-drifting-loss", "--set-loss-action"):
        assert part in text, text
    assert not ap.sets  # verification sets nothing


def test_allow_drifting_loss_flies_with_a_warning(caplog):
    caplog.set_level(logging.INFO, "swarmdrop.agent")
    loss, ap = asyncio.run(_verify("px4", PX4_STOCK, allow_drifting_loss=True))
    assert loss.then == AfterLoss.DESCEND and not ap.sets
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("COM_OBL_RC_ACT = 0" in w and "--allow-drifting-loss" in w for w in warnings), warnings


def test_px4_hold_is_logged_in_one_info_line_with_its_values(caplog):
    caplog.set_level(logging.INFO, "swarmdrop.agent")
    table = PX4_STOCK | {"COM_OBL_RC_ACT": (5, INT32), "COM_OF_LOSS_T": (0.5, REAL32), "MPC_ACC_HOR": (2.5, REAL32)}
    loss, _ = asyncio.run(_verify("px4", table))
    assert (loss.then, loss.timeout_s, loss.brake_hor_mps2) == (AfterLoss.HOLD, 0.5, 2.5)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("if this companion stops:")]
    assert len(lines) == 1 and "COM_OBL_RC_ACT 5" in lines[0] and "holds there for ever" in lines[0], lines
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_deciding_parameter_not_served_is_refused_and_named():
    """As our SITL before it served COM_OBL_RC_ACT: a real PX4 always has it."""
    table = {k: v for k, v in PX4_STOCK.items() if k != "COM_OBL_RC_ACT"}
    err, _ = asyncio.run(_verify("px4", table))
    assert isinstance(err, NodeFailure) and err.code == ExitCode.SETUP
    assert "does not answer for COM_OBL_RC_ACT" in str(err)


def test_braking_limits_not_served_fall_back_to_the_stock_values_with_a_warning(caplog):
    caplog.set_level(logging.INFO, "swarmdrop.agent")
    loss, _ = asyncio.run(_verify("ardupilot", {"GUID_TIMEOUT": (0.5, REAL32)}))
    assert (loss.then, loss.timeout_s, loss.brake_hor_mps2, loss.jerk_hor_mps3) == (AfterLoss.HOLD, 0.5, 2.5, 5.0)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("WPNAV_ACCEL, WPNAV_ACCEL_Z, PSC_JERK_XY, PSC_JERK_Z" in w for w in warnings), warnings


def test_set_loss_action_sets_the_parameter_says_so_and_then_verifies(caplog):
    caplog.set_level(logging.INFO, "swarmdrop.agent")
    err, ap = asyncio.run(_verify("px4", PX4_STOCK, set_loss_action="land"))  # the mission assumes a hold
    assert isinstance(err, NodeFailure) and "it lands where the mission assumes a hold" in str(err)
    loss, ap = asyncio.run(_verify("px4", PX4_STOCK, LossEnvelope(then="land"), set_loss_action="land"))
    assert ap.sets == [("COM_OBL_RC_ACT", 4.0)] and ap.table["COM_OBL_RC_ACT"] == (4.0, INT32)
    assert loss.then == AfterLoss.LAND
    assert any("set COM_OBL_RC_ACT = 4 (was 0)" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    again, ap = asyncio.run(_verify("px4", PX4_STOCK | {"COM_OBL_RC_ACT": (5, INT32)}, set_loss_action="hold"))
    assert again.then == AfterLoss.HOLD and not ap.sets  # already so: nothing written


def test_set_loss_action_land_is_refused_on_ardupilot_which_always_holds():
    err, ap = asyncio.run(_verify("ardupilot", ARDUPILOT_STOCK, set_loss_action="land"))
    assert isinstance(err, NodeFailure) and "--set-loss-action land" in str(err) and "cannot" in str(err)
    held, ap = asyncio.run(_verify("ardupilot", ARDUPILOT_STOCK, set_loss_action="hold"))
    # GUIDED holds whatever its parameters; its stock 3 s timeout comes down to the mission's 1 s
    assert held.then == AfterLoss.HOLD and held.timeout_s == 1.0 and ap.sets == [("GUID_TIMEOUT", 1.0)]


def test_a_loss_beyond_the_missions_envelope_is_refused_naming_each_limit_and_the_fix(caplog):
    """The swarm draws every ghost from mission.swarm.loss: an autopilot that coasts longer or
    brakes softer can leave it. ArduPilot's stock GUID_TIMEOUT (3 s) and a soft PX4 stop."""
    err, ap = asyncio.run(_verify("ardupilot", ARDUPILOT_STOCK))
    assert isinstance(err, NodeFailure) and err.code == ExitCode.SETUP and not ap.sets
    for part in ("its setpoint timeout 3 s is longer than the mission's 1 s", "set GUID_TIMEOUT to at most 1 s",
                 "--set-loss-action", "mission.swarm.loss", "--allow-drifting-loss"):
        assert part in str(err), str(err)
    soft = PX4_STOCK | {"COM_OBL_RC_ACT": (5, INT32), "MPC_ACC_HOR": (2.0, REAL32), "MPC_JERK_AUTO": (3.0, REAL32)}
    err, _ = asyncio.run(_verify("px4", soft))
    assert isinstance(err, NodeFailure)
    for part in ("its horizontal braking limit 2 is below the mission's 2.5",
                 "its horizontal jerk limit 3 is below the mission's 4", "its vertical jerk limit 3"):
        assert part in str(err), str(err)
    caplog.set_level(logging.INFO, "swarmdrop.agent")
    loss, ap = asyncio.run(_verify("ardupilot", ARDUPILOT_STOCK, allow_drifting_loss=True))
    assert loss.timeout_s == 3.0 and not ap.sets
    assert any("longer than the mission's 1 s" in r.getMessage() and "--allow-drifting-loss" in r.getMessage()
               for r in caplog.records if r.levelno == logging.WARNING)


def test_the_envelope_covers_the_stock_autopilots_once_set_and_draws_the_ghost_it_says():
    env = LossEnvelope()
    px4, ardupilot = dialect_named("px4"), dialect_named("ardupilot")
    assert env.exceeded_by(px4.loss_behaviour({"COM_OBL_RC_ACT": 5})) == []  # Hold, every other PX4 default
    assert env.exceeded_by(ardupilot.loss_behaviour({"GUID_TIMEOUT": 1.0})) == []
    assert env.exceeded_by(ardupilot.loss_behaviour({})) == ["its setpoint timeout 3 s is longer than the mission's 1 s"]
    assert env.exceeded_by(px4.loss_behaviour({"COM_OBL_RC_ACT": 4})) == ["it lands where the mission assumes a hold"]
    lands = LossEnvelope(then="land")  # covers a hold and a landing
    for then in (5, 4):
        assert lands.exceeded_by(px4.loss_behaviour({"COM_OBL_RC_ACT": then})) == []
    b = env.behaviour()
    assert (b.timeout_s, b.then, b.brake_hor_mps2, b.brake_ver_mps2, b.jerk_hor_mps3, b.stop_lead_s) == (
        1.0, AfterLoss.HOLD, 2.5, 1.0, 4.0, 0.6)
    assert lands.behaviour().then == AfterLoss.LAND and lands.behaviour().descent_speed_mps == 0.7
