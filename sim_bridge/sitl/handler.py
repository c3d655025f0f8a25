"""Inbound MAVLink: route a decoded message to its vehicle and answer as PX4 would.

The router knows the SITL only through the small `SitlContext` protocol (the
server implements it), so it can be tested without sockets.
"""
from __future__ import annotations

import math
import time
from typing import Callable, Protocol

from companion.link.enums import FailureType, FailureUnit, MavCmd, MavFtpErr, MavFtpOpcode, MavMissionType, MsgId
from companion.link.framing import signature_of
from companion.link.limits import INVALID_SETPOINTS, check_attitude, check_trajectory
from companion.link.params import param_name
from companion.link.setpoints import Rejected, decode_attitude_target, decode_position_target
from sim_bridge.sitl.autopilot import (
    ACCEPTED,
    DENIED,
    FAILED,
    SEV_CRITICAL,
    SEV_INFO,
    TEMPORARILY_REJECTED,
    UNSUPPORTED,
    Autopilot,
)
from sim_bridge.sitl.params_table import ParamTable
from sim_bridge.sitl.telemetry import (
    HEARTBEAT,
    REQUESTABLE,
    STREAMS,
    Outgoing,
    TelemetryBuilder,
)
from sim_bridge.world.faults import RotorFaults

CMD_NAV_LAND = MavCmd.MAV_CMD_NAV_LAND
CMD_NAV_TAKEOFF = MavCmd.MAV_CMD_NAV_TAKEOFF
CMD_DO_SET_MODE = MavCmd.MAV_CMD_DO_SET_MODE
CMD_ARM_DISARM = MavCmd.MAV_CMD_COMPONENT_ARM_DISARM
CMD_INJECT_FAILURE = MavCmd.MAV_CMD_INJECT_FAILURE
CMD_GET_MESSAGE_INTERVAL = MavCmd.MAV_CMD_GET_MESSAGE_INTERVAL
CMD_SET_MESSAGE_INTERVAL = MavCmd.MAV_CMD_SET_MESSAGE_INTERVAL
CMD_REQUEST_MESSAGE = MavCmd.MAV_CMD_REQUEST_MESSAGE
CMD_REQUEST_AUTOPILOT_CAPABILITIES = MavCmd.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES
CMD_SD_RELEASE = MavCmd.MAV_CMD_USER_1
"""swarmdrop's own: release this vehicle from the carrier now."""
FTP_NAK = MavFtpOpcode.MAV_FTP_OPCODE_NAK

COMMAND_INT_OK = frozenset({CMD_NAV_LAND, CMD_NAV_TAKEOFF, CMD_DO_SET_MODE, CMD_ARM_DISARM, CMD_INJECT_FAILURE,
                            CMD_SET_MESSAGE_INTERVAL, CMD_REQUEST_MESSAGE, CMD_GET_MESSAGE_INTERVAL,
                            CMD_REQUEST_AUTOPILOT_CAPABILITIES, CMD_SD_RELEASE})


PARAM_LIST_RATE_HZ = 1000.0
"""PARAM_VALUEs per second per listing client (PX4 paces its list by link bandwidth): a full
table takes tens of ms, and a flood of PARAM_REQUEST_LIST cannot queue more than one list."""
PARAM_LISTS_MAX = 64
"""Listings in progress at once (all vehicles and clients); a new one beyond this replaces the oldest."""
SETUP_SIGNING_REPORT_S = 1.0
"""At most one "SETUP_SIGNING refused" STATUSTEXT per vehicle per this many wall seconds
(each refusal is counted; a flood of them must not become a flood of STATUSTEXTs)."""


class SitlContext(Protocol):
    """What the router reads of the SITL and asks it to do (SitlServer implements it)."""

    n: int
    home_alt_amsl_m: float
    rotor_faults: RotorFaults
    autopilots: list[Autopilot]
    params: list[ParamTable]
    telemetry: TelemetryBuilder

    @property
    def sim_s(self) -> float: ...
    def send(self, k: int, msg: Outgoing, endpoint, addr) -> None: ...
    def set_message_interval(self, k: int, msgid: int, interval_s: float | None, endpoint=None) -> None: ...
    def message_interval_s(self, k: int, msgid: int, endpoint=None) -> float: ...
    def on_setpoint(self, k: int) -> None: ...
    def on_companion_tick(self, k: int, time_usec: int) -> None: ...
    def set_origin_geodetic(self, k: int, lat_e7: int, lon_e7: int, alt_mm: int) -> None: ...
    def after_change(self, k: int) -> None: ...


class MessageRouter:
    """Args:
        ctx: the SITL (SitlContext).
        clock: monotonic wall seconds (paces the SETUP_SIGNING reports).
    """

    def __init__(self, ctx: SitlContext, clock: Callable[[], float] = time.monotonic):
        self.ctx = ctx
        self.clock = clock
        self._last_reject: dict[int, str] = {}
        self._lists: dict[tuple[int, int, object], list] = {}
        """(vehicle, endpoint id, client address) -> [endpoint, next index, budget]: paced listings."""
        self.param_lists_replaced = 0
        """Listings dropped because PARAM_LISTS_MAX others were in progress."""
        self._dispatch = {
            "COMMAND_LONG": self._command_long,
            "COMMAND_INT": self._command_int,
            "SET_POSITION_TARGET_LOCAL_NED": self._position_target,
            "SET_ATTITUDE_TARGET": self._attitude_target,
            "PARAM_REQUEST_LIST": self._param_list,
            "PARAM_REQUEST_READ": self._param_read,
            "PARAM_SET": self._param_set,
            "TIMESYNC": self._timesync,
            "PING": self._ping,
            "MISSION_REQUEST_LIST": self._mission_list,
            "FILE_TRANSFER_PROTOCOL": self._ftp,
            "SET_GPS_GLOBAL_ORIGIN": self._set_origin,
            "SWARMDROP_TICK": self._companion_tick,
            "SETUP_SIGNING": self._setup_signing,
        }
        self.setup_signing_refused = 0
        """SETUP_SIGNING refused in this SITL, on any endpoint, in any signing mode (per
        link: SigningCounters.setup_signing_refused)."""
        self._setup_reported: dict[int, float] = {}
        """vehicle -> wall time of its last "SETUP_SIGNING refused" report."""

    def targets(self, msg, vehicle: int | None) -> list[int]:
        """Vehicle indices a message is for: its own vehicle on a per-vehicle link,
        by target_system on the shared link (0 = all)."""
        tsys = getattr(msg, "target_system", 0)
        tcomp = getattr(msg, "target_component", 0)
        if tcomp not in (0, 1):
            return []
        if vehicle is not None:
            return [vehicle] if tsys in (0, vehicle + 1) else []
        if tsys == 0:
            return list(range(self.ctx.n))
        return [tsys - 1] if 1 <= tsys <= self.ctx.n else []

    def handle(self, endpoint, msg, addr, vehicle: int | None) -> None:
        fn = self._dispatch.get(msg.get_type())
        if msg.get_type() == "SWARMDROP_TICK":  # no target fields: a companion's own vehicle
            if vehicle is not None and fn is not None:
                fn(vehicle, msg, endpoint, addr)
            return
        if fn is None:
            return
        if msg.get_type() in ("TIMESYNC", "PING") and vehicle is None:
            ks = [0]  # the shared link answers once, as vehicle 1
        else:
            ks = self.targets(msg, vehicle)
        for k in ks:
            fn(k, msg, endpoint, addr)
            self.ctx.after_change(k)

    # ---- commands ------------------------------------------------------------------
    def _ack(self, k, msg, endpoint, addr, command, result) -> None:
        ack = self.ctx.telemetry.build_fields[MsgId.COMMAND_ACK](
            command=command, result=result, target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent())
        self.ctx.send(k, (MsgId.COMMAND_ACK, ack), endpoint, addr)

    def _reply_message(self, k, msgid: int) -> tuple[int, object | None]:
        """(ACK result, message) for REQUEST_MESSAGE of msgid."""
        msg = self.ctx.telemetry.build(k, msgid, self.ctx.sim_s)
        if msg is None:  # e.g. GPS_GLOBAL_ORIGIN before the first fix
            return TEMPORARILY_REJECTED, None
        return ACCEPTED, msg

    def _command_long(self, k, msg, endpoint, addr) -> None:
        p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._command(k, msg, endpoint, addr, msg.command, p)

    def _command_int(self, k, msg, endpoint, addr) -> None:
        if msg.command not in COMMAND_INT_OK:
            self._ack(k, msg, endpoint, addr, msg.command, UNSUPPORTED)
            return
        p = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._command(k, msg, endpoint, addr, msg.command, p)

    def _command(self, k, msg, endpoint, addr, command, p) -> None:
        ctx, ap, now = self.ctx, self.ctx.autopilots[k], self.ctx.sim_s
        followup = None
        if command == CMD_ARM_DISARM:
            result = ap.command_arm(p[0], p[1], now)
        elif command == CMD_NAV_TAKEOFF:
            result = ap.command_takeoff(p[6], ctx.home_alt_amsl_m, now)
        elif command == CMD_NAV_LAND:
            result = ap.command_land(now)
        elif command == CMD_DO_SET_MODE:
            result = ap.command_set_mode(p[0], p[1], p[2], now)
        elif command == CMD_SD_RELEASE:
            result = ap.command_release()
        elif command == CMD_INJECT_FAILURE:
            result = self._inject_failure(k, ap, p[0], p[1], p[2])
        elif command == CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(k, p[0], p[1], endpoint)
        elif command == CMD_GET_MESSAGE_INTERVAL:
            result, followup = self._get_interval(k, p[0], endpoint)
        elif command in (CMD_REQUEST_MESSAGE, CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            msgid = MsgId.AUTOPILOT_VERSION if command == CMD_REQUEST_AUTOPILOT_CAPABILITIES else p[0]
            if not math.isfinite(msgid) or int(msgid) not in REQUESTABLE:
                result = DENIED
            else:
                result, followup = self._reply_message(k, int(msgid))
        else:
            result = UNSUPPORTED
        self._ack(k, msg, endpoint, addr, command, result)
        if followup is not None:
            ctx.send(k, followup, endpoint, addr)

    def _inject_failure(self, k, ap, unit, kind, instance) -> int:
        """PX4's failure injection, motors only: DENIED unless the autopilot enables it (PX4:
        SYS_FAILURE_EN 1), UNSUPPORTED for other units and types and on autopilots without
        the command (ArduPilot).
        instance 0 stops every motor, 1..4 one of them. A stopped motor stays stopped
        (FAILURE_TYPE_OK is refused: the simulated rotor does not come back)."""
        if not ap.behaviour.supports_failure_injection:
            return UNSUPPORTED
        if not all(math.isfinite(x) for x in (unit, kind, instance)):
            return DENIED
        if not ap.behaviour.failure_injection_enabled(self.ctx.params[k]):
            return DENIED
        motor = int(instance)
        if int(unit) != FailureUnit.FAILURE_UNIT_SYSTEM_MOTOR or int(kind) != FailureType.FAILURE_TYPE_OFF \
                or not 0 <= motor <= 4:
            return UNSUPPORTED
        for r in (range(4) if motor == 0 else (motor - 1,)):
            self.ctx.rotor_faults.fail_now(k, r, self.ctx.sim_s)
        ap.events.append((SEV_CRITICAL, f"motor failure injected: {'all' if motor == 0 else motor}"))
        return ACCEPTED

    def _set_interval(self, k, msgid_f, interval_us, endpoint) -> int:
        """SET_MESSAGE_INTERVAL for the link it came on (endpoint): intervals are per link."""
        if not (math.isfinite(msgid_f) and math.isfinite(interval_us)):
            return DENIED
        msgid = int(msgid_f)
        if msgid not in STREAMS and msgid != HEARTBEAT:
            # not a stream here: both autopilots answer FAILED (PX4 mavlink_receiver, ArduPilot
            # GCS_Common set_message_interval), ArduPilot also tells its ground stations
            ap = self.ctx.autopilots[k]
            if ap.behaviour.says_unknown_interval_id:
                ap.events.append((SEV_INFO, f"No ap_message for mavlink id ({msgid})"))
            return FAILED
        if interval_us > 2**31 - 1:  # MESSAGE_INTERVAL carries an int32: refuse what it cannot report
            return DENIED
        if interval_us < 0:
            value = math.inf
        elif interval_us == 0:
            value = None
        else:
            value = interval_us * 1e-6
        self.ctx.set_message_interval(k, msgid, value, endpoint)
        return ACCEPTED

    def _get_interval(self, k, msgid_f, endpoint):
        if not math.isfinite(msgid_f) or (int(msgid_f) not in STREAMS and int(msgid_f) != HEARTBEAT):
            return DENIED, None
        iv = self.ctx.message_interval_s(k, int(msgid_f), endpoint)
        us = -1 if not math.isfinite(iv) else int(round(iv * 1e6))
        return ACCEPTED, (MsgId.MESSAGE_INTERVAL, self.ctx.telemetry.build_fields[MsgId.MESSAGE_INTERVAL](
            message_id=int(msgid_f), interval_us=us))

    # ---- offboard ------------------------------------------------------------------
    def _position_target(self, k, msg, endpoint, addr) -> None:
        ap = self.ctx.autopilots[k]
        sp = decode_position_target(
            msg.type_mask, msg.coordinate_frame, (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz),
            (msg.afx, msg.afy, msg.afz), msg.yaw, msg.yaw_rate, ap.rot, ap.dialect.setpoint_rules)
        if not isinstance(sp, Rejected):
            sp = check_trajectory(sp, ap.knobs.limits())
        self._offboard(k, ap, sp)

    def _attitude_target(self, k, msg, endpoint, addr) -> None:
        ap = self.ctx.autopilots[k]
        sp = decode_attitude_target(msg.type_mask, tuple(msg.q),
                                    (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate), msg.thrust,
                                    ap.dialect.setpoint_rules)
        if not isinstance(sp, Rejected):
            sp = check_attitude(sp, ap.knobs.limits(), ap.knobs.thrust_is_thrust)
        self._offboard(k, ap, sp)

    def _offboard(self, k, ap, sp) -> None:
        if isinstance(sp, Rejected):
            if self._last_reject.get(k) != sp.reason:  # one STATUSTEXT per new reason, no flood
                self._last_reject[k] = sp.reason
                ap.events.append((SEV_CRITICAL, sp.reason))
            if sp.reason == INVALID_SETPOINTS:  # PX4's failsafe setpoint: stop where it is
                ap.on_invalid_setpoint()
            return
        self._last_reject.pop(k, None)
        ap.on_offboard_setpoint(sp, self.ctx.sim_s)
        self.ctx.on_setpoint(k)

    def _setup_signing(self, k, msg, endpoint, addr) -> None:
        """A new key, accepted only over an already trusted link: signing is on for this
        endpoint and the message itself was signed with the current key and is new (the
        signing layer drops, counts and reports the rest before decoding: see
        refuse_setup_signing). Without that, anyone on the link could install their own key."""
        sg = getattr(endpoint, "signing", None)
        if sg is None or signature_of(msg) is None:
            if sg is not None:
                sg.counters.setup_signing_refused += 1
            self.refuse_setup_signing(k, "signing off" if sg is None else "unsigned")
            return
        sg.set_key(bytes(msg.secret_key))

    def refuse_setup_signing(self, k: int, reason: str) -> None:
        """Count a refused SETUP_SIGNING for vehicle k and say so by STATUSTEXT (CRITICAL, to
        the vehicle's ground stations, never to the sender), at most once per vehicle per
        SETUP_SIGNING_REPORT_S with the number refused so far."""
        self.setup_signing_refused += 1
        now = self.clock()
        if now - self._setup_reported.get(k, -math.inf) < SETUP_SIGNING_REPORT_S:
            return
        self._setup_reported[k] = now
        self.ctx.autopilots[k].events.append(
            (SEV_CRITICAL, f"SETUP_SIGNING refused ({reason}), {self.setup_signing_refused} so far"))

    def _companion_tick(self, k, msg, endpoint, addr) -> None:
        self.ctx.on_companion_tick(k, msg.time_usec)

    def _set_origin(self, k, msg, endpoint, addr) -> None:
        if msg.target_system != k + 1:  # PX4: only for its own sysid, never broadcast
            return
        self.ctx.set_origin_geodetic(k, msg.latitude, msg.longitude, msg.altitude)

    # ---- parameters ------------------------------------------------------------------
    def _param_value(self, k, index) -> Outgoing:
        table = self.ctx.params[k]
        name, wire, ptype = table.wire(index)
        return MsgId.PARAM_VALUE, self.ctx.telemetry.build_fields[MsgId.PARAM_VALUE](
            param_id=name.encode(), param_value=wire, param_type=ptype, param_count=len(table), param_index=index)

    def _param_list(self, k, msg, endpoint, addr) -> None:
        """Start (or restart) a paced listing for this client: `pump_params` sends it.
        A repeated request restarts the one listing instead of queueing another."""
        key = (k, id(endpoint), addr)
        if key not in self._lists and len(self._lists) >= PARAM_LISTS_MAX:
            self._lists.pop(next(iter(self._lists)))
            self.param_lists_replaced += 1
        self._lists[key] = [endpoint, 0, 1.0]

    def pump_params(self, dt_s: float) -> set:
        """Send the listings in progress, PARAM_LIST_RATE_HZ each, for dt_s of wall time;
        returns the endpoints that got messages (to flush)."""
        touched = set()
        for key in list(self._lists):
            k, _, addr = key
            item = self._lists[key]
            endpoint, i, budget = item
            budget = min(budget + dt_s * PARAM_LIST_RATE_HZ, 0.05 * PARAM_LIST_RATE_HZ)
            n = len(self.ctx.params[k])
            while budget >= 1.0 and i < n:
                self.ctx.send(k, self._param_value(k, i), endpoint, addr)
                i += 1
                budget -= 1.0
            touched.add(endpoint)
            if i >= n:
                del self._lists[key]
            else:
                item[1], item[2] = i, budget
        return touched

    def _param_read(self, k, msg, endpoint, addr) -> None:
        table = self.ctx.params[k]
        if msg.param_index >= 0:
            idx = msg.param_index if msg.param_index < len(table) else None
        else:
            idx = table.index_of(param_name(msg.param_id))
        if idx is not None:
            self.ctx.send(k, self._param_value(k, idx), endpoint, addr)

    def _param_set(self, k, msg, endpoint, addr) -> None:
        idx = self.ctx.params[k].set_wire(param_name(msg.param_id), msg.param_value, msg.param_type)
        if idx is not None:
            self.ctx.send(k, self._param_value(k, idx), endpoint, addr)

    # ---- time, ping, missions -----------------------------------------------------------
    def _timesync(self, k, msg, endpoint, addr) -> None:
        if msg.tc1 != 0:
            return
        # tc1 is the autopilot's boot clock in ns: simulation time (PX4 SITL in lockstep too).
        b = self.ctx.telemetry.build_fields[MsgId.TIMESYNC]
        fields = {"tc1": int(round(self.ctx.sim_s * 1e9)), "ts1": msg.ts1}
        if "target_system" in getattr(b, "fields", ()):  # (newer common.xml addresses the reply)
            fields |= {"target_system": msg.get_srcSystem(), "target_component": msg.get_srcComponent()}
        self.ctx.send(k, (MsgId.TIMESYNC, b(**fields)), endpoint, addr)

    def _ping(self, k, msg, endpoint, addr) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            self.ctx.send(k, (MsgId.PING, self.ctx.telemetry.build_fields[MsgId.PING](
                time_usec=msg.time_usec, seq=msg.seq, target_system=msg.get_srcSystem(),
                target_component=msg.get_srcComponent())), endpoint, addr)

    def _mission_list(self, k, msg, endpoint, addr) -> None:
        """No missions in the SITL: an empty list keeps ground stations happy."""
        self.ctx.send(k, (MsgId.MISSION_COUNT, self.ctx.telemetry.build_fields[MsgId.MISSION_COUNT](
            target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent(), count=0,
            mission_type=getattr(msg, "mission_type", MavMissionType.MAV_MISSION_TYPE_MISSION))), endpoint, addr)


    def _ftp(self, k, msg, endpoint, addr) -> None:
        """No MAVLink FTP: NAK every request (FileNotFound) so clients fall back at once
        (MAVProxy then fetches parameters with PARAM_REQUEST_LIST)."""
        req = bytes(msg.payload)
        if len(req) < 12 or req[3] in (MavFtpOpcode.MAV_FTP_OPCODE_ACK, FTP_NAK):  # not a request, or an ACK/NAK
            return
        seq = (int.from_bytes(req[0:2], "little") + 1) & 0xFFFF
        reply = bytearray(251)
        reply[0:2] = seq.to_bytes(2, "little")
        reply[2], reply[3], reply[4], reply[5] = req[2], FTP_NAK, 1, req[3]  # session, NAK, size 1, req_opcode
        reply[12] = MavFtpErr.MAV_FTP_ERR_FILENOTFOUND
        self.ctx.send(k, (MsgId.FILE_TRANSFER_PROTOCOL, self.ctx.telemetry.build_fields[MsgId.FILE_TRANSFER_PROTOCOL](
            target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent(), payload=tuple(reply))),
            endpoint, addr)


