"""Telemetry: MAVLink messages built as data, and a batched per-message interval scheduler.

Builders return pymavlink message objects (not packed); the endpoint sender task
packs them. The scheduler keeps one (N, M) table of intervals and due times so a
tick costs one numpy comparison however many vehicles there are.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.frames import ned_to_geodetic, rot_to_euler_zyx, rot_to_quat_wxyz  # noqa: E402
from companion.state import FleetState  # noqa: E402
from sim_bridge.estimator import Estimator  # noqa: E402
from sim_bridge.sitl.autopilot import Autopilot  # noqa: E402
from sim_bridge.sitl.config import HomeConfig, StreamRates  # noqa: E402

MAV_TYPE_QUADROTOR = 2

HEARTBEAT = 0
SYS_STATUS = 1
SYSTEM_TIME = 2
GPS_RAW_INT = 24
ATTITUDE = 30
ATTITUDE_QUATERNION = 31
LOCAL_POSITION_NED = 32
GLOBAL_POSITION_INT = 33
GPS_GLOBAL_ORIGIN = 49
BATTERY_STATUS = 147
AUTOPILOT_VERSION = 148
HOME_POSITION = 242
EXTENDED_SYS_STATE = 245

STREAMS = (SYS_STATUS, SYSTEM_TIME, GPS_RAW_INT, ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED,
           GLOBAL_POSITION_INT, BATTERY_STATUS, HOME_POSITION, EXTENDED_SYS_STATE)
"""Messages streamed on simulation time (HEARTBEAT has its own wall-clock schedule)."""
REQUESTABLE = frozenset(STREAMS) | {HEARTBEAT, AUTOPILOT_VERSION, GPS_GLOBAL_ORIGIN}

_RATE_FIELD = {SYS_STATUS: "sys_status", SYSTEM_TIME: "system_time", GPS_RAW_INT: "gps_raw_int",
               ATTITUDE: "attitude", ATTITUDE_QUATERNION: "attitude_quaternion",
               LOCAL_POSITION_NED: "local_position_ned", GLOBAL_POSITION_INT: "global_position_int",
               BATTERY_STATUS: "battery_status", HOME_POSITION: "home_position",
               EXTENDED_SYS_STATE: "extended_sys_state", HEARTBEAT: "heartbeat"}

# SYS_STATUS sensor bits: gyro, accel, mag, baro, GPS, rate/attitude/yaw/alt/xy control,
# motor outputs, AHRS, battery; PREARM_CHECK only in health when pre-arm checks pass.
SENSORS = (0x1 | 0x2 | 0x4 | 0x8 | 0x20 | 0x400 | 0x800 | 0x1000 | 0x2000 | 0x4000 | 0x8000
           | 0x200000 | 0x2000000)
PREARM_CHECK = 0x10000000
GEOFENCE = 0x100000
BATTERY_FLIGHT_S = 1200.0
BATTERY_CELLS = 4


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


def world_to_geodetic(home: HomeConfig, ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World NED (tangent frame at home) -> lat_deg, lon_deg, alt_amsl_m on the WGS-84
    ellipsoid: the same conversion the agent uses (companion.frames)."""
    return ned_to_geodetic(ned_m, home.lat_deg, home.lon_deg, home.alt_amsl_m)


def quantised_origin(home: HomeConfig, origin_ned_m: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int]]:
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

    def __init__(self, state: FleetState, autopilots: list[Autopilot], home: HomeConfig,
                 home_ned_m: np.ndarray, epoch_unix_s: float | None = None, estimator: Estimator | None = None):
        self.state = state
        self.estimator = estimator
        """GPS/estimator errors and latency on what is reported (None: the true state)."""
        self.aps = autopilots
        self.home = home
        self.home_ned_m = home_ned_m
        self.flight_time_s = np.zeros(state.n)
        self.epoch_unix_s = float(round(time.time())) if epoch_unix_s is None else float(epoch_unix_s)
        hl, ho, ha = world_to_geodetic(home, home_ned_m)
        self.home_lat_e7 = np.round(hl * 1e7).astype(np.int64)
        self.home_lon_e7 = np.round(ho * 1e7).astype(np.int64)
        self.home_alt_mm = np.round(ha * 1e3).astype(np.int64)
        self.origin_e7: list[tuple[int, int, int] | None] = [None] * state.n
        """GPS_GLOBAL_ORIGIN (lat 1e7, lon 1e7, alt mm) of each vehicle, None before its fix."""
        self._snap: Snapshot | None = None

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
        return snap._geo[k]

    def heartbeat(self, k: int) -> mavlink.MAVLink_message:
        ap = self.aps[k]
        return mavlink.MAVLink_heartbeat_message(MAV_TYPE_QUADROTOR, ap.dialect.autopilot_id, ap.base_mode,
                                                 ap.custom_mode, ap.system_status, 3)

    def statustext(self, severity: int, text: str) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_statustext_message(severity, text.encode()[:50])

    def gps_global_origin(self, k: int, sim_s: float) -> mavlink.MAVLink_message | None:
        o = self.origin_e7[k]
        if o is None:
            return None
        return mavlink.MAVLink_gps_global_origin_message(o[0], o[1], o[2], int(sim_s * 1e6))

    def autopilot_version(self, k: int) -> mavlink.MAVLink_message:
        # COMMAND_INT, SET_ATT/POS_TARGET, MAVLINK2 + how integer parameters travel
        # (PX4: PARAM_ENCODE_BYTEWISE 16; ArduPilot: PARAM_FLOAT 2, C-cast by value).
        caps = 8 | 128 | 256 | 8192 | (16 if self.aps[k].dialect.param_encoding == "bytewise" else 2)
        return mavlink.MAVLink_autopilot_version_message(
            caps, (1 << 24) | (15 << 16) | (0 << 8) | 255, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8,
            0x26AC, 0x0011, 0x5D00000000 + self.aps[k].sysid)

    def build(self, k: int, msgid: int, sim_s: float) -> mavlink.MAVLink_message | None:
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
            return mavlink.MAVLink_local_position_ned_message(tb, float(p[0]), float(p[1]), float(p[2]),
                                                              float(v[0]), float(v[1]), float(v[2]))
        if msgid == ATTITUDE:
            r, w = snap.rpy[k], s.omega_body_radps[k]
            return mavlink.MAVLink_attitude_message(tb, float(r[0]), float(r[1]), float(r[2]),
                                                    float(w[0]), float(w[1]), float(w[2]))
        if msgid == ATTITUDE_QUATERNION:
            q, w = snap.quat[k], s.omega_body_radps[k]
            return mavlink.MAVLink_attitude_quaternion_message(tb, float(q[0]), float(q[1]), float(q[2]),
                                                               float(q[3]), float(w[0]), float(w[1]), float(w[2]))
        if msgid == GLOBAL_POSITION_INT:
            if ap.origin_ned_m is None:
                return None
            lat, lon, alt = self._geodetic(snap, k)
            v = snap.vel_ned_mps[k]
            hdg = int(round(math.degrees(snap.rpy[k, 2]) * 100)) % 36000
            rel_mm = int(round((self.home_ned_m[k, 2] - snap.pos_ned_m[k, 2]) * 1000))
            return mavlink.MAVLink_global_position_int_message(
                tb, lat, lon, alt, rel_mm, _i16(v[0] * 100), _i16(v[1] * 100),
                _i16(v[2] * 100), hdg)
        if msgid == GPS_RAW_INT:
            v = snap.vel_ned_mps[k]
            if ap.origin_ned_m is None:
                return mavlink.MAVLink_gps_raw_int_message(int(sim_s * 1e6), 1, 0, 0, 0, 65535, 65535, 65535,
                                                           65535, 0)
            lat, lon, alt = self._geodetic(snap, k)
            cog = int(round(math.degrees(math.atan2(v[1], v[0])) * 100)) % 36000
            return mavlink.MAVLink_gps_raw_int_message(
                int(sim_s * 1e6), 3, lat, lon, alt, 80, 120,
                min(65534, int(math.hypot(v[0], v[1]) * 100)), cog, 12)
        if msgid == SYS_STATUS:
            health = (SENSORS | (PREARM_CHECK if ap.prearm_failure(sim_s) is None else 0)
                      | (0 if ap.fence_breached else GEOFENCE))
            if ap.origin_ned_m is None:
                health &= ~0x20  # GPS not healthy before the fix
            pct, mv = self._battery(k)
            present = SENSORS | PREARM_CHECK | GEOFENCE
            return mavlink.MAVLink_sys_status_message(present, present, health,
                                                      200, mv, -1, pct, 0, 0, 0, 0, 0, 0)
        if msgid == BATTERY_STATUS:
            pct, mv = self._battery(k)
            cells = [mv // BATTERY_CELLS] * BATTERY_CELLS + [65535] * (10 - BATTERY_CELLS)
            return mavlink.MAVLink_battery_status_message(0, 1, 1, 32767, cells, -1, -1, -1, pct)
        if msgid == EXTENDED_SYS_STATE:
            return mavlink.MAVLink_extended_sys_state_message(0, int(ap.landed_state))
        if msgid == HOME_POSITION:
            h = self.home_ned_m[k] - (ap.origin_ned_m if ap.origin_ned_m is not None else 0.0)
            return mavlink.MAVLink_home_position_message(
                int(self.home_lat_e7[k]), int(self.home_lon_e7[k]), int(self.home_alt_mm[k]),
                float(h[0]), float(h[1]), float(h[2]), [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(sim_s * 1e6))
        if msgid == SYSTEM_TIME:
            return mavlink.MAVLink_system_time_message(int(round((self.epoch_unix_s + sim_s) * 1e6)), tb)
        return None

    def _battery(self, k: int) -> tuple[int, int]:
        frac = max(0.0, 1.0 - self.flight_time_s[k] / BATTERY_FLIGHT_S)
        return int(round(frac * 100)), int((3.5 + 0.7 * frac) * 1000 * BATTERY_CELLS)


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(float(x)))))
