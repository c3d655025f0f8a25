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

from companion.state import FleetState  # noqa: E402
from companion.frames import rot_to_euler_zyx, rot_to_quat_wxyz  # noqa: E402
from sim_bridge.sitl.autopilot import Autopilot  # noqa: E402
from sim_bridge.sitl.config import HomeConfig, StreamRates  # noqa: E402

EARTH_RADIUS_M = 6371000.0
MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_PX4 = 12

HEARTBEAT = 0
SYS_STATUS = 1
SYSTEM_TIME = 2
GPS_RAW_INT = 24
ATTITUDE = 30
ATTITUDE_QUATERNION = 31
LOCAL_POSITION_NED = 32
GLOBAL_POSITION_INT = 33
BATTERY_STATUS = 147
AUTOPILOT_VERSION = 148
HOME_POSITION = 242
EXTENDED_SYS_STATE = 245

STREAMS = (SYS_STATUS, SYSTEM_TIME, GPS_RAW_INT, ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED,
           GLOBAL_POSITION_INT, BATTERY_STATUS, HOME_POSITION, EXTENDED_SYS_STATE)
"""Messages streamed on simulation time (HEARTBEAT has its own wall-clock schedule)."""
REQUESTABLE = frozenset(STREAMS) | {HEARTBEAT, AUTOPILOT_VERSION}

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
        phase = (np.arange(n)[:, None] + 0.5) / max(n, 1)
        finite = np.where(np.isfinite(self.interval_s), self.interval_s, 0.0)
        self.next_s = start_s + phase * finite

    def set_interval(self, k: int, msgid: int, interval_s: float | None, now_s: float) -> None:
        """None = back to default; inf = off."""
        j = self.col[msgid]
        value = self.default_s[j] if interval_s is None else interval_s
        self.interval_s[k, j] = value
        if math.isfinite(value):
            self.next_s[k, j] = now_s

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


def ned_to_geodetic(home: HomeConfig, ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local NED (origin at home) -> lat_deg, lon_deg, alt_amsl_m (flat-earth, fine for km)."""
    lat = home.lat_deg + np.degrees(ned_m[..., 0] / EARTH_RADIUS_M)
    lon = home.lon_deg + np.degrees(ned_m[..., 1] / (EARTH_RADIUS_M * math.cos(math.radians(home.lat_deg))))
    return lat, lon, home.alt_amsl_m - ned_m[..., 2]


@dataclass
class Snapshot:
    """Derived per-vehicle quantities, computed once per tick for all vehicles."""

    time_boot_ms: int
    rpy: np.ndarray
    quat: np.ndarray
    lat_e7: np.ndarray
    lon_e7: np.ndarray
    alt_mm: np.ndarray


class TelemetryBuilder:
    """Builds every telemetry message of the SITL from the fleet state and autopilots."""

    def __init__(self, state: FleetState, autopilots: list[Autopilot], home: HomeConfig,
                 home_ned_m: np.ndarray, boot_wall_s: float | None = None):
        self.state = state
        self.aps = autopilots
        self.home = home
        self.home_ned_m = home_ned_m
        self.flight_time_s = np.zeros(state.n)
        self.boot_wall_s = time.time() if boot_wall_s is None else boot_wall_s
        hl, ho, ha = ned_to_geodetic(home, home_ned_m)
        self.home_lat_e7 = np.round(hl * 1e7).astype(np.int64)
        self.home_lon_e7 = np.round(ho * 1e7).astype(np.int64)
        self.home_alt_mm = np.round(ha * 1e3).astype(np.int64)
        self._snap: Snapshot | None = None

    def snapshot(self, sim_s: float) -> Snapshot:
        s = self.state
        lat, lon, alt = ned_to_geodetic(self.home, s.pos_ned_m)
        self._snap = Snapshot(
            time_boot_ms=int(round(sim_s * 1000)) & 0xFFFFFFFF, rpy=rot_to_euler_zyx(s.rot_body_to_ned),
            quat=rot_to_quat_wxyz(s.rot_body_to_ned), lat_e7=np.round(lat * 1e7).astype(np.int64),
            lon_e7=np.round(lon * 1e7).astype(np.int64), alt_mm=np.round(alt * 1e3).astype(np.int64))
        return self._snap

    def heartbeat(self, k: int) -> mavlink.MAVLink_message:
        ap = self.aps[k]
        return mavlink.MAVLink_heartbeat_message(MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, ap.base_mode,
                                                 ap.custom_mode, ap.system_status, 3)

    def statustext(self, severity: int, text: str) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_statustext_message(severity, text.encode()[:50])

    def autopilot_version(self, k: int) -> mavlink.MAVLink_message:
        caps = 8 | 16 | 128 | 256 | 8192  # COMMAND_INT, PARAM_ENCODE_BYTEWISE, SET_ATT/POS_TARGET, MAVLINK2
        return mavlink.MAVLink_autopilot_version_message(
            caps, (1 << 24) | (15 << 16) | (0 << 8) | 255, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8,
            0x26AC, 0x0011, 0x5D00000000 + self.aps[k].sysid)

    def build(self, k: int, msgid: int, sim_s: float) -> mavlink.MAVLink_message | None:
        """The current value of message msgid for vehicle k (None if not provided)."""
        if msgid == HEARTBEAT:
            return self.heartbeat(k)
        if msgid == AUTOPILOT_VERSION:
            return self.autopilot_version(k)
        snap = self._snap if self._snap is not None else self.snapshot(sim_s)
        s = self.state
        tb = snap.time_boot_ms
        if msgid == LOCAL_POSITION_NED:
            p, v = s.pos_ned_m[k], s.vel_ned_mps[k]
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
            v = s.vel_ned_mps[k]
            hdg = int(round(math.degrees(snap.rpy[k, 2]) * 100)) % 36000
            rel_mm = int(round((self.home_ned_m[k, 2] - s.pos_ned_m[k, 2]) * 1000))
            return mavlink.MAVLink_global_position_int_message(
                tb, int(snap.lat_e7[k]), int(snap.lon_e7[k]), int(snap.alt_mm[k]), rel_mm,
                _i16(v[0] * 100), _i16(v[1] * 100), _i16(v[2] * 100), hdg)
        if msgid == GPS_RAW_INT:
            v = s.vel_ned_mps[k]
            cog = int(round(math.degrees(math.atan2(v[1], v[0])) * 100)) % 36000
            return mavlink.MAVLink_gps_raw_int_message(
                int(sim_s * 1e6), 3, int(snap.lat_e7[k]), int(snap.lon_e7[k]), int(snap.alt_mm[k]),
                80, 120, min(65534, int(math.hypot(v[0], v[1]) * 100)), cog, 12)
        if msgid == SYS_STATUS:
            ap = self.aps[k]
            health = (SENSORS | (PREARM_CHECK if ap.prearm_failure(sim_s) is None else 0)
                      | (0 if ap.fence_breached else GEOFENCE))
            pct, mv = self._battery(k)
            present = SENSORS | PREARM_CHECK | GEOFENCE
            return mavlink.MAVLink_sys_status_message(present, present, health,
                                                      200, mv, -1, pct, 0, 0, 0, 0, 0, 0)
        if msgid == BATTERY_STATUS:
            pct, mv = self._battery(k)
            cells = [mv // BATTERY_CELLS] * BATTERY_CELLS + [65535] * (10 - BATTERY_CELLS)
            return mavlink.MAVLink_battery_status_message(0, 1, 1, 32767, cells, -1, -1, -1, pct)
        if msgid == EXTENDED_SYS_STATE:
            return mavlink.MAVLink_extended_sys_state_message(0, int(self.aps[k].landed_state))
        if msgid == HOME_POSITION:
            h = self.home_ned_m[k]
            return mavlink.MAVLink_home_position_message(
                int(self.home_lat_e7[k]), int(self.home_lon_e7[k]), int(self.home_alt_mm[k]),
                float(h[0]), float(h[1]), float(h[2]), [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(sim_s * 1e6))
        if msgid == SYSTEM_TIME:
            return mavlink.MAVLink_system_time_message(int(time.time() * 1e6), tb)
        return None

    def _battery(self, k: int) -> tuple[int, int]:
        frac = max(0.0, 1.0 - self.flight_time_s[k] / BATTERY_FLIGHT_S)
        return int(round(frac * 100)), int((3.5 + 0.7 * frac) * 1000 * BATTERY_CELLS)


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(float(x)))))
