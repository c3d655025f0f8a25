"""The carrier aircraft and its launch schedule (paper section 4.1, stage 1).

The carrier flies a straight line at constant velocity and releases one vehicle
every `release_interval_s`. A released vehicle starts at the carrier's position
with the carrier's velocity and a random attitude and body rate drawn from the
configured distribution (an injected numpy Generator makes it reproducible).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass
from scipy.spatial.transform import Rotation

from companion.config import STRICT


@dataclass(config=STRICT)
class AttitudeDistribution:
    """How release attitudes are drawn.

    kind "uniform_so3": uniform over all rotations whose angle from level-with-yaw-0
    is at most max_angle_deg (rejection sampling; 180 = all of SO(3)).
    kind "euler": roll, pitch, yaw each uniform in +-{roll,pitch,yaw}_max_deg.
    kind "fixed": exactly roll_deg/pitch_deg/yaw_deg (used for the paper's 90-deg case).
    """

    kind: Literal["uniform_so3", "euler", "fixed"] = "uniform_so3"
    max_angle_deg: float = Field(default=179.0, gt=0, le=180.0)
    roll_max_deg: float = Field(default=180.0, ge=0, le=180.0)
    pitch_max_deg: float = Field(default=90.0, ge=0, le=90.0)
    yaw_max_deg: float = Field(default=180.0, ge=0, le=180.0)
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0
    body_rate_std_radps: float = Field(default=0.0, ge=0)
    """Standard deviation of each body-rate component at release (tumble)."""


@dataclass(config=STRICT)
class CarrierConfig:
    """The carrier aircraft (module docstring): its straight track (NED m, m/s at t = 0),
    when it releases (first_release_s, then every release_interval_s, s; or "command": a
    vehicle goes on MAV_CMD 31010 in the SITL) and the release attitudes.

    Raises:
        pydantic.ValidationError: first_release_s < 0, release_interval_s not > 0, or an
            unknown release kind.
    """

    start_ned_m: tuple[float, float, float] = (0.0, 0.0, -30.0)
    vel_ned_mps: tuple[float, float, float] = (5.0, 0.0, 0.0)
    first_release_s: float = Field(default=0.0, ge=0)
    release_interval_s: float = Field(default=1.0, gt=0)
    release: Literal["schedule", "command"] = "schedule"
    attitude: AttitudeDistribution = AttitudeDistribution()


def carrier_position_ned_m(cfg: CarrierConfig, t_s: float | np.ndarray) -> np.ndarray:
    """Carrier position at time t_s (s since scenario start). Shape (3,) or (len(t), 3)."""
    t = np.asarray(t_s, dtype=float)
    return np.asarray(cfg.start_ned_m) + t[..., None] * np.asarray(cfg.vel_ned_mps)


def release_times_s(cfg: CarrierConfig, n: int) -> np.ndarray:
    """Scheduled release time of each of n vehicles, shape (n,). Vehicle k goes k-th."""
    return cfg.first_release_s + cfg.release_interval_s * np.arange(n, dtype=float)


def sample_release_attitudes(
    cfg: CarrierConfig, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Draw n release attitudes and body rates.

    Returns:
        rot_body_to_ned: (n, 3, 3) rotation matrices.
        omega_body_radps: (n, 3) body rates, FRD.
    """
    dist = cfg.attitude
    if dist.kind == "fixed":
        eul = np.tile(np.radians([dist.yaw_deg, dist.pitch_deg, dist.roll_deg]), (n, 1))
        rot = Rotation.from_euler("ZYX", eul)
    elif dist.kind == "euler":
        lim = np.radians([dist.yaw_max_deg, dist.pitch_max_deg, dist.roll_max_deg])
        rot = Rotation.from_euler("ZYX", rng.uniform(-lim, lim, size=(n, 3)))
    else:
        quats: list[np.ndarray] = []
        max_angle = np.radians(dist.max_angle_deg)
        # Bounded rejection loop: a draw is accepted with probability >= ~0.2 for
        # max_angle >= 90 deg, so 1000 rounds never run out in practice.
        for _ in range(1000):
            cand = Rotation.random(4 * n, rng=rng)
            quats.append(cand[cand.magnitude() <= max_angle].as_quat())
            if sum(len(q) for q in quats) >= n:
                break
        else:  # pragma: no cover - only with absurdly small max_angle_deg
            raise ValueError(f"carrier.attitude.max_angle_deg={dist.max_angle_deg} too small to sample")
        rot = Rotation.from_quat(np.concatenate(quats)[:n])
    omega = rng.normal(0.0, dist.body_rate_std_radps, size=(n, 3))
    return rot.as_matrix(), omega
