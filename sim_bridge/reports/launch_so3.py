"""Geometric vs PID over many releases at any attitude (issue 9: launch studies on SO(3)).

Every draw is a vehicle released at `release_height_m` with the carrier's speed along
north, an attitude uniform over SO(3) and a body rate uniform in the ball of radius
`body_rate_max_radps`. Both controllers fly the same draws (one batch each: the fleet
stepper runs all of them at once), with the STABILISE setpoint (velocity zero, no yaw).
Settling uses the launch study's thresholds (tilt and speed), judged on samples every
`sample_period_s`; height lost is the largest descent below the release height.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from companion.state import FleetSetpoint, FleetState
from sim_bridge.scenario import ScenarioConfig
from sim_bridge.world.physics import Physics, hover_rotor_speed_radps

CONTROLLERS: tuple[Literal["geometric", "pid"], ...] = ("geometric", "pid")
PERCENTILES = (50, 95)


@dataclass(frozen=True)
class ReleaseDraws:
    """rot_body_to_ned (N, 3, 3) and omega_body_radps (N, 3) FRD of N releases."""

    rot_body_to_ned: np.ndarray
    omega_body_radps: np.ndarray

    @property
    def n(self) -> int:
        return len(self.omega_body_radps)


def draw_releases(n: int, body_rate_max_radps: float, rng: np.random.Generator) -> ReleaseDraws:
    """n attitudes uniform over SO(3) and body rates uniform in a ball (radius in rad/s)."""
    rot = Rotation.random(n, rng=rng).as_matrix() if n else np.zeros((0, 3, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
    radius = body_rate_max_radps * rng.uniform(size=(n, 1)) ** (1.0 / 3.0)
    return ReleaseDraws(rot, direction * radius)


@dataclass(frozen=True)
class BatchOutcome:
    """Per draw (N,): settled within the duration, settle time s (NaN if not), drift m from
    the release point at settling (NaN if not), height lost m (largest descent)."""

    controller: str
    settled: np.ndarray
    settle_time_s: np.ndarray
    drift_m: np.ndarray
    altitude_loss_m: np.ndarray

    def percentile(self, name: str, p: float) -> float | None:
        """p-th percentile of a figure over all draws; a draw that never settled counts as
        +inf for settle time and drift (so a failure can only make the figure worse)."""
        x = np.asarray(getattr(self, name), float)
        if not len(x):
            return None
        v = float(np.percentile(np.where(np.isnan(x), np.inf, x), p))
        return v if np.isfinite(v) else None


def fly_batch(cfg: ScenarioConfig, controller: Literal["geometric", "pid"], draws: ReleaseDraws) -> BatchOutcome:
    """Release every draw and fly the STABILISE setpoint for launch_study.duration_s."""
    study = cfg.launch_study
    inner = dataclasses.replace(cfg.inner_loop, controller=controller)
    dt = 1.0 / cfg.physics.rate_hz
    phys = Physics(cfg.vehicle, inner, dt_s=dt, wind=None, ground_z_m=None, rng=np.random.default_rng(0))
    n = draws.n
    st = FleetState.zeros(n)
    st.pos_ned_m[:] = [0.0, 0.0, -study.release_height_m]
    st.vel_ned_mps[:] = [study.speed_mps, 0.0, 0.0]
    st.rot_body_to_ned[:] = draws.rot_body_to_ned
    st.omega_body_radps[:] = draws.omega_body_radps
    st.rotor_speed_radps[:] = hover_rotor_speed_radps(cfg.vehicle)
    sp = FleetSetpoint.empty(n)
    sp.vel_ned_mps[:] = 0.0
    every = max(1, int(round(study.sample_period_s / dt)))
    m = int(round(study.duration_s / (every * dt))) + 1
    pos0 = st.pos_ned_m.copy()
    calm = np.zeros((m, n), bool)
    pos = np.empty((m, n, 3))
    cos_tilt_ok = np.cos(np.radians(study.settle_tilt_deg))
    for k in range(m):
        pos[k] = st.pos_ned_m
        calm[k] = (st.rot_body_to_ned[:, 2, 2] > cos_tilt_ok) & (
            np.linalg.norm(st.vel_ned_mps, axis=1) < study.settle_speed_mps)
        if k < m - 1:
            phys.step(st, sp, every)
    t = np.arange(m) * every * dt
    settled = calm[-1].copy()
    # first sample after the last uncalm one
    last_bad = np.where(calm.all(axis=0), -1, m - 1 - np.argmax(~calm[::-1], axis=0))
    k_settle = np.minimum(last_bad + 1, m - 1)
    idx = np.arange(n)
    settle_s = np.where(settled, t[k_settle], np.nan)
    drift = np.where(settled, np.linalg.norm(pos[k_settle, idx] - pos0, axis=1), np.nan)
    loss = np.maximum(0.0, (pos[:, :, 2] - pos0[:, 2]).max(axis=0))
    return BatchOutcome(controller, settled, settle_s, drift, loss)


@dataclass(frozen=True)
class So3Study:
    """Both controllers on the same draws."""

    draws: ReleaseDraws
    geometric: BatchOutcome
    pid: BatchOutcome
    speed_mps: float
    release_height_m: float
    body_rate_max_radps: float

    def summary(self) -> dict:
        """JSON-ready: recovered fraction and p50/p95 of each figure, per controller."""
        out: dict = {"draws": self.draws.n, "speed_mps": self.speed_mps, "release_height_m": self.release_height_m,
                     "body_rate_max_radps": self.body_rate_max_radps}
        for b in (self.geometric, self.pid):
            row: dict = {"recovered_fraction": float(b.settled.mean()) if len(b.settled) else None}
            for name in ("settle_time_s", "altitude_loss_m", "drift_m"):
                for p in PERCENTILES:
                    row[f"{name}_p{p}"] = b.percentile(name, p)
            out[b.controller] = row
        return out

    def geometric_wins(self) -> bool:
        """Geometric recovers every draw and is better than PID at the median and the 95th
        percentile of settle time and of height lost."""
        if not self.geometric.settled.all():
            return False
        for name in ("settle_time_s", "altitude_loss_m"):
            for p in PERCENTILES:
                g, q = self.geometric.percentile(name, p), self.pid.percentile(name, p)
                if g is None or (q is not None and g >= q):
                    return False
        return True

    def rows(self) -> list[dict]:
        """One CSV row per draw and controller (attitude as ZYX Euler degrees)."""
        eul = np.degrees(Rotation.from_matrix(self.draws.rot_body_to_ned).as_euler("ZYX")) if self.draws.n else []
        out = []
        for b in (self.geometric, self.pid):
            for i in range(self.draws.n):
                out.append({"draw": i, "controller": b.controller, "roll_deg": eul[i][2], "pitch_deg": eul[i][1],
                            "yaw_deg": eul[i][0], "rate_radps": float(np.linalg.norm(self.draws.omega_body_radps[i])),
                            "settled": bool(b.settled[i]), "settle_time_s": b.settle_time_s[i],
                            "drift_m": b.drift_m[i], "altitude_loss_m": b.altitude_loss_m[i]})
        return out


def run_so3_study(cfg: ScenarioConfig, draws: int | None = None, seed: int | None = None) -> So3Study:
    """Draw the releases (seeded from the scenario seed unless given) and fly both controllers."""
    study = cfg.launch_study
    n = study.so3_draws if draws is None else draws
    rng = np.random.default_rng([cfg.seed if seed is None else seed, 0x50_33])  # its own stream
    d = draw_releases(n, study.body_rate_max_radps, rng)
    out = {c: fly_batch(cfg, c, d) for c in CONTROLLERS}
    return So3Study(d, out["geometric"], out["pid"], study.speed_mps, study.release_height_m, study.body_rate_max_radps)
