"""What the autopilot's estimator reports: the true state with GPS-like errors and a delay.

Used for the states the agent receives, headless (its OwnState) and in the SITL (every
telemetry message), so both see the same model. The inner-loop controller still flies
on the true state: the errors are in what the companion sees and plans with (see
docs/scenario.md, "Disturbed world").

Model, per vehicle and axis:
    * position error: first-order Gauss-Markov with stationary std pos_noise_std_m
      (horizontal) / pos_noise_std_vertical_m and correlation time pos_noise_tau_s: GPS
      error wanders slowly rather than jumping every sample;
    * velocity: white noise of std vel_noise_std_mps;
    * attitude: a small rotation with white components of std att_noise_std_rad;
    * latency: the values are those of latency_s ago (the stamp stays "now", as an
      estimator that does not know its own delay).

The autopilot's own position controller flies on the same estimate: a position setpoint
the companion computed from an estimated position is met where the *estimate* says it
is. The simulators keep the inner loop on the true state and emulate this by shifting
position setpoints by `offset_ned_m` (estimate minus truth), which is exact for a
controller linear in the position error. Without it a slowly wandering GPS error would
make every vehicle chase its own error and walk away.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.control.so3 import exp_so3_np


@dataclass(config=STRICT)
class EstimatorConfig:
    pos_noise_std_m: float = Field(default=0.0, ge=0)
    """Horizontal position error, stationary std per axis."""
    pos_noise_std_vertical_m: float = Field(default=0.0, ge=0)
    pos_noise_tau_s: float = Field(default=2.0, gt=0)
    """Correlation time of the position error."""
    vel_noise_std_mps: float = Field(default=0.0, ge=0)
    att_noise_std_rad: float = Field(default=0.0, ge=0)
    latency_s: float = Field(default=0.0, ge=0, le=2.0)

    @property
    def active(self) -> bool:
        return any(v > 0 for v in (self.pos_noise_std_m, self.pos_noise_std_vertical_m, self.vel_noise_std_mps,
                                   self.att_noise_std_rad, self.latency_s))


class Estimator:
    """Applies EstimatorConfig to N vehicles; call observe() with increasing t_s.

    Args:
        cfg: the error model.
        n: vehicles.
        rng: the estimator's own random stream.
    """

    def __init__(self, cfg: EstimatorConfig, n: int, rng: np.random.Generator):
        self.cfg, self.n, self.rng = cfg, n, rng
        self._std = np.array([cfg.pos_noise_std_m, cfg.pos_noise_std_m, cfg.pos_noise_std_vertical_m])
        self.pos_err_m = rng.normal(size=(n, 3)) * self._std
        self._t_last: float | None = None
        self._history: deque = deque()
        self.offset_ned_m = np.zeros((n, 3))
        """(N, 3) last reported position minus the true position at that time, m."""

    def observe(self, t_s: float, pos_ned_m: np.ndarray, vel_ned_mps: np.ndarray,
                rot_body_to_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(pos (N,3), vel (N,3), rot (N,3,3)) as the estimator reports them at t_s (new arrays)."""
        c = self.cfg
        if not c.active:
            return pos_ned_m.copy(), vel_ned_mps.copy(), rot_body_to_ned.copy()
        if c.latency_s > 0:
            self._history.append((t_s, pos_ned_m.copy(), vel_ned_mps.copy(), rot_body_to_ned.copy()))
            while len(self._history) > 1 and self._history[1][0] <= t_s - c.latency_s + 1e-9:
                self._history.popleft()
            _, pos, vel, rot = self._history[0]
        else:
            pos, vel, rot = pos_ned_m, vel_ned_mps, rot_body_to_ned
        dt = 0.0 if self._t_last is None else max(t_s - self._t_last, 0.0)
        self._t_last = t_s
        if dt > 0 and self._std.any():
            phi = math.exp(-dt / c.pos_noise_tau_s)
            self.pos_err_m = phi * self.pos_err_m + math.sqrt(1.0 - phi * phi) * self._std * self.rng.normal(size=(self.n, 3))
        pos = pos + self.pos_err_m
        self.offset_ned_m = pos - pos_ned_m
        if c.vel_noise_std_mps > 0:
            vel = vel + self.rng.normal(0.0, c.vel_noise_std_mps, (self.n, 3))
        else:
            vel = vel.copy()
        if c.att_noise_std_rad > 0:
            rot = rot @ exp_so3_np(self.rng.normal(0.0, c.att_noise_std_rad, (self.n, 3)))
        else:
            rot = rot.copy()
        return pos, vel, rot


def to_true_frame(sp_pos_ned_m: np.ndarray, offset_ned_m: np.ndarray) -> np.ndarray:
    """Position setpoints (N, 3) given in the estimate's frame, as the true-state controller must
    fly them (NaN axes stay NaN)."""
    return sp_pos_ned_m - offset_ned_m
