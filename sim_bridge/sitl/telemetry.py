"""Telemetry: MAVLink messages built as data, and a batched per-message interval scheduler.

Builders return a message as data, `(MsgId, field values)`, through the lean codec's
named-field builders (companion.link.builder, resolved once here); the endpoint sender
task packs them. The scheduler keeps one (N, M) table of intervals and due times so a
tick costs one numpy comparison however many vehicles there are.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from companion.frames import ned_to_geodetic, rot_to_euler_zyx, rot_to_quat_wxyz
from companion.link.enums import (
    GpsFixType,
    MavBatteryFunction,
    MavBatteryType,
    MavProtocolCapability,
    MavSysStatusSensor,
    MavType,
    MsgId,
)
from companion.link.wire import Codec
from companion.mission import GeodeticOrigin
from companion.state import FleetState
from sim_bridge.sitl.autopilot import Autopilot
from sim_bridge.sitl.config import StreamRates
from sim_bridge.world.estimator import Estimator

Outgoing = tuple[int, tuple]
"""A message as data: (message id, its field values in declaration order)."""

HEARTBEAT = MsgId.HEARTBEAT
SYS_STATUS = MsgId.SYS_STATUS
SYSTEM_TIME = MsgId.SYSTEM_TIME
GPS_RAW_INT = MsgId.GPS_RAW_INT
ATTITUDE = MsgId.ATTITUDE
ATTITUDE_QUATERNION = MsgId.ATTITUDE_QUATERNION
LOCAL_POSITION_NED = MsgId.LOCAL_POSITION_NED
GLOBAL_POSITION_INT = MsgId.GLOBAL_POSITION_INT
GPS_GLOBAL_ORIGIN = MsgId.GPS_GLOBAL_ORIGIN
BATTERY_STATUS = MsgId.BATTERY_STATUS
AUTOPILOT_VERSION = MsgId.AUTOPILOT_VERSION
HOME_POSITION = MsgId.HOME_POSITION
EXTENDED_SYS_STATE = MsgId.EXTENDED_SYS_STATE

STREAMS = (SYS_STATUS, SYSTEM_TIME, GPS_RAW_INT, ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED,
           GLOBAL_POSITION_INT, BATTERY_STATUS, HOME_POSITION, EXTENDED_SYS_STATE)
"""Messages streamed on simulation time (HEARTBEAT has its own wall-clock schedule)."""
REQUESTABLE = frozenset(STREAMS) | {HEARTBEAT, AUTOPILOT_VERSION, GPS_GLOBAL_ORIGIN}
SENT = (*STREAMS, HEARTBEAT, AUTOPILOT_VERSION, GPS_GLOBAL_ORIGIN, MsgId.STATUSTEXT, MsgId.COMMAND_ACK,
        MsgId.MESSAGE_INTERVAL, MsgId.PARAM_VALUE, MsgId.TIMESYNC, MsgId.PING, MsgId.MISSION_COUNT,
        MsgId.FILE_TRANSFER_PROTOCOL)
"""Every message the SITL sends (their builders are resolved once)."""

_RATE_FIELD: dict[int, str] = {SYS_STATUS: "sys_status", SYSTEM_TIME: "system_time", GPS_RAW_INT: "gps_raw_int",
               ATTITUDE: "attitude", ATTITUDE_QUATERNION: "attitude_quaternion",
               LOCAL_POSITION_NED: "local_position_ned", GLOBAL_POSITION_INT: "global_position_int",
               BATTERY_STATUS: "battery_status", HOME_POSITION: "home_position",
               EXTENDED_SYS_STATE: "extended_sys_state", HEARTBEAT: "heartbeat"}

S = MavSysStatusSensor
SENSORS = (S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL | S.MAV_SYS_STATUS_SENSOR_3D_MAG
           | S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | S.MAV_SYS_STATUS_SENSOR_GPS
           | S.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | S.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
           | S.MAV_SYS_STATUS_SENSOR_YAW_POSITION | S.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
           | S.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
           | S.MAV_SYS_STATUS_AHRS | S.MAV_SYS_STATUS_SENSOR_BATTERY)
"""SYS_STATUS sensors present: gyro, accel, mag, baro, GPS, rate/attitude/yaw/alt/xy control,
motor outputs, AHRS, battery; PREARM_CHECK is in health only when pre-arm checks pass."""
PREARM_CHECK = S.MAV_SYS_STATUS_PREARM_CHECK
GEOFENCE = S.MAV_SYS_STATUS_GEOFENCE
GPS_SENSOR = S.MAV_SYS_STATUS_SENSOR_GPS
BATTERY_FLIGHT_S = 1200.0
BATTERY_CELLS = 4
_CAP = MavProtocolCapability
CAPABILITIES = (_CAP.MAV_PROTOCOL_CAPABILITY_COMMAND_INT | _CAP.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                | _CAP.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | _CAP.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
"""AUTOPILOT_VERSION capabilities of every vehicle, plus how integer parameters travel."""


def default_interval_s(rates: StreamRates, msgid: int) -> float:
    hz = getattr(rates, _RATE_FIELD[msgid])
    return math.inf if hz <= 0 else 1.0 / hz


class IntervalScheduler:
    """Due times of M message kinds for N vehicles on one clock."""

    def __init__(self, n: int, msgids: tuple[int, ...], default_s: list[float], start_s: float):
        self.msgids = msgids
        self.col = {m: j for j, m in enumerate(msgids)}
        self.default_s = np.asarray(default_s, dtype=float)
        self.interval_s = np.tile(self.default_s, (n, 1))
        self.phase = (np.arange(n) + 0.5) / max(n, 1)
        """Each vehicle's streams start this fraction of their interval late: the vehicles'
        messages spread over the interval instead of all leaving in one tick."""
        finite = np.where(np.isfinite(self.interval_s), self.interval_s, 0.0)
        self.next_s = start_s + self.phase[:, None] * finite

    def set_interval(self, k: int, msgid: int, interval_s: float | None, now_s: float) -> None:
        """None = back to default; inf = off."""
        j = self.col[msgid]
        value = self.default_s[j] if interval_s is None else interval_s
        self.interval_s[k, j] = value
        if math.isfinite(value):
            # On the vehicle's own grid (multiples of the interval, shifted by its phase):
            # streams with equal intervals fall in the same tick whenever they were requested
            # (a companion gets position and attitude of one instant together), and the
            # vehicles stay spread over the interval.
            off = self.phase[k] * value
            self.next_s[k, j] = math.ceil((now_s - off) / value - 1e-9) * value + off if value > 0 else now_s

    def interval(self, k: int, msgid: int) -> float:
        return float(self.interval_s[k, self.col[msgid]])

    def due(self, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(vehicle indices, column indices) due now; advances their next times."""
        # tolerate round-off between tick counts and accumulated intervals
        mask = (self.next_s <= now_s + 1e-9) & np.isfinite(self.interval_s)
        if not mask.any():
            return np.empty(0, int), np.empty(0, int)
        ks, js = np.nonzero(mask)
        nxt = self.next_s[ks, js] + self.interval_s[ks, js]
        late = nxt <= now_s + 1e-9
        nxt[late] = now_s + self.interval_s[ks, js][late]
        self.next_s[ks, js] = nxt
        return ks, js


def world_to_geodetic(home: GeodeticOrigin, ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World NED (tangent frame at home) -> lat_deg, lon_deg, alt_amsl_m on the WGS-84
    ellipsoid: the same conversion the agent uses (companion.frames)."""
    return ned_to_geodetic(ned_m, home.lat_deg, home.lon_deg, home.alt_amsl_m)


def quantised_origin(home: GeodeticOrigin, origin_ned_m: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int]]:
    """An EKF origin as GPS_GLOBAL_ORIGIN carries it (1e-7 deg, mm) and the world point
    that is exactly that origin, so LOCAL_POSITION_NED and the origin agree to the bit."""
    from companion.frames import geodetic_to_ned

    lat, lon, alt = world_to_geodetic(home, np.asarray(origin_ned_m, float))
    q = (int(round(float(lat) * 1e7)), int(round(float(lon) * 1e7)), int(round(float(alt) * 1e3)))
    exact = geodetic_to_ned(q[0] * 1e-7, q[1] * 1e-7, q[2] * 1e-3, home.lat_deg, home.lon_deg, home.alt_amsl_m)
    return exact, q


@dataclass
class Snapshot:
    """Derived per-vehicle quantities, computed once per tick for all vehicles."""

    time_boot_ms: int
    rpy: np.ndarray
    quat: np.ndarray
    pos_ned_m: np.ndarray
    """(N, 3) world NED positions as the estimator reports them."""
    vel_ned_mps: np.ndarray
    _geo: dict | None = None


class TelemetryBuilder:
    """Builds every telemetry message of the SITL from the fleet state and autopilots.

    Positions: the simulation runs in one world NED frame (the tangent frame at
    `home`); each vehicle reports LOCAL_POSITION_NED relative to its own EKF origin
    (autopilot.origin_ned_m, set at its first fix) and GLOBAL_POSITION_INT on the
    WGS-84 ellipsoid. Time: time_boot_ms and SYSTEM_TIME run on simulation time, with
    SYSTEM_TIME.time_unix_usec = epoch_unix_s + simulation time.
    """

    def __init__(self, state: FleetState, autopilots: list[Autopilot], home: GeodeticOrigin,
                 home_ned_m: np.ndarray, codec: Codec, epoch_unix_s: float | None = None,
                 estimator: Estimator | None = None, origin_e7: list | None = None,
                 flight_time_s: np.ndarray | None = None):
        self.state = state
        self.estimator = estimator
        """GPS/estimator errors and latency on what is reported (None: the true state)."""
        self.aps = autopilots
        self.home = home
        self.home_ned_m = home_ned_m
        self.build_fields = {m: codec.builder(m) for m in SENT}
        """MsgId -> its named-field builder (also used by the handler's replies)."""
        self.flight_time_s = np.zeros(state.n) if flight_time_s is None else flight_time_s
        """Armed time of each vehicle, s (the vehicles' own array: the battery model reads it)."""
        self.epoch_unix_s = float(round(time.time())) if epoch_unix_s is None else float(epoch_unix_s)
        hl, ho, ha = world_to_geodetic(home, home_ned_m)
        self.home_lat_e7 = np.round(hl * 1e7).astype(np.int64)
        self.home_lon_e7 = np.round(ho * 1e7).astype(np.int64)
        self.home_alt_mm = np.round(ha * 1e3).astype(np.int64)
        self.origin_e7: list[tuple[int, int, int] | None] = [None] * state.n if origin_e7 is None else origin_e7
        """GPS_GLOBAL_ORIGIN (lat 1e7, lon 1e7, alt mm) of each vehicle, None before its fix
        (the vehicles' own list)."""
        self._snap: Snapshot | None = None
        b = self.build_fields
        self._lpn, self._att, self._attq = b[LOCAL_POSITION_NED], b[ATTITUDE], b[ATTITUDE_QUATERNION]
        self._gpi, self._gps, self._sys = b[GLOBAL_POSITION_INT], b[GPS_RAW_INT], b[SYS_STATUS]

    def snapshot(self, sim_s: float) -> Snapshot:
        s = self.state
        if self.estimator is not None and self.estimator.cfg.active:
            pos, vel, rot = self.estimator.observe(sim_s, s.pos_ned_m, s.vel_ned_mps, s.rot_body_to_ned)
        else:
            pos, vel, rot = s.pos_ned_m, s.vel_ned_mps, s.rot_body_to_ned
        self._snap = Snapshot(time_boot_ms=int(round(sim_s * 1000)) & 0xFFFFFFFF,
                              rpy=rot_to_euler_zyx(rot), quat=rot_to_quat_wxyz(rot), pos_ned_m=pos, vel_ned_mps=vel)
        return self._snap

    def prepare_geodetic(self, ks) -> None:
        """Convert the vehicles ks to WGS-84 in one vectorised call (a tick's GLOBAL_POSITION_INT
        and GPS_RAW_INT then read it); pymap3d costs ~0.1 ms a call whatever its size."""
        snap = self._snap
        if snap is None or not len(ks):
            return
        if snap._geo is None:
            snap._geo = {}
        ks = [k for k in ks if k not in snap._geo]
        if not ks:
            return
        lat, lon, alt = world_to_geodetic(self.home, snap.pos_ned_m[ks])
        for k, a, b, c in zip(ks, np.round(lat * 1e7).tolist(), np.round(lon * 1e7).tolist(),
                              np.round(alt * 1e3).tolist()):
            snap._geo[k] = (int(a), int(b), int(c))

    def _geodetic(self, snap: Snapshot, k: int) -> tuple[int, int, int]:
        """lat_e7, lon_e7, alt_mm of vehicle k now (computed once per snapshot and vehicle)."""
        if snap._geo is None or k not in snap._geo:
            self._snap = snap
            self.prepare_geodetic([k])
        assert snap._geo is not None  # (prepare_geodetic made it)
        return snap._geo[k]

    def heartbeat(self, k: int) -> Outgoing:
        ap = self.aps[k]
        base_mode, custom_mode, system_status = ap.heartbeat.fields()
        return HEARTBEAT, self.build_fields[HEARTBEAT](
            type=MavType.MAV_TYPE_QUADROTOR, autopilot=ap.dialect.autopilot_id, base_mode=base_mode,
            custom_mode=custom_mode, system_status=system_status)

    def statustext(self, severity: int, text: str) -> Outgoing:
        return MsgId.STATUSTEXT, self.build_fields[MsgId.STATUSTEXT](severity=severity, text=text.encode()[:50])

    def gps_global_origin(self, k: int, sim_s: float) -> Outgoing | None:
        o = self.origin_e7[k]
        if o is None:
            return None
        return GPS_GLOBAL_ORIGIN, self.build_fields[GPS_GLOBAL_ORIGIN](
            latitude=o[0], longitude=o[1], altitude=o[2], time_usec=int(sim_s * 1e6))

    def autopilot_version(self, k: int) -> Outgoing:
        # how integer parameters travel: PX4 byte-wise (PARAM_ENCODE_BYTEWISE), ArduPilot C-cast by value
        enc = _CAP.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE if self.aps[k].dialect.param_encoding == "bytewise" \
            else _CAP.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | _CAP.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
        return AUTOPILOT_VERSION, self.build_fields[AUTOPILOT_VERSION](
            capabilities=CAPABILITIES | enc, flight_sw_version=(1 << 24) | (15 << 16) | (0 << 8) | 255,
            vendor_id=0x26AC, product_id=0x0011, uid=0x5D00000000 + self.aps[k].sysid)

    def build(self, k: int, msgid: int, sim_s: float) -> Outgoing | None:
        """The current value of message msgid for vehicle k (None if not provided now)."""
        if msgid == HEARTBEAT:
            return self.heartbeat(k)
        if msgid == AUTOPILOT_VERSION:
            return self.autopilot_version(k)
        if msgid == GPS_GLOBAL_ORIGIN:
            return self.gps_global_origin(k, sim_s)
        snap = self._snap
        if snap is None or snap.time_boot_ms != int(round(sim_s * 1000)) & 0xFFFFFFFF:
            snap = self.snapshot(sim_s)  # a requested message between streams: not the last stream's time
        s, ap = self.state, self.aps[k]
        tb = snap.time_boot_ms
        if msgid == LOCAL_POSITION_NED:
            if ap.origin_ned_m is None:
                return None  # no local position before the EKF has an origin
            p, v = snap.pos_ned_m[k] - ap.origin_ned_m, snap.vel_ned_mps[k]
            return msgid, self._lpn(time_boot_ms=tb, x=float(p[0]), y=float(p[1]), z=float(p[2]), vx=float(v[0]),
                                    vy=float(v[1]), vz=float(v[2]))
        if msgid == ATTITUDE:
            r, w = snap.rpy[k], s.omega_body_radps[k]
            return msgid, self._att(time_boot_ms=tb, roll=float(r[0]), pitch=float(r[1]), yaw=float(r[2]),
                                    rollspeed=float(w[0]), pitchspeed=float(w[1]), yawspeed=float(w[2]))
        if msgid == ATTITUDE_QUATERNION:
            q, w = snap.quat[k], s.omega_body_radps[k]
            return msgid, self._attq(time_boot_ms=tb, q1=float(q[0]), q2=float(q[1]), q3=float(q[2]), q4=float(q[3]),
                                     rollspeed=float(w[0]), pitchspeed=float(w[1]), yawspeed=float(w[2]))
        if msgid == GLOBAL_POSITION_INT:
            if ap.origin_ned_m is None:
                return None
            lat, lon, alt = self._geodetic(snap, k)
            v = snap.vel_ned_mps[k]
            hdg = int(round(math.degrees(snap.rpy[k, 2]) * 100)) % 36000
            rel_mm = int(round((self.home_ned_m[k, 2] - snap.pos_ned_m[k, 2]) * 1000))
            return msgid, self._gpi(time_boot_ms=tb, lat=lat, lon=lon, alt=alt, relative_alt=rel_mm,
                                    vx=_i16(v[0] * 100), vy=_i16(v[1] * 100), vz=_i16(v[2] * 100), hdg=hdg)
        if msgid == GPS_RAW_INT:
            v = snap.vel_ned_mps[k]
            if ap.origin_ned_m is None:
                return msgid, self._gps(time_usec=int(sim_s * 1e6), fix_type=GpsFixType.GPS_FIX_TYPE_NO_FIX,
                                        eph=65535, epv=65535, vel=65535, cog=65535)
            lat, lon, alt = self._geodetic(snap, k)
            cog = int(round(math.degrees(math.atan2(v[1], v[0])) * 100)) % 36000
            return msgid, self._gps(time_usec=int(sim_s * 1e6), fix_type=GpsFixType.GPS_FIX_TYPE_3D_FIX, lat=lat,
                                    lon=lon, alt=alt, eph=80, epv=120, vel=min(65534, int(math.hypot(v[0], v[1]) * 100)),
                                    cog=cog, satellites_visible=12)
        if msgid == SYS_STATUS:
            health = (SENSORS | (PREARM_CHECK if ap.prearm_failure(sim_s) is None else 0)
                      | (0 if ap.fence_breached else GEOFENCE))
            if ap.origin_ned_m is None:
                health &= ~GPS_SENSOR  # GPS not healthy before the fix
            pct, mv = self._battery(k)
            present = SENSORS | PREARM_CHECK | GEOFENCE
            return msgid, self._sys(onboard_control_sensors_present=present, onboard_control_sensors_enabled=present,
                                    onboard_control_sensors_health=health, load=200, voltage_battery=mv,
                                    current_battery=-1, battery_remaining=pct)
        if msgid == BATTERY_STATUS:
            pct, mv = self._battery(k)
            cells = (mv // BATTERY_CELLS,) * BATTERY_CELLS + (65535,) * (10 - BATTERY_CELLS)
            return msgid, self.build_fields[BATTERY_STATUS](
                id=0, battery_function=MavBatteryFunction.MAV_BATTERY_FUNCTION_ALL,
                type=MavBatteryType.MAV_BATTERY_TYPE_LIPO, temperature=32767, voltages=cells, current_battery=-1,
                current_consumed=-1, energy_consumed=-1, battery_remaining=pct)
        if msgid == EXTENDED_SYS_STATE:
            return msgid, self.build_fields[EXTENDED_SYS_STATE](landed_state=int(ap.landed_state))
        if msgid == HOME_POSITION:
            h = self.home_ned_m[k] - (ap.origin_ned_m if ap.origin_ned_m is not None else 0.0)
            return msgid, self.build_fields[HOME_POSITION](
                latitude=int(self.home_lat_e7[k]), longitude=int(self.home_lon_e7[k]), altitude=int(self.home_alt_mm[k]),
                x=float(h[0]), y=float(h[1]), z=float(h[2]), q=(1.0, 0.0, 0.0, 0.0), time_usec=int(sim_s * 1e6))
        if msgid == SYSTEM_TIME:
            return msgid, self.build_fields[SYSTEM_TIME](
                time_unix_usec=int(round((self.epoch_unix_s + sim_s) * 1e6)), time_boot_ms=tb)
        return None

    def _battery(self, k: int) -> tuple[int, int]:
        frac = max(0.0, 1.0 - self.flight_time_s[k] / BATTERY_FLIGHT_S)
        return int(round(frac * 100)), int((3.5 + 0.7 * frac) * 1000 * BATTERY_CELLS)


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(float(x)))))
