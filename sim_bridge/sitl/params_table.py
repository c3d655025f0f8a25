"""Parameter table of one simulated vehicle, in its autopilot's names and units.

The table really drives the simulation: gains, limits, failsafe timers and the
take-off altitude are read from it by the autopilot and the physics loop. Which
parameters a vehicle has is its autopilot's (sim_bridge/sitl/autopilots/: PX4 names,
or ArduCopter names in ArduPilot units, cm/s and cm), plus the simulator's own `SD_*`
gains and throw thresholds, which every autopilot carries (`simulator_specs`).
Integers travel as the dialect says (companion.link.params: byte-wise or by value).

Each parameter may carry roles: what the autopilot-neutral state machine reads it as
(`Role`), in the role's SI unit after dividing by the parameter's `divisor` (100 for
ArduPilot's cm and cdeg). `ParamTable.role` reads them, so the state machine never
names an autopilot's parameter.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import Enum

from companion.link.params import (
    INT_FORMATS,
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    Encoding,
    decode_param_value,
    encode_param_value,
)
from companion.params import GeometricGains, InnerLoopConfig
from sim_bridge.world.autopilot_model import THROW_RATE_RADPS, THROW_SPEED_MPS, THROW_TILT_DEG

__all__ = ["ParamSpec", "ParamTable", "Role", "real_param", "int_param", "simulator_specs", "MAV_PARAM_TYPE_INT32",
           "MAV_PARAM_TYPE_REAL32", "encode_param_value", "decode_param_value"]


class Role(Enum):
    """What the autopilot-neutral state machine reads a parameter as (every autopilot's
    table has each exactly once; one parameter may have several)."""

    TILT_MAX_DEG = "tilt_max_deg"
    """Tilt limit of the position controller, deg (also the physics' limit)."""
    TAKEOFF_ALT_M = "takeoff_alt_m"
    """Take-off height above home when the command gives none, m."""
    TAKEOFF_SPEED_MPS = "takeoff_speed_mps"
    """Climb speed of a take-off, m/s."""
    DESCENT_SPEED_MPS = "descent_speed_mps"
    """Descent speed (e.g. a climb-rate thrust field below its middle), m/s."""
    LAND_SPEED_MPS = "land_speed_mps"
    """Descent speed in Land, m/s."""
    DISARM_PREFLIGHT_S = "disarm_preflight_s"
    """Disarm this long after arming without a take-off, s (<= 0 off)."""
    DISARM_LAND_S = "disarm_land_s"
    """Disarm this long after landing, s (< 0 off)."""
    HOVER_THRUST = "hover_thrust"
    """Normalised collective thrust that hovers (0..1)."""
    OFFBOARD_TIMEOUT_S = "offboard_timeout_s"
    """How long the autopilot flies on without a new companion setpoint, s."""


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: name, MAV_PARAM_TYPE, default, bounds, what it means, and its roles."""

    name: str
    param_type: int
    default: float
    min_value: float
    max_value: float
    description: str
    roles: tuple[Role, ...] = ()
    """What the state machine reads this parameter as (ParamTable.role)."""
    divisor: float = 1.0
    """The roles' value is the parameter's value divided by this (ArduPilot cm -> m: 100)."""
    read_only: bool = False
    """PARAM_SET refuses it (identity, the airframe's hover thrust)."""


def real_param(name: str, default: float, lo: float, hi: float, desc: str, roles: tuple[Role, ...] = (),
               divisor: float = 1.0, read_only: bool = False) -> ParamSpec:
    """A REAL32 parameter."""
    return ParamSpec(name, MAV_PARAM_TYPE_REAL32, float(default), float(lo), float(hi), desc, roles, divisor,
                     read_only)


def int_param(name: str, default: float, lo: float, hi: float, desc: str, read_only: bool = False) -> ParamSpec:
    """An INT32 parameter."""
    return ParamSpec(name, MAV_PARAM_TYPE_INT32, float(default), float(lo), float(hi), desc, read_only=read_only)


def simulator_specs(inner: InnerLoopConfig) -> list[ParamSpec]:
    """The simulated inner loop and throw recovery (every autopilot carries them). The
    inner loop's attitude gains only: position-family setpoints reach it as the
    acceleration the autopilot's own position loops ask for (its MPC_* / PSC_* gains)."""
    g = inner.geometric
    f = real_param
    return [
        f("SD_ACC_MAX", g.acc_max_mps2, 0.1, 100.0, "norm limit of the commanded acceleration, m/s^2"),
        f("SD_GEO_KR", g.kR_per_s2, 1e-3, 1e5, "geometric attitude gain per unit inertia, 1/s^2"),
        f("SD_GEO_KOM", g.kOmega_per_s, 1e-3, 1e4, "geometric body-rate gain per unit inertia, 1/s"),
        f("SD_THR_TILT", THROW_TILT_DEG, 1.0, 90.0, "throw: tilt below which the vehicle counts as upright, deg"),
        f("SD_THR_RATE", THROW_RATE_RADPS, 0.01, 10.0, "throw: body-rate norm below which it counts as stable, rad/s"),
        f("SD_THR_SPEED", THROW_SPEED_MPS, 0.01, 10.0, "throw: speed below which it counts as recovered, m/s"),
    ]


class ParamTable:
    """Parameter values of one vehicle; index order is name order.

    Args:
        specs: the parameters, in name order (AutopilotBehaviour.param_specs).
        encoding: how integers travel ("bytewise" PX4, "c_cast" ArduPilot).
    Raises:
        ValueError: a role carried by two parameters.
    """

    def __init__(self, specs: tuple[ParamSpec, ...], encoding: Encoding = "bytewise"):
        self.specs = specs
        self.encoding = encoding
        self._index = {s.name: i for i, s in enumerate(specs)}
        self._values = [s.default for s in specs]
        self._roles: dict[Role, int] = {}
        for i, spec in enumerate(specs):
            for r in spec.roles:
                if r in self._roles:
                    raise ValueError(f"parameters {specs[self._roles[r]].name} and {spec.name} both have role {r.value}")
                self._roles[r] = i
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

    def role(self, role: Role) -> float:
        """The value of the parameter with this role, in the role's unit.

        Raises:
            KeyError: no parameter has it (AutopilotBehaviour.param_specs checks every role is there).
        """
        i = self._roles[role]
        return self._values[i] / self.specs[i].divisor

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
        if spec.read_only or not math.isfinite(value) or not spec.min_value <= value <= spec.max_value:
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
        """The inner-loop config this table asks for (attitude gains and limits from the table;
        the position gains stay the config's, which the autopilot's own loops stand in for)."""
        tilt = self.role(Role.TILT_MAX_DEG)
        return InnerLoopConfig(
            controller=base.controller,
            geometric=GeometricGains(
                kx_per_s2=base.geometric.kx_per_s2, kv_per_s=base.geometric.kv_per_s,
                kR_per_s2=self["SD_GEO_KR"], kOmega_per_s=self["SD_GEO_KOM"],
                tilt_max_deg=min(tilt, 89.0), acc_max_mps2=self["SD_ACC_MAX"],
                large_angle=base.geometric.large_angle, yaw_error_max_rad=base.geometric.yaw_error_max_rad,
            ),
            pid=base.pid,
        )

    def gain_key(self) -> tuple:
        """The values that select a physics group (vehicles with equal keys share one)."""
        tilt = self.role(Role.TILT_MAX_DEG)
        return (self["SD_GEO_KR"], self["SD_GEO_KOM"], tilt, self["SD_ACC_MAX"])
