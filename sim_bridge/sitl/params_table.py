"""Parameter table of one simulated vehicle, in its autopilot's dialect.

The table really drives the simulation: gains, limits, failsafe timers and the
take-off altitude are read from it by the autopilot and the physics loop. PX4
vehicles carry PX4 names and encode integers byte-wise; ArduPilot vehicles carry
ArduCopter names (in ArduPilot units: cm/s, cm) and encode integers by value
(companion.link.params). `Knobs` reads the values the state machine needs under
one set of names and SI units, whichever dialect the table speaks.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from companion.link.dialects import AutopilotDialect
from companion.link.dialects.ardupilot import GUID_OPTIONS_THRUST
from companion.link.limits import SetpointLimits
from companion.link.params import (
    INT_FORMATS,
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    Encoding,
    decode_param_value,
    encode_param_value,
)
from companion.params import GeometricGains, InnerLoopConfig
from sim_bridge.autopilot_model import THROW_RATE_RADPS, THROW_SPEED_MPS, THROW_TILT_DEG

__all__ = ["ParamSpec", "ParamTable", "Knobs", "default_specs", "MAV_PARAM_TYPE_INT32", "MAV_PARAM_TYPE_REAL32",
           "encode_param_value", "decode_param_value"]


@dataclass(frozen=True)
class ParamSpec:
    name: str
    param_type: int
    default: float
    min_value: float
    max_value: float
    description: str


def _f(name, default, lo, hi, desc) -> ParamSpec:
    return ParamSpec(name, MAV_PARAM_TYPE_REAL32, float(default), float(lo), float(hi), desc)


def _i(name, default, lo, hi, desc) -> ParamSpec:
    return ParamSpec(name, MAV_PARAM_TYPE_INT32, float(default), float(lo), float(hi), desc)


def _simulator_specs(inner: InnerLoopConfig) -> list[ParamSpec]:
    """The simulated inner loop and throw recovery (both dialects)."""
    g = inner.geometric
    return [
        _f("SD_ACC_MAX", g.acc_max_mps2, 0.1, 100.0, "norm limit of the commanded acceleration, m/s^2"),
        _f("SD_GEO_KX", g.kx_per_s2, 0.0, 1000.0, "geometric position gain per unit mass, 1/s^2"),
        _f("SD_GEO_KV", g.kv_per_s, 0.0, 1000.0, "geometric velocity gain per unit mass, 1/s"),
        _f("SD_GEO_KR", g.kR_per_s2, 1e-3, 1e5, "geometric attitude gain per unit inertia, 1/s^2"),
        _f("SD_GEO_KOM", g.kOmega_per_s, 1e-3, 1e4, "geometric body-rate gain per unit inertia, 1/s"),
        _f("SD_THR_TILT", THROW_TILT_DEG, 1.0, 90.0, "throw: tilt below which the vehicle counts as upright, deg"),
        _f("SD_THR_RATE", THROW_RATE_RADPS, 0.01, 10.0, "throw: body-rate norm below which it counts as stable, rad/s"),
        _f("SD_THR_SPEED", THROW_SPEED_MPS, 0.01, 10.0, "throw: speed below which it counts as recovered, m/s"),
    ]


def _px4_specs(inner: InnerLoopConfig, sysid: int, hover_thrust: float) -> list[ParamSpec]:
    return [
        _f("MIS_TAKEOFF_ALT", 2.5, 0.0, 1000.0, "take-off altitude above home, m"),
        _f("MPC_TKO_SPEED", 1.5, 0.1, 10.0, "take-off climb speed, m/s"),
        _f("MPC_LAND_SPEED", 0.7, 0.1, 5.0, "landing descent speed, m/s"),
        _f("MPC_TILTMAX_AIR", inner.geometric.tilt_max_deg, 1.0, 89.0, "tilt limit of the position controller, deg"),
        _f("MPC_THR_HOVER", hover_thrust, 0.05, 0.95, "normalised collective thrust that hovers"),
        _f("MPC_THR_MIN", 0.12, 0.0, 1.0, "offboard thrust floor (normalised)"),
        _f("MPC_THR_MAX", 1.0, 0.0, 1.0, "offboard thrust ceiling (normalised)"),
        _f("MPC_XY_VEL_MAX", 12.0, 0.0, 20.0, "horizontal speed limit of offboard velocity setpoints, m/s"),
        _f("MPC_Z_VEL_MAX_UP", 3.0, 0.5, 8.0, "climb speed limit, m/s"),
        _f("MPC_Z_VEL_MAX_DN", 1.5, 0.5, 4.0, "descent speed limit, m/s"),
        _f("MC_ROLLRATE_MAX", 220.0, 0.0, 1800.0, "roll rate limit, deg/s"),
        _f("MC_PITCHRATE_MAX", 220.0, 0.0, 1800.0, "pitch rate limit, deg/s"),
        _f("MC_YAWRATE_MAX", 200.0, 0.0, 1800.0, "yaw rate limit, deg/s"),
        _f("COM_OF_LOSS_T", 1.0, 0.0, 60.0, "offboard setpoint timeout before Hold, s"),
        _f("SD_OBL_LAND_T", 5.0, -1.0, 3600.0, "time in Hold after offboard loss before Land, s (-1 never)"),
        _f("COM_DISARM_PRFLT", 10.0, -1.0, 20.0, "disarm if armed and not taken off within, s (<=0 off)"),
        _f("COM_DISARM_LAND", 2.0, -1.0, 20.0, "disarm after landing detected, s (<0 off)"),
        _i("GF_ACTION", 2, 0, 5, "geofence action: 0 none, 1 warn, 2 hold, 3 return(=land), 4 terminate, 5 land"),
        _f("GF_MAX_HOR_DIST", 0.0, 0.0, 1e6, "geofence horizontal radius from home, m (0 off)"),
        _f("GF_MAX_VER_DIST", 0.0, 0.0, 1e6, "geofence maximum height above home, m (0 off)"),
        _i("COM_THROW_EN", 1, 0, 1, "stabilise after carrier release (throw launch)"),
        _i("SYS_FAILURE_EN", 0, 0, 1, "accept MAV_CMD_INJECT_FAILURE (motor off only in the SITL)"),
        _i("MAV_SYS_ID", sysid, 1, 250, "MAVLink system id (read only in the SITL)"),
        _i("MAV_COMP_ID", 1, 1, 250, "MAVLink component id (read only in the SITL)"),
        _i("MAV_TYPE", 2, 0, 30, "vehicle type (quadrotor)"),
        _i("SYS_AUTOSTART", 4001, 0, 9999999, "airframe (generic quadrotor x)"),
    ]


def _ardupilot_specs(inner: InnerLoopConfig, sysid: int, hover_thrust: float) -> list[ParamSpec]:
    return [
        _f("PILOT_TKOFF_ALT", 250.0, 0.0, 100000.0, "take-off altitude when NAV_TAKEOFF gives none, cm"),
        _f("WPNAV_SPEED_UP", 250.0, 10.0, 1000.0, "climb speed, cm/s"),
        _f("WPNAV_SPEED_DN", 150.0, 10.0, 500.0, "descent speed, cm/s"),
        _f("LAND_SPEED", 50.0, 30.0, 200.0, "final landing speed, cm/s"),
        _f("ANGLE_MAX", inner.geometric.tilt_max_deg * 100.0, 1000.0, 8000.0, "tilt limit, centidegrees"),
        _f("MOT_THST_HOVER", hover_thrust, 0.05, 0.95, "normalised collective thrust that hovers"),
        _f("GUID_TIMEOUT", 3.0, 0.1, 5.0, "GUIDED: setpoint timeout, s (then stop / level)"),
        _i("GUID_OPTIONS", 0, 0, 65535, "GUIDED options; bit 3 (8): SET_ATTITUDE_TARGET thrust is thrust"),
        _f("DISARM_DELAY", 10.0, 0.0, 127.0, "disarm this long after landing or arming without take-off, s"),
        _i("THROW_NEXTMODE", 18, 3, 18, "mode after a successful throw (4 GUIDED, 5 LOITER, 17 BRAKE, 18 stay)"),
        _i("THROW_TYPE", 1, 0, 1, "throw type: 0 upward, 1 drop (a carrier release is a drop)"),
        _i("SYSID_THISMAV", sysid, 1, 255, "MAVLink system id (read only in the SITL)"),
        _i("FRAME_CLASS", 1, 0, 20, "frame class (quad)"),
    ]


def default_specs(inner: InnerLoopConfig, sysid: int, dialect: str = "px4",
                  hover_thrust: float = 0.5) -> tuple[ParamSpec, ...]:
    """All parameters of one vehicle, sorted by name (autopilots serve them in name order).

    Args:
        hover_thrust: the simulated airframe's hover thrust as a fraction of maximum.
    """
    specific = _px4_specs if dialect == "px4" else _ardupilot_specs
    return tuple(sorted(_simulator_specs(inner) + specific(inner, sysid, hover_thrust), key=lambda s: s.name))


READ_ONLY = frozenset({"MAV_SYS_ID", "MAV_COMP_ID", "MAV_TYPE", "SYS_AUTOSTART", "SYSID_THISMAV", "FRAME_CLASS",
                       "MPC_THR_HOVER", "MOT_THST_HOVER"})
"""Identity and the airframe's hover thrust (a property of the simulated vehicle)."""


class ParamTable:
    """Parameter values of one vehicle; index order is name order.

    Args:
        specs: the parameters (default_specs).
        encoding: how integers travel ("bytewise" PX4, "c_cast" ArduPilot).
    """

    def __init__(self, specs: tuple[ParamSpec, ...], encoding: Encoding = "bytewise"):
        self.specs = specs
        self.encoding = encoding
        self._index = {s.name: i for i, s in enumerate(specs)}
        self._values = [s.default for s in specs]
        self.version = 0
        """Incremented on every accepted change (lets consumers cache derived objects)."""

    def __len__(self) -> int:
        return len(self.specs)

    def __getitem__(self, name: str) -> float:
        return self._values[self._index[name]]

    def get(self, name: str, default: float) -> float:
        idx = self._index.get(name)
        return default if idx is None else self._values[idx]

    def index_of(self, name: str) -> int | None:
        return self._index.get(name)

    def wire(self, index: int) -> tuple[str, float, int]:
        """(name, encoded float, MAV_PARAM_TYPE) of the parameter at index."""
        s = self.specs[index]
        return s.name, encode_param_value(self._values[index], s.param_type, self.encoding), s.param_type

    def set_wire(self, name: str, wire: float, param_type: int) -> int | None:
        """Apply a PARAM_SET; returns the index to echo, or None when the name is unknown.

        A value that is not finite, outside [min, max] or read-only is refused:
        the echo then carries the unchanged value (the sender sees it did not take).
        """
        idx = self._index.get(name)
        if idx is None:
            return None
        spec = self.specs[idx]
        known = param_type in INT_FORMATS or param_type == MAV_PARAM_TYPE_REAL32
        try:
            value = decode_param_value(wire, param_type if known else spec.param_type, self.encoding)
        except (struct.error, KeyError, ValueError, OverflowError):
            return idx
        if spec.param_type != MAV_PARAM_TYPE_REAL32:
            if not math.isfinite(value):
                return idx
            value = float(round(value))
        if name in READ_ONLY or not math.isfinite(value) or not spec.min_value <= value <= spec.max_value:
            return idx
        if self._values[idx] != value:
            self._values[idx] = value
            self.version += 1
        return idx

    def set(self, name: str, value: float, force: bool = False) -> bool:
        """Direct (config/test) set with the same checks as PARAM_SET; force also sets
        read-only parameters (the SITL's own start-up configuration)."""
        spec = self.specs[self._index[name]]
        if force and spec.min_value <= value <= spec.max_value:
            if self._values[self._index[name]] != value:
                self._values[self._index[name]] = float(value)
                self.version += 1
            return True
        before = self.version
        self.set_wire(name, encode_param_value(value, spec.param_type, self.encoding), spec.param_type)
        return self.version != before or self[name] == value

    def inner_loop(self, base: InnerLoopConfig) -> InnerLoopConfig:
        """The inner-loop config this table asks for (gains and limits from the table)."""
        tilt = self._tilt_max_deg()
        return InnerLoopConfig(
            controller=base.controller,
            geometric=GeometricGains(
                kx_per_s2=self["SD_GEO_KX"], kv_per_s=self["SD_GEO_KV"],
                kR_per_s2=self["SD_GEO_KR"], kOmega_per_s=self["SD_GEO_KOM"],
                tilt_max_deg=min(tilt, 89.0), acc_max_mps2=self["SD_ACC_MAX"],
            ),
            pid=base.pid,
        )

    def _tilt_max_deg(self) -> float:
        return self["MPC_TILTMAX_AIR"] if "MPC_TILTMAX_AIR" in self._index else self["ANGLE_MAX"] / 100.0

    def gain_key(self) -> tuple:
        """The values that select a physics group (vehicles with equal keys share one)."""
        tilt = self._tilt_max_deg()
        return (self["SD_GEO_KX"], self["SD_GEO_KV"], self["SD_GEO_KR"], self["SD_GEO_KOM"], tilt, self["SD_ACC_MAX"])


class Knobs:
    """What the autopilot state machine reads, in SI units, from either dialect's table."""

    def __init__(self, table: ParamTable, dialect: AutopilotDialect):
        self.t = table
        self.dialect = dialect
        self.px4 = dialect.name == "px4"
        self._lim_version = -1
        self._lim = SetpointLimits()

    @property
    def takeoff_alt_m(self) -> float:
        return self.t["MIS_TAKEOFF_ALT"] if self.px4 else self.t["PILOT_TKOFF_ALT"] / 100.0

    @property
    def takeoff_speed_mps(self) -> float:
        return self.t["MPC_TKO_SPEED"] if self.px4 else self.t["WPNAV_SPEED_UP"] / 100.0

    @property
    def descent_speed_mps(self) -> float:
        return self.t["MPC_LAND_SPEED"] if self.px4 else self.t["WPNAV_SPEED_DN"] / 100.0

    @property
    def land_speed_mps(self) -> float:
        return self.t["MPC_LAND_SPEED"] if self.px4 else self.t["LAND_SPEED"] / 100.0

    @property
    def offboard_timeout_s(self) -> float:
        return self.t[self.dialect.setpoint_timeout_param]

    @property
    def loss_land_after_s(self) -> float:
        """Hold this long after an offboard loss, then land (PX4); < 0: never (ArduPilot stays in GUIDED)."""
        return self.t["SD_OBL_LAND_T"] if self.px4 else -1.0

    @property
    def disarm_preflight_s(self) -> float:
        return self.t["COM_DISARM_PRFLT"] if self.px4 else self.t["DISARM_DELAY"]

    @property
    def disarm_land_s(self) -> float:
        return self.t["COM_DISARM_LAND"] if self.px4 else self.t["DISARM_DELAY"]

    @property
    def throw_enabled(self) -> bool:
        return self.t["COM_THROW_EN"] >= 1 if self.px4 else True

    @property
    def hover_thrust(self) -> float:
        return self.t[self.dialect.hover_thrust_param]

    @property
    def thrust_is_thrust(self) -> bool:
        """SET_ATTITUDE_TARGET.thrust is thrust (PX4 always; ArduPilot with GUID_OPTIONS bit 3)."""
        return self.px4 or (int(self.t["GUID_OPTIONS"]) & GUID_OPTIONS_THRUST) != 0

    def limits(self) -> SetpointLimits:
        """Offboard setpoint limits (companion.link.limits): PX4's parameters; ArduPilot
        keeps PX4's defaults except its own tilt limit (ANGLE_MAX). Cached per table version."""
        t = self.t
        if self._lim_version == t.version:
            return self._lim
        self._lim_version, self._lim = t.version, self._limits()
        return self._lim

    def _limits(self) -> SetpointLimits:
        t = self.t
        tilt = math.radians(t._tilt_max_deg())
        if not self.px4:
            return SetpointLimits(tilt_max_rad=tilt)
        d = math.radians
        return SetpointLimits(
            xy_vel_max_mps=t["MPC_XY_VEL_MAX"], z_vel_max_up_mps=t["MPC_Z_VEL_MAX_UP"],
            z_vel_max_dn_mps=t["MPC_Z_VEL_MAX_DN"], tilt_max_rad=tilt, thr_min=t["MPC_THR_MIN"],
            thr_max=max(t["MPC_THR_MIN"], t["MPC_THR_MAX"]), roll_rate_max_radps=d(t["MC_ROLLRATE_MAX"]),
            pitch_rate_max_radps=d(t["MC_PITCHRATE_MAX"]), yaw_rate_max_radps=d(t["MC_YAWRATE_MAX"]))

    def geofence(self) -> tuple[int, float, float]:
        """(action, horizontal radius m, maximum height m); radius/height 0 = off."""
        if not self.px4:
            return 0, 0.0, 0.0
        return int(self.t["GF_ACTION"]), self.t["GF_MAX_HOR_DIST"], self.t["GF_MAX_VER_DIST"]

    def throw_thresholds(self) -> tuple[float, float, float]:
        return self.t["SD_THR_TILT"], self.t["SD_THR_RATE"], self.t["SD_THR_SPEED"]
