"""Headless runner: the paper's whole scenario in-process, far faster than real time.

The loop is: release due vehicles from the carrier -> one batched Agent.step for
every vehicle (the same Agent the MAVLink companion runs for one vehicle) ->
Physics.step for physics_rate/agent_rate steps with the setpoints held (the
inner-loop geometric or PID controller runs at the physics rate) -> record.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit
from scipy.spatial.distance import pdist
from tqdm import tqdm

from companion import frames
from companion.agent import Agent, OwnState, Phase, SwarmView
from companion.mission import Mission
from companion.state import FleetState, FleetSetpoint
from sim_bridge.carrier import carrier_position_ned_m, release_times_s, sample_release_attitudes
from sim_bridge.physics import Physics, hover_rotor_speed_radps
from sim_bridge.scenario import ScenarioConfig


@dataclass
class SafetyTracker:
    """Running minima of separation and obstacle clearance, sampled every agent tick."""

    separation_m: float
    min_pair_dist_m: float = math.inf
    min_pair_time_s: float = math.nan
    min_pair: tuple[int, int] = (-1, -1)
    violating_pairs: set[tuple[int, int]] = field(default_factory=set)
    min_clearance_m: float = math.inf
    min_clearance_time_s: float = math.nan
    min_clearance_vehicle: int = -1

    def update(self, t_s: float, ids: np.ndarray, pos: np.ndarray, mission: Mission) -> None:
        """ids: (k,) vehicle ids of the airborne vehicles, pos: (k, 3) their positions."""
        if len(ids) >= 2:
            d_min, i, j, n_close = _closest_pair(pos, self.separation_m)
            if d_min < self.min_pair_dist_m:
                self.min_pair_dist_m, self.min_pair_time_s = d_min, t_s
                self.min_pair = (int(ids[i]), int(ids[j]))
            if n_close:  # rare: list the offending pairs
                d = pdist(pos)
                for k in np.flatnonzero(d < self.separation_m):
                    a, b = _pair_from_condensed(int(k), len(ids))
                    self.violating_pairs.add((int(ids[a]), int(ids[b])))
        if len(ids) and len(mission.obstacle_radii_m):
            gap = (
                np.linalg.norm(pos[:, None, :] - mission.obstacle_centres_ned_m[None], axis=2)
                - mission.obstacle_radii_m[None]
            )
            k = np.unravel_index(np.argmin(gap), gap.shape)
            if gap[k] < self.min_clearance_m:
                self.min_clearance_m, self.min_clearance_time_s = float(gap[k]), t_s
                self.min_clearance_vehicle = int(ids[k[0]])


@njit(cache=True)
def _closest_pair(pos: np.ndarray, threshold_m: float) -> tuple[float, int, int, int]:
    """Smallest pairwise distance of (k, 3) points, its pair, and how many pairs are
    closer than threshold_m (compiled: this runs every agent tick)."""
    best, bi, bj, close = np.inf, 0, 1, 0
    for i in range(pos.shape[0]):
        for j in range(i + 1, pos.shape[0]):
            d = np.sqrt((pos[i, 0] - pos[j, 0]) ** 2 + (pos[i, 1] - pos[j, 1]) ** 2 + (pos[i, 2] - pos[j, 2]) ** 2)
            if d < best:
                best, bi, bj = d, i, j
            if d < threshold_m:
                close += 1
    return best, bi, bj, close


def _pair_from_condensed(k: int, n: int) -> tuple[int, int]:
    """Inverse of scipy's condensed pdist index for n points."""
    i = int(n - 2 - math.floor(math.sqrt(-8 * k + 4 * n * (n - 1) - 7) / 2.0 - 0.5))
    j = int(k + i + 1 - n * (n - 1) // 2 + (n - i) * ((n - i) - 1) // 2)
    return i, j


@dataclass
class Recorder:
    """Telemetry samples at the log rate; arrays are (T, N, ...) after finish()."""

    t_s: list = field(default_factory=list)
    pos_ned_m: list = field(default_factory=list)
    vel_ned_mps: list = field(default_factory=list)
    rot_body_to_ned: list = field(default_factory=list)
    omega_body_radps: list = field(default_factory=list)
    rotor_speed_radps: list = field(default_factory=list)
    acc_cmd_ned_mps2: list = field(default_factory=list)
    slot_ned_m: list = field(default_factory=list)
    phase: list = field(default_factory=list)

    def add(self, t_s: float, st: FleetState, sp: FleetSetpoint, slot: np.ndarray, phase: np.ndarray) -> None:
        self.t_s.append(t_s)
        self.pos_ned_m.append(st.pos_ned_m.astype(np.float32))
        self.vel_ned_mps.append(st.vel_ned_mps.astype(np.float32))
        self.rot_body_to_ned.append(st.rot_body_to_ned.copy())  # -> quaternions once, in arrays()
        self.omega_body_radps.append(st.omega_body_radps.astype(np.float32))
        self.rotor_speed_radps.append(st.rotor_speed_radps.astype(np.float32))
        self.acc_cmd_ned_mps2.append(sp.acc_ned_mps2.astype(np.float32))
        self.slot_ned_m.append(slot.astype(np.float32))
        self.phase.append(phase.astype(np.int8))

    def arrays(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(v) for k, v in self.__dict__.items() if k != "rot_body_to_ned"}
        out["att_q_wxyz"] = frames.rot_to_quat_wxyz(np.asarray(self.rot_body_to_ned)).astype(np.float32)
        return out


@dataclass
class RunResult:
    cfg: ScenarioConfig
    mission: Mission
    log: dict[str, np.ndarray]
    release_s: np.ndarray
    release_pos_ned_m: np.ndarray
    phase_entry_s: np.ndarray  # (N, len(Phase)) first time each vehicle entered each phase
    safety: SafetyTracker
    t_go_s: float
    t_all_assembled_s: float
    t_complete_s: float
    wall_s: float
    sim_s: float
    vehicle_steps: int


def release_into(state: FleetState, rows: np.ndarray, cfg: ScenarioConfig, t_s: float, rng: np.random.Generator) -> None:
    """Put vehicles `rows` into free flight at the carrier's position and velocity
    with attitudes drawn from the carrier's distribution, rotors at hover speed."""
    rot, omega = sample_release_attitudes(cfg.carrier, len(rows), rng)
    state.pos_ned_m[rows] = carrier_position_ned_m(cfg.carrier, t_s)
    state.vel_ned_mps[rows] = cfg.carrier.vel_ned_mps
    state.rot_body_to_ned[rows] = rot
    state.omega_body_radps[rows] = omega
    state.rotor_speed_radps[rows] = hover_rotor_speed_radps(cfg.vehicle)
    state.ctrl_integral[rows] = 0.0


def run_scenario(cfg: ScenarioConfig, progress: bool = True, clock=None) -> RunResult:
    """Fly the scenario headless and return the recorded run.

    Args:
        cfg: validated scenario.
        progress: show a tqdm progress bar over simulated time.
        clock: wall-clock function (seconds) for the timing figures; time.perf_counter by default.
    Raises:
        FormationUnstableError: the mission's consensus gains are not stabilising.
    """
    clock = clock or time.perf_counter
    rng = np.random.default_rng(cfg.seed)
    mission = Mission(cfg.mission)
    n = mission.n
    physics = Physics(
        cfg.vehicle, cfg.inner_loop, dt_s=1.0 / cfg.physics.rate_hz, wind=cfg.physics.wind,
        ground_z_m=cfg.physics.ground_z_m, rng=rng,
    )
    agent = Agent(mission, np.arange(n))
    dt_agent = 1.0 / cfg.agent.rate_hz
    sub_steps = int(round(cfg.physics.rate_hz / cfg.agent.rate_hz))
    log_every = int(round(cfg.agent.rate_hz / cfg.output.log_rate_hz))

    state = FleetState.zeros(n)
    released = np.zeros(n, dtype=bool)
    rel_s = release_times_s(cfg.carrier, n)
    rel_pos = carrier_position_ned_m(cfg.carrier, rel_s)
    phase = np.zeros(n, dtype=np.int8)
    assembled = np.zeros(n, dtype=bool)
    phase_entry = np.full((n, len(Phase)), np.nan)
    phase_entry[:, Phase.LAUNCH] = 0.0
    safety = SafetyTracker(cfg.safety.separation_m)
    rec = Recorder()
    t_complete = math.nan
    t_all_assembled = math.nan
    wall0 = clock()
    n_ticks = int(math.ceil(cfg.duration_s / dt_agent))
    vehicle_steps = 0
    bar = tqdm(total=round(cfg.duration_s), unit="sim-s", disable=not progress, desc=cfg.name, mininterval=0.5)
    for k in range(n_ticks + 1):
        t = k * dt_agent
        due = ~released & (rel_s <= t + 1e-9)
        if due.any():
            release_into(state, np.flatnonzero(due), cfg, t, rng)
            released |= due
        docked = ~released
        state.pos_ned_m[docked] = carrier_position_ned_m(cfg.carrier, t)
        state.vel_ned_mps[docked] = cfg.carrier.vel_ned_mps

        tilt = frames.tilt_rad(state.rot_body_to_ned)
        own = OwnState(state.pos_ned_m, state.vel_ned_mps, tilt, released)
        known = np.where(released[:, None], state.pos_ned_m, np.nan)
        swarm = SwarmView(known, np.where(released[:, None], state.vel_ned_mps, np.nan), phase, assembled)
        out = agent.step(t, own, swarm)
        changed = out.phase != phase
        for v in np.flatnonzero(changed):
            phase_entry[v, out.phase[v]] = t
        phase, assembled = out.phase, out.assembled
        if math.isnan(t_all_assembled) and assembled.all():
            t_all_assembled = t

        slot = mission.slot_ned_m(mission.tau_s(t, out.t_go_s))
        airborne = np.flatnonzero(released)
        safety.update(t, airborne, state.pos_ned_m[airborne], mission)
        if k % log_every == 0:
            rec.add(t, state, out.setpoint, slot, phase)

        if math.isnan(t_complete) and np.all(phase == Phase.HOVER):
            dev = np.linalg.norm(state.pos_ned_m - slot, axis=1).max()
            if dev < cfg.completion_tol_m:
                t_complete = t
        if not math.isnan(t_complete) and t >= t_complete + cfg.completion_hold_s:
            break
        if k == n_ticks:
            break
        physics.step(state, out.setpoint, n_steps=sub_steps, active=released)
        vehicle_steps += sub_steps * int(released.sum())
        if int(t + dt_agent) != int(t):
            bar.update(1)
            bar.set_postfix_str(_phase_summary(phase))
    bar.total = bar.n  # finished early (mission complete): close the bar at 100 %
    bar.close()
    wall = clock() - wall0
    return RunResult(
        cfg, mission, rec.arrays(), rel_s, rel_pos, phase_entry, safety, float(out.t_go_s), t_all_assembled, t_complete,
        wall, t, vehicle_steps,
    )


def _phase_summary(phase: np.ndarray) -> str:
    counts = np.bincount(phase, minlength=len(Phase))
    return " ".join(f"{p.name.lower()}:{counts[p]}" for p in Phase if counts[p])


def save_log(result: RunResult, out_dir: Path) -> Path:
    """Write every recorded state of every vehicle to out_dir/telemetry.npz."""
    path = out_dir / "telemetry.npz"
    np.savez_compressed(
        path, release_s=result.release_s, release_pos_ned_m=result.release_pos_ned_m,
        phase_entry_s=result.phase_entry_s, offsets_ned_m=result.mission.offsets_ned_m, **result.log,
    )
    return path
