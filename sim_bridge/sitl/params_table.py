"""PX4-style parameter table of one simulated vehicle.

The table really drives the simulation: gains, limits, failsafe timers and the
take-off altitude are read from it by the autopilot and the physics loop.
Integer parameters travel PX4-style, byte-wise: the four bytes of the int32 are
reinterpreted as the float `param_value` (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from companion.params import GeometricGains, InnerLoopConfig

MAV_PARAM_TYPE_UINT8 = 1
MAV_PARAM_TYPE_INT8 = 2
MAV_PARAM_TYPE_UINT16 = 3
MAV_PARAM_TYPE_INT16 = 4
MAV_PARAM_TYPE_UINT32 = 5
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
_INT_TYPES = {
    MAV_PARAM_TYPE_UINT8: "<B", MAV_PARAM_TYPE_INT8: "<b", MAV_PARAM_TYPE_UINT16: "<H",
    MAV_PARAM_TYPE_INT16: "<h", MAV_PARAM_TYPE_UINT32: "<I", MAV_PARAM_TYPE_INT32: "<i",
}


@dataclass(frozen=True)
class ParamSpec:
    name: str
    param_type: int
    default: float
    min_value: float
    max_value: float
    description: str


def encode_param_value(value: float, param_type: int) -> float:
    """Value -> the float carried in PARAM_VALUE/PARAM_SET (PX4 byte-wise for ints)."""
    if param_type == MAV_PARAM_TYPE_REAL32:
        return float(value)
    fmt = _INT_TYPES[param_type]
    raw = struct.pack(fmt, int(value)).ljust(4, b"\x00")
    return struct.unpack("<f", raw)[0]


def decode_param_value(wire: float, param_type: int) -> float:
    """Float from PARAM_SET/PARAM_VALUE -> value (inverse of encode_param_value)."""
    if param_type == MAV_PARAM_TYPE_REAL32:
        return float(wire)
    fmt = _INT_TYPES[param_type]
    raw = struct.pack("<f", wire)[: struct.calcsize(fmt)]
    return float(struct.unpack(fmt, raw)[0])


def _f(name, default, lo, hi, desc) -> ParamSpec:
    return ParamSpec(name, MAV_PARAM_TYPE_REAL32, float(default), float(lo), float(hi), desc)


def _i(name, default, lo, hi, desc) -> ParamSpec:
    return ParamSpec(name, MAV_PARAM_TYPE_INT32, float(default), float(lo), float(hi), desc)


def default_specs(inner: InnerLoopConfig, sysid: int) -> tuple[ParamSpec, ...]:
    """All parameters, sorted by name (PX4 serves them in name order)."""
    g = inner.geometric
    specs = [
        _f("MIS_TAKEOFF_ALT", 2.5, 0.0, 1000.0, "take-off altitude above home, m"),
        _f("MPC_TKO_SPEED", 1.5, 0.1, 10.0, "take-off climb speed, m/s"),
        _f("MPC_LAND_SPEED", 0.7, 0.1, 5.0, "landing descent speed, m/s"),
        _f("MPC_TILTMAX_AIR", g.tilt_max_deg, 1.0, 89.0, "tilt limit of the geometric controller, deg"),
        _f("SD_ACC_MAX", g.acc_max_mps2, 0.1, 100.0, "norm limit of the commanded acceleration, m/s^2"),
        _f("SD_GEO_KX", g.kx_per_s2, 0.0, 1000.0, "geometric position gain per unit mass, 1/s^2"),
        _f("SD_GEO_KV", g.kv_per_s, 0.0, 1000.0, "geometric velocity gain per unit mass, 1/s"),
        _f("SD_GEO_KR", g.kR_per_s2, 1e-3, 1e5, "geometric attitude gain per unit inertia, 1/s^2"),
        _f("SD_GEO_KOM", g.kOmega_per_s, 1e-3, 1e4, "geometric body-rate gain per unit inertia, 1/s"),
        _f("COM_OF_LOSS_T", 1.0, 0.0, 60.0, "offboard setpoint timeout before Hold, s"),
        _f("SD_OBL_LAND_T", 5.0, -1.0, 3600.0, "time in Hold after offboard loss before Land, s (-1 never)"),
        _f("COM_DISARM_PRFLT", 10.0, -1.0, 20.0, "disarm if armed and not taken off within, s (<=0 off)"),
        _f("COM_DISARM_LAND", 2.0, -1.0, 20.0, "disarm after landing detected, s (<0 off)"),
        _i("GF_ACTION", 2, 0, 5, "geofence action: 0 none, 1 warn, 2 hold, 3 return(=land), 4 terminate, 5 land"),
        _f("GF_MAX_HOR_DIST", 0.0, 0.0, 1e6, "geofence horizontal radius from home, m (0 off)"),
        _f("GF_MAX_VER_DIST", 0.0, 0.0, 1e6, "geofence maximum height above home, m (0 off)"),
        _i("COM_THROW_EN", 1, 0, 1, "stabilise after carrier release (throw launch)"),
        _f("SD_THR_TILT", 10.0, 1.0, 90.0, "throw: tilt below which the vehicle counts as upright, deg"),
        _f("SD_THR_RATE", 0.5, 0.01, 10.0, "throw: body-rate norm below which it counts as stable, rad/s"),
        _f("SD_THR_SPEED", 0.5, 0.01, 10.0, "throw: speed below which it switches to Hold, m/s"),
        _i("MAV_SYS_ID", sysid, 1, 250, "MAVLink system id (read only in the SITL)"),
        _i("MAV_COMP_ID", 1, 1, 250, "MAVLink component id (read only in the SITL)"),
        _i("MAV_TYPE", 2, 0, 30, "vehicle type (quadrotor)"),
        _i("SYS_AUTOSTART", 4001, 0, 9999999, "airframe (generic quadrotor x)"),
    ]
    return tuple(sorted(specs, key=lambda s: s.name))


READ_ONLY = frozenset({"MAV_SYS_ID", "MAV_COMP_ID", "MAV_TYPE", "SYS_AUTOSTART"})


class ParamTable:
    """Parameter values of one vehicle; index order is name order."""

    def __init__(self, specs: tuple[ParamSpec, ...]):
        self.specs = specs
        self._index = {s.name: i for i, s in enumerate(specs)}
        self._values = [s.default for s in specs]
        self.version = 0
        """Incremented on every accepted change (lets consumers cache derived objects)."""

    def __len__(self) -> int:
        return len(self.specs)

    def __getitem__(self, name: str) -> float:
        return self._values[self._index[name]]

    def index_of(self, name: str) -> int | None:
        return self._index.get(name)

    def wire(self, index: int) -> tuple[str, float, int]:
        """(name, encoded float, MAV_PARAM_TYPE) of the parameter at index."""
        s = self.specs[index]
        return s.name, encode_param_value(self._values[index], s.param_type), s.param_type

    def set_wire(self, name: str, wire: float, param_type: int) -> int | None:
        """Apply a PARAM_SET; returns the index to echo, or None when the name is unknown.

        A value that is not finite, outside [min, max] or read-only is refused:
        the echo then carries the unchanged value (the sender sees it did not take).
        """
        idx = self._index.get(name)
        if idx is None:
            return None
        spec = self.specs[idx]
        known = param_type in _INT_TYPES or param_type == MAV_PARAM_TYPE_REAL32
        try:
            value = decode_param_value(wire, param_type if known else spec.param_type)
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

    def set(self, name: str, value: float) -> bool:
        """Direct (config/test) set with the same checks as PARAM_SET."""
        spec = self.specs[self._index[name]]
        before = self.version
        self.set_wire(name, encode_param_value(value, spec.param_type), spec.param_type)
        return self.version != before or self[name] == value

    def inner_loop(self, base: InnerLoopConfig) -> InnerLoopConfig:
        """The inner-loop config this table asks for (gains and limits from the table)."""
        return InnerLoopConfig(
            controller=base.controller,
            geometric=GeometricGains(
                kx_per_s2=self["SD_GEO_KX"], kv_per_s=self["SD_GEO_KV"],
                kR_per_s2=self["SD_GEO_KR"], kOmega_per_s=self["SD_GEO_KOM"],
                tilt_max_deg=self["MPC_TILTMAX_AIR"], acc_max_mps2=self["SD_ACC_MAX"],
            ),
            pid=base.pid,
        )
