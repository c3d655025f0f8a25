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

A real estimator also carries an accelerometer bias and a tilt error (PX4 SIH: 0.2-0.4 m/s^2
of accelerometer bias, about 2 deg of tilt error; ../shared/notes/mavlink-facts.md). What
that does to a flying vehicle is modelled as a constant acceleration disturbance per
vehicle acting on the true physics (the autopilot commands a, the vehicle realises a + d;
`bias_disturbance_ned_mps2`, handed to Physics.step as its external acceleration):
horizontally g tan(tilt error) in the direction of the tilt error, vertically the
accelerometer bias. Each vehicle's draw comes from the seed's own stream, so the SITL and
the headless runner disturb vehicle k alike. Without integral action somewhere (the
autopilot's velocity integrators, the agent's) it leaves a steady position offset.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.control.so3 import exp_so3_np
from companion.params import GRAVITY_MPS2


@dataclass(config=STRICT)
class EstimatorConfig:
    """The estimator's error model (module docstring): position noise (std m, correlation
    time s), velocity noise (m/s), attitude noise (rad) and latency (s), and the bias a
    flying vehicle feels (tilt error, deg; accelerometer bias, m/s^2). All zero (the
    default): the agents see the true state (`active` is False) and nothing is disturbed
    (`biased` is False).

    Raises:
        pydantic.ValidationError: a negative std, pos_noise_tau_s not > 0, latency_s
            outside [0, 2], or a tilt error std of 30 deg or more.
    """

    pos_noise_std_m: float = Field(default=0.0, ge=0)
    """Horizontal position error, stationary std per axis."""
    pos_noise_std_vertical_m: float = Field(default=0.0, ge=0)
    pos_noise_tau_s: float = Field(default=2.0, gt=0)
    """Correlation time of the position error."""
    vel_noise_std_mps: float = Field(default=0.0, ge=0)
    att_noise_std_rad: float = Field(default=0.0, ge=0)
    latency_s: float = Field(default=0.0, ge=0, le=2.0)
    tilt_error_std_deg: float = Field(default=0.0, ge=0, lt=30.0)
    """Tilt error of each vehicle's estimator, std per horizontal axis (deg): a horizontal
    disturbance of g tan(tilt error) towards the tilt (PX4 SIH: about 2 deg)."""
    accel_bias_std_mps2: float = Field(default=0.0, ge=0)
    """Vertical accelerometer bias of each vehicle's estimator, std (m/s^2): a vertical
    disturbance of that size (PX4 SIH: 0.2-0.4 m/s^2)."""

    @property
    def biased(self) -> bool:
        """Some vehicle is disturbed by its estimator's bias (bias_disturbance_ned_mps2)."""
        return self.tilt_error_std_deg > 0 or self.accel_bias_std_mps2 > 0

    @property
    def active(self) -> bool:
        return any(v > 0 for v in (self.pos_noise_std_m, self.pos_noise_std_vertical_m, self.vel_noise_std_mps,
                                   self.att_noise_std_rad, self.latency_s))


_BIAS_STREAM = 0x42494153  # "BIAS": the per-vehicle bias draws, apart from every other stream


def bias_disturbance_ned_mps2(cfg: EstimatorConfig, n: int, seed: int) -> np.ndarray:
    """(n, 3) constant acceleration disturbance of each vehicle from its estimator's bias
    (module docstring), NED m/s^2: the tilt error is drawn per horizontal axis (std
    tilt_error_std_deg, so its direction is uniform) and gives g tan(|tilt|) along it; the
    vertical part is the accelerometer bias (std accel_bias_std_mps2). From the seed's own
    stream; all zero without a bias (nothing drawn)."""
    out = np.zeros((n, 3))
    if not cfg.biased or n == 0:
        return out
    z = np.random.default_rng([seed, _BIAS_STREAM]).standard_normal((n, 3))  # (row k: vehicle k's, whatever n)
    tilt = np.radians(cfg.tilt_error_std_deg * z[:, :2])
    bias = cfg.accel_bias_std_mps2 * z[:, 2]
    mag = np.hypot(tilt[:, 0], tilt[:, 1])
    scale = np.where(mag > 0, GRAVITY_MPS2 * np.tan(mag) / np.maximum(mag, 1e-300), 0.0)
    out[:, :2] = tilt * scale[:, None]
    out[:, 2] = bias
    return out


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
