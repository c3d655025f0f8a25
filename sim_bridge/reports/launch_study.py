"""Geometric vs PID on one carrier launch (paper section 2.2, Fig. 2 vs Fig. 3).

One vehicle is released with a given roll at the carrier's speed and commanded
to brake and hover (velocity setpoint zero, the same setpoint the Agent sends in
its STABILISE phase). Both controllers fly the same physics and share their
small-angle closed-loop poles (docs/controllers.md), so any difference comes
from large-angle behaviour.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion import frames
from companion.params import InnerLoopConfig
from companion.state import FleetSetpoint, FleetState
from sim_bridge.scenario import LaunchStudyConfig, ScenarioConfig
from sim_bridge.world.physics import Physics, hover_rotor_speed_radps


@dataclass
class LaunchTrace:
    """A recorded launch at the physics rate: t (T,), pos/vel (T,3), euler_rad (T,3) roll/pitch/yaw."""

    controller: str
    roll_deg: float
    t_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    euler_rad: np.ndarray
    tilt_rad: np.ndarray


def fly_launch(cfg: ScenarioConfig, controller: Literal["geometric", "pid"], roll_deg: float) -> LaunchTrace:
    """Simulate one launch at the scenario's physics rate for launch_study.duration_s."""
    study = cfg.launch_study
    inner = InnerLoopConfig(controller=controller, geometric=cfg.inner_loop.geometric, pid=cfg.inner_loop.pid)
    dt = 1.0 / cfg.physics.rate_hz
    phys = Physics(cfg.vehicle, inner, dt_s=dt, wind=None, ground_z_m=None, rng=np.random.default_rng(0))
    st = FleetState.zeros(1)
    st.pos_ned_m[0] = [0.0, 0.0, -study.release_height_m]
    st.vel_ned_mps[0] = [study.speed_mps, 0.0, 0.0]
    st.rot_body_to_ned[0] = frames.euler_zyx_to_rot(np.radians(roll_deg), 0.0, 0.0)
    st.rotor_speed_radps[0] = hover_rotor_speed_radps(cfg.vehicle)
    sp = FleetSetpoint.empty(1)
    sp.vel_ned_mps[0] = 0.0
    n = int(round(study.duration_s / dt)) + 1
    pos, vel, rot = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
    for k in range(n):
        pos[k], vel[k], rot[k] = st.pos_ned_m[0], st.vel_ned_mps[0], st.rot_body_to_ned[0]
        if k < n - 1:
            phys.step(st, sp, n_steps=1)
    return LaunchTrace(
        controller, roll_deg, np.arange(n) * dt, pos, vel, frames.rot_to_euler_zyx(rot), frames.tilt_rad(rot)
    )


def settle_index(tr: LaunchTrace, study: LaunchStudyConfig) -> int | None:
    """First sample after which tilt and speed stay inside the thresholds; None if never."""
    ok = (tr.tilt_rad < np.radians(study.settle_tilt_deg)) & (
        np.linalg.norm(tr.vel_ned_mps, axis=1) < study.settle_speed_mps
    )
    if not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return 0 if len(bad) == 0 else int(bad[-1]) + 1


@dataclass(frozen=True)
class LaunchOutcome:
    """How one launch went (SI units; None where the vehicle never settled)."""

    settled: bool
    settling_time_s: float | None
    drift_m: float | None
    drift_horizontal_m: float | None
    final_displacement_m: float
    max_lateral_speed_mps: float
    altitude_loss_m: float
    max_tilt_after_0p5s_deg: float


@dataclass(frozen=True)
class LaunchComparison:
    """Both controllers on the same release; pid_over_geometric: PID's figure over the
    geometric controller's, for settling time, drift, height lost and lateral speed (None if
    undefined); above 1 the geometric controller is better."""

    roll_deg: float
    geometric: LaunchOutcome
    pid: LaunchOutcome
    pid_over_geometric: dict[str, float | None]

    @property
    def key(self) -> str:
        return f"roll_{self.roll_deg:g}"

    def geometric_beats_pid(self) -> bool:
        """Geometric settles, and sooner, with less drift and less height lost than PID."""
        g, p = self.geometric, self.pid
        if not g.settled or g.settling_time_s is None or g.drift_m is None:
            return False
        if not p.settled or p.settling_time_s is None or p.drift_m is None:
            return True
        return g.settling_time_s < p.settling_time_s and g.drift_m < p.drift_m and g.altitude_loss_m < p.altitude_loss_m

    def to_json(self) -> dict:
        return {"geometric": dataclasses.asdict(self.geometric), "pid": dataclasses.asdict(self.pid),
                "pid_over_geometric": dict(self.pid_over_geometric)}


def launch_study_json(study: list[LaunchComparison]) -> dict:
    """{"roll_90": {"geometric": {...}, "pid": {...}, "pid_over_geometric": {...}}, ...} for metrics.json."""
    return {c.key: c.to_json() for c in study}


def launch_metrics(tr: LaunchTrace, study: LaunchStudyConfig) -> LaunchOutcome:
    """Settling time, drift and lateral speed of one launch (SI units)."""
    k = settle_index(tr, study)
    disp = tr.pos_ned_m - tr.pos_ned_m[0]
    return LaunchOutcome(
        settled=k is not None,
        settling_time_s=None if k is None else float(tr.t_s[k]),
        drift_m=None if k is None else float(np.linalg.norm(disp[k])),
        drift_horizontal_m=None if k is None else float(np.linalg.norm(disp[k, :2])),
        final_displacement_m=float(np.linalg.norm(disp[-1])),
        max_lateral_speed_mps=float(np.abs(tr.vel_ned_mps[:, 1]).max()),
        altitude_loss_m=float(max(0.0, disp[:, 2].max())),
        max_tilt_after_0p5s_deg=float(np.degrees(tr.tilt_rad[tr.t_s >= 0.5].max())),
    )


def run_launch_study(cfg: ScenarioConfig) -> tuple[list[LaunchComparison], dict[float, dict[str, LaunchTrace]]]:
    """Fly every configured roll with both controllers.

    Returns:
        comparisons: one LaunchComparison per configured roll, in order.
        traces: {roll_deg: {"geometric": LaunchTrace, "pid": LaunchTrace}}
    """
    study = cfg.launch_study
    out, traces = [], {}
    for roll in study.roll_deg:
        pair = {c: fly_launch(cfg, c, roll) for c in ("geometric", "pid")}
        g, p = launch_metrics(pair["geometric"], study), launch_metrics(pair["pid"], study)
        ratios: dict[str, float | None] = {}
        for key in ("settling_time_s", "drift_m", "altitude_loss_m", "max_lateral_speed_mps"):
            gv, pv = getattr(g, key), getattr(p, key)
            ratios[key] = None if (gv is None or pv is None or gv == 0) else pv / gv
        out.append(LaunchComparison(float(roll), g, p, ratios))
        traces[roll] = pair
    return out, traces
