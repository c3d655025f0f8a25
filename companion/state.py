"""Typed, batched vehicle state and setpoints (NED world frame, FRD body frame).

Every array has the fleet size N as its first axis, so one code path serves one
vehicle (N = 1) or a whole fleet. NaN in a setpoint field means "not commanded",
mirroring the ignore bits of MAVLink's SET_POSITION_TARGET_LOCAL_NED.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _nan(*shape: int) -> np.ndarray:
    return np.full(shape, np.nan)


@dataclass
class FleetState:
    """Rigid-body state of N vehicles.

    Attributes:
        pos_ned_m: (N, 3) position of the centre of mass, NED, metres.
        vel_ned_mps: (N, 3) velocity, NED, m/s.
        rot_body_to_ned: (N, 3, 3) rotation matrix R mapping FRD body vectors to NED.
        omega_body_radps: (N, 3) body angular rate, FRD, rad/s.
        rotor_speed_radps: (N, 4) rotor speeds Q_1..Q_4, rad/s.
        ctrl_integral: (N, 6) controller integrator memory (PID baseline: attitude
            [0:3], velocity [3:6]); unused by the geometric controller.
    """

    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    rot_body_to_ned: np.ndarray
    omega_body_radps: np.ndarray
    rotor_speed_radps: np.ndarray
    ctrl_integral: np.ndarray

    @classmethod
    def zeros(cls, n: int) -> "FleetState":
        """N vehicles at the origin, level, at rest, rotors stopped."""
        return cls(
            pos_ned_m=np.zeros((n, 3)),
            vel_ned_mps=np.zeros((n, 3)),
            rot_body_to_ned=np.repeat(np.eye(3)[None], n, axis=0),
            omega_body_radps=np.zeros((n, 3)),
            rotor_speed_radps=np.zeros((n, 4)),
            ctrl_integral=np.zeros((n, 6)),
        )

    @property
    def n(self) -> int:
        return self.pos_ned_m.shape[0]

    def copy(self) -> "FleetState":
        return FleetState(*(np.array(getattr(self, f)) for f in self.__dataclass_fields__))

    def subset(self, idx) -> "FleetState":
        """A copy holding only the vehicles selected by idx (index array or mask)."""
        return FleetState(*(np.array(getattr(self, f)[idx]) for f in self.__dataclass_fields__))


@dataclass
class FleetSetpoint:
    """Inner-loop setpoints for N vehicles; NaN marks a field as not commanded.

    Position-family mode (used when att_q_wxyz is NaN):
        pos_ned_m (N, 3), vel_ned_mps (N, 3), acc_ned_mps2 (N, 3): per-axis NaN masks.
        yaw_rad (N,), yaw_rate_radps (N,).
    Attitude mode (used when att_q_wxyz is finite), as SET_ATTITUDE_TARGET:
        att_q_wxyz (N, 4): NED->FRD quaternion, MAVLink order w, x, y, z.
        thrust_norm (N,): collective thrust as a fraction of maximum, 0..1.
        body_rate_radps (N, 3): body rate feed-forward (NaN = 0).
    """

    pos_ned_m: np.ndarray = field(default_factory=lambda: _nan(0, 3))
    vel_ned_mps: np.ndarray = field(default_factory=lambda: _nan(0, 3))
    acc_ned_mps2: np.ndarray = field(default_factory=lambda: _nan(0, 3))
    yaw_rad: np.ndarray = field(default_factory=lambda: _nan(0))
    yaw_rate_radps: np.ndarray = field(default_factory=lambda: _nan(0))
    att_q_wxyz: np.ndarray = field(default_factory=lambda: _nan(0, 4))
    thrust_norm: np.ndarray = field(default_factory=lambda: _nan(0))
    body_rate_radps: np.ndarray = field(default_factory=lambda: _nan(0, 3))

    @classmethod
    def empty(cls, n: int) -> "FleetSetpoint":
        """N setpoints with nothing commanded (all NaN).

        The fields are views of one (N, 19) block: one allocation instead of eight
        (this runs every agent tick on a small computer).
        """
        b = np.full((n, 19), np.nan)
        return cls(b[:, 0:3], b[:, 3:6], b[:, 6:9], b[:, 9], b[:, 10], b[:, 11:15], b[:, 15], b[:, 16:19])

    @property
    def n(self) -> int:
        return self.pos_ned_m.shape[0]

    def select(self, idx) -> "FleetSetpoint":
        """A copy holding only the vehicles selected by idx (index array or mask)."""
        return FleetSetpoint(*(np.array(getattr(self, f)[idx]) for f in self.__dataclass_fields__))

    def assign(self, idx, other: "FleetSetpoint") -> None:
        """Overwrite the vehicles selected by idx with the rows of other."""
        for f in self.__dataclass_fields__:
            getattr(self, f)[idx] = getattr(other, f)
