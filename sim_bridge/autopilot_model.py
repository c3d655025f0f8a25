"""What a simulated autopilot does on its own, shared by the SITL and the headless runner.

After a carrier release the autopilot, not the companion, recovers the vehicle
(PX4 COM_THROW_EN, ArduCopter THROW): it commands zero velocity until the vehicle
is upright, slow and no longer spinning, then holds where it comes to rest. The
SITL's per-vehicle state machine and the headless runner's vectorised model call
these same functions, so both simulators recover a vehicle identically.
"""
from __future__ import annotations

import numpy as np

THROW_TILT_DEG = 10.0
"""Throw recovery is done below this tilt (SITL parameter SD_THR_TILT)."""
THROW_RATE_RADPS = 0.5
"""... and below this body-rate norm (SD_THR_RATE)."""
THROW_SPEED_MPS = 0.5
"""... and below this speed (SD_THR_SPEED)."""
HOLD_BRAKE_MPS2 = 3.0
"""Deceleration assumed when Hold captures the point where the vehicle will stop."""
HOLD_BRAKE_MAX_M = 10.0
"""Longest braking distance Hold looks ahead."""


def throw_recovered(cos_tilt, rate_radps, speed_mps, tilt_deg: float = THROW_TILT_DEG,
                    rate_max_radps: float = THROW_RATE_RADPS, speed_max_mps: float = THROW_SPEED_MPS):
    """True where a thrown vehicle counts as recovered; scalars or arrays of one shape.

    Args:
        cos_tilt: cosine of the angle between body z and world z (R[2, 2]).
        rate_radps: body-rate norm, rad/s.
        speed_mps: speed, m/s.
    """
    return (cos_tilt > np.cos(np.radians(tilt_deg))) & (rate_radps < rate_max_radps) & (speed_mps < speed_max_mps)


def hold_point(pos_ned_m: np.ndarray, vel_ned_mps: np.ndarray) -> np.ndarray:
    """Where Hold brings a flying vehicle to rest: its position plus the braking
    distance at HOLD_BRAKE_MPS2 along its velocity (at most HOLD_BRAKE_MAX_M).

    Args:
        pos_ned_m, vel_ned_mps: (..., 3).
    Returns:
        (..., 3) NED point, m.
    """
    v = np.asarray(vel_ned_mps, float)
    speed = np.sqrt(np.sum(v * v, axis=-1, keepdims=True))
    ahead = np.minimum(speed / (2.0 * HOLD_BRAKE_MPS2), HOLD_BRAKE_MAX_M / np.maximum(speed, 1e-9))
    return np.asarray(pos_ned_m, float) + np.where(speed > 0.05, v * ahead, 0.0)
