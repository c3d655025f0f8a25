"""Inbound MAVLink: route a decoded message to its vehicle and answer as PX4 would.

The router knows the SITL only through the small `SitlContext` protocol (the
server implements it), so it can be tested without sockets.
"""
from __future__ import annotations

import math
import os
import time
from typing import Protocol

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from sim_bridge.sitl.autopilot import (  # noqa: E402
    ACCEPTED, DENIED, SEV_CRITICAL, UNSUPPORTED, Autopilot,
)
from sim_bridge.sitl.offboard import Rejected, decode_attitude_target, decode_position_target  # noqa: E402
from sim_bridge.sitl.params_table import ParamTable  # noqa: E402
from sim_bridge.sitl.telemetry import HEARTBEAT, REQUESTABLE, STREAMS, TelemetryBuilder  # noqa: E402

CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_ARM_DISARM = 400
CMD_GET_MESSAGE_INTERVAL = 510
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_MESSAGE = 512
CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
CMD_SD_RELEASE = 31010  # MAV_CMD_USER_1: release this vehicle from the carrier now

COMMAND_INT_OK = frozenset({CMD_NAV_LAND, CMD_NAV_TAKEOFF, CMD_DO_SET_MODE, CMD_ARM_DISARM,
                            CMD_SET_MESSAGE_INTERVAL, CMD_REQUEST_MESSAGE, CMD_GET_MESSAGE_INTERVAL,
                            CMD_SD_RELEASE})


class SitlContext(Protocol):
    n: int
    sim_s: float
    home_alt_amsl_m: float
    autopilots: list[Autopilot]
    params: list[ParamTable]
    telemetry: TelemetryBuilder

    def send(self, k: int, msg: mavlink.MAVLink_message, endpoint, addr) -> None: ...
    def set_message_interval(self, k: int, msgid: int, interval_s: float | None) -> None: ...
    def message_interval_s(self, k: int, msgid: int) -> float: ...
    def on_setpoint(self, k: int) -> None: ...
    def after_change(self, k: int) -> None: ...


class MessageRouter:
    def __init__(self, ctx: SitlContext):
        self.ctx = ctx
        self._last_reject: dict[int, str] = {}
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
        }

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
        self.ctx.send(k, mavlink.MAVLink_command_ack_message(
            command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()), endpoint, addr)

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
        elif command == CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(k, p[0], p[1])
        elif command == CMD_GET_MESSAGE_INTERVAL:
            result, followup = self._get_interval(k, p[0])
        elif command in (CMD_REQUEST_MESSAGE, CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            msgid = 148 if command == CMD_REQUEST_AUTOPILOT_CAPABILITIES else p[0]
            if not math.isfinite(msgid) or int(msgid) not in REQUESTABLE:
                result = DENIED
            else:
                result = ACCEPTED
                followup = ctx.telemetry.build(k, int(msgid), now)
        else:
            result = UNSUPPORTED
        self._ack(k, msg, endpoint, addr, command, result)
        if followup is not None:
            ctx.send(k, followup, endpoint, addr)

    def _set_interval(self, k, msgid_f, interval_us) -> int:
        if not (math.isfinite(msgid_f) and math.isfinite(interval_us)):
            return DENIED
        msgid = int(msgid_f)
        if msgid not in STREAMS and msgid != HEARTBEAT:
            return DENIED
        if interval_us < 0:
            value = math.inf
        elif interval_us == 0:
            value = None
        else:
            value = interval_us * 1e-6
        self.ctx.set_message_interval(k, msgid, value)
        return ACCEPTED

    def _get_interval(self, k, msgid_f):
        if not math.isfinite(msgid_f) or (int(msgid_f) not in STREAMS and int(msgid_f) != HEARTBEAT):
            return DENIED, None
        iv = self.ctx.message_interval_s(k, int(msgid_f))
        us = -1 if not math.isfinite(iv) else int(round(iv * 1e6))
        return ACCEPTED, mavlink.MAVLink_message_interval_message(int(msgid_f), us)

    # ---- offboard ------------------------------------------------------------------
    def _position_target(self, k, msg, endpoint, addr) -> None:
        ap = self.ctx.autopilots[k]
        sp = decode_position_target(
            msg.type_mask, msg.coordinate_frame, (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz),
            (msg.afx, msg.afy, msg.afz), msg.yaw, msg.yaw_rate, ap.rot)
        self._offboard(k, ap, sp)

    def _attitude_target(self, k, msg, endpoint, addr) -> None:
        ap = self.ctx.autopilots[k]
        sp = decode_attitude_target(msg.type_mask, tuple(msg.q),
                                    (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate), msg.thrust)
        self._offboard(k, ap, sp)

    def _offboard(self, k, ap, sp) -> None:
        if isinstance(sp, Rejected):
            if self._last_reject.get(k) != sp.reason:  # one STATUSTEXT per new reason, no flood
                self._last_reject[k] = sp.reason
                ap.events.append((SEV_CRITICAL, sp.reason))
            return
        self._last_reject.pop(k, None)
        ap.on_offboard_setpoint(sp, self.ctx.sim_s)
        self.ctx.on_setpoint(k)

    # ---- parameters ------------------------------------------------------------------
    def _param_value(self, k, index) -> mavlink.MAVLink_message:
        table = self.ctx.params[k]
        name, wire, ptype = table.wire(index)
        return mavlink.MAVLink_param_value_message(name.encode(), wire, ptype, len(table), index)

    def _param_list(self, k, msg, endpoint, addr) -> None:
        for i in range(len(self.ctx.params[k])):
            self.ctx.send(k, self._param_value(k, i), endpoint, addr)

    def _param_read(self, k, msg, endpoint, addr) -> None:
        table = self.ctx.params[k]
        if msg.param_index >= 0:
            idx = msg.param_index if msg.param_index < len(table) else None
        else:
            idx = table.index_of(_name(msg.param_id))
        if idx is not None:
            self.ctx.send(k, self._param_value(k, idx), endpoint, addr)

    def _param_set(self, k, msg, endpoint, addr) -> None:
        idx = self.ctx.params[k].set_wire(_name(msg.param_id), msg.param_value, msg.param_type)
        if idx is not None:
            self.ctx.send(k, self._param_value(k, idx), endpoint, addr)

    # ---- time, ping, missions -----------------------------------------------------------
    def _timesync(self, k, msg, endpoint, addr) -> None:
        if msg.tc1 != 0:
            return
        now_ns = time.monotonic_ns()
        reply = mavlink.MAVLink_timesync_message(now_ns, msg.ts1)
        if hasattr(reply, "target_system"):
            reply.target_system, reply.target_component = msg.get_srcSystem(), msg.get_srcComponent()
        self.ctx.send(k, reply, endpoint, addr)

    def _ping(self, k, msg, endpoint, addr) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            self.ctx.send(k, mavlink.MAVLink_ping_message(
                msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()), endpoint, addr)

    def _mission_list(self, k, msg, endpoint, addr) -> None:
        """No missions in the SITL: an empty list keeps ground stations happy."""
        self.ctx.send(k, mavlink.MAVLink_mission_count_message(
            msg.get_srcSystem(), msg.get_srcComponent(), 0, getattr(msg, "mission_type", 0)), endpoint, addr)


    def _ftp(self, k, msg, endpoint, addr) -> None:
        """No MAVLink FTP: NAK every request (FileNotFound) so clients fall back at once
        (MAVProxy then fetches parameters with PARAM_REQUEST_LIST)."""
        req = bytes(msg.payload)
        if len(req) < 12 or req[3] in (128, 129):  # not a request, or an ACK/NAK
            return
        seq = (int.from_bytes(req[0:2], "little") + 1) & 0xFFFF
        reply = bytearray(251)
        reply[0:2] = seq.to_bytes(2, "little")
        reply[2], reply[3], reply[4], reply[5] = req[2], 129, 1, req[3]  # session, NAK, size 1, req_opcode
        reply[12] = 10  # MAV_FTP_ERR_FILENOTFOUND
        self.ctx.send(k, mavlink.MAVLink_file_transfer_protocol_message(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(reply)), endpoint, addr)


def _name(param_id) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return param_id.split("\x00", 1)[0]
