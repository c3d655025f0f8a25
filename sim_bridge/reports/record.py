"""What a run recorded, shared by the headless runner and the SITL's recorder.

`MissionTracker` turns a stream of (time, true fleet state, phases, flags, transit
starts) into everything metrics.json and the figures read: the logged
trajectories, first entry into each phase, separation and obstacle clearance,
assembly and completion times. The headless runner feeds it its agents' outputs;
the SITL feeds it the true physics state and what the agents published on the
swarm radio. `save_run` / `load_run` carry a RunResult across processes.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit
from scipy.spatial.distance import pdist

from companion import frames
from companion.agent import Phase
from companion.mission import Mission
from companion.state import FleetSetpoint, FleetState
from sim_bridge.scenario import ScenarioConfig, ends_landed
from sim_bridge.world.jit import compiled
from sim_bridge.world.transport import LinkStats

_HOVER = int(Phase.HOVER)
_LAND = int(Phase.LAND)
_rot_to_quat = compiled(frames.rot_to_quat_rows)


@dataclass
class SafetyTracker:
    """Running minima of separation and obstacle clearance, sampled every agent tick.

    Pairs of healthy vehicles are judged against separation_m and collision_m; a vehicle
    whose rotor has failed (sim_bridge.world.faults) is tracked apart: how close it came to a
    healthy one, and which healthy ones it touched (within collision_m).
    """

    separation_m: float
    min_pair_dist_m: float = math.inf
    min_pair_time_s: float = math.nan
    min_pair: tuple[int, int] = (-1, -1)
    violating_pairs: set[tuple[int, int]] = field(default_factory=set)
    min_clearance_m: float = math.inf
    min_clearance_time_s: float = math.nan
    min_clearance_vehicle: int = -1
    collision_m: float = 0.2
    colliding_pairs: set[tuple[int, int]] = field(default_factory=set)
    """Healthy pairs whose centres came within collision_m."""
    min_failed_dist_m: float = math.inf
    """Closest approach of a failed vehicle to a healthy one."""
    failed_contacts: set[tuple[int, int]] = field(default_factory=set)
    """(failed, healthy) pairs within collision_m."""

    def update(self, t_s: float, ids: np.ndarray, pos: np.ndarray, mission: Mission,
               healthy: np.ndarray | None = None) -> None:
        """ids: (k,) vehicle ids of the airborne vehicles, pos: (k, 3) their positions,
        healthy: (k,) bool, no rotor failed (default all)."""
        k: int | np.signedinteger  # (a pair index from np.flatnonzero, then the row closest to an obstacle)
        if healthy is not None and not healthy.all():
            bad = ~healthy
            if healthy.any():
                d = np.linalg.norm(pos[bad][:, None, :] - pos[healthy][None], axis=2)
                self.min_failed_dist_m = min(self.min_failed_dist_m, float(d.min()))
                for a, b in zip(*np.nonzero(d < self.collision_m)):
                    self.failed_contacts.add((int(ids[bad][a]), int(ids[healthy][b])))
            ids, pos = ids[healthy], pos[healthy]
        if len(ids) >= 2:
            d_min, i, j, n_close = _closest_pair(pos, self.separation_m)
            if d_min < self.min_pair_dist_m:
                self.min_pair_dist_m, self.min_pair_time_s = d_min, t_s
                self.min_pair = (int(ids[i]), int(ids[j]))
            if n_close:  # rare: list the offending pairs
                d = pdist(pos)
                for k in np.flatnonzero(d < self.separation_m):
                    a, b = _pair_from_condensed(int(k), len(ids))
                    pair = (int(ids[a]), int(ids[b]))
                    self.violating_pairs.add(pair)
                    if d[k] < self.collision_m:
                        self.colliding_pairs.add(pair)
        if len(ids) and len(mission.obstacle_radii_m):
            gap, k = _closest_obstacle(np.ascontiguousarray(pos, float), mission.obstacle_centres_ned_m,
                                       mission.obstacle_radii_m)
            if gap < self.min_clearance_m:
                self.min_clearance_m, self.min_clearance_time_s = gap, t_s
                self.min_clearance_vehicle = int(ids[k])

    def to_json(self) -> dict:
        return {"separation_m": self.separation_m, "min_pair_dist_m": self.min_pair_dist_m,
                "min_pair_time_s": self.min_pair_time_s, "min_pair": list(self.min_pair),
                "violating_pairs": sorted(list(p) for p in self.violating_pairs),
                "min_clearance_m": self.min_clearance_m, "min_clearance_time_s": self.min_clearance_time_s,
                "min_clearance_vehicle": self.min_clearance_vehicle, "collision_m": self.collision_m,
                "colliding_pairs": sorted(list(p) for p in self.colliding_pairs),
                "min_failed_dist_m": self.min_failed_dist_m,
                "failed_contacts": sorted(list(p) for p in self.failed_contacts)}

    @classmethod
    def from_json(cls, sf: dict) -> "SafetyTracker":
        return cls(sf["separation_m"], sf["min_pair_dist_m"], sf["min_pair_time_s"], tuple(sf["min_pair"]),
                   {tuple(p) for p in sf["violating_pairs"]}, sf["min_clearance_m"], sf["min_clearance_time_s"],
                   sf["min_clearance_vehicle"], sf["collision_m"], {tuple(p) for p in sf["colliding_pairs"]},
                   sf["min_failed_dist_m"], {tuple(p) for p in sf["failed_contacts"]})


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


@njit(cache=True)
def _closest_obstacle(pos: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> tuple[float, int]:
    """Smallest gap between (k, 3) points and spheres (m, 3), (m,), and whose it is."""
    best, bi = np.inf, 0
    for i in range(pos.shape[0]):
        for j in range(centres.shape[0]):
            d = np.sqrt((pos[i, 0] - centres[j, 0]) ** 2 + (pos[i, 1] - centres[j, 1]) ** 2
                        + (pos[i, 2] - centres[j, 2]) ** 2) - radii[j]
            if d < best:
                best, bi = d, i
    return best, bi


def warm_up() -> None:
    """Compile (or load from cache) the tracker's kernel before a real-time run needs it."""
    _closest_pair(np.zeros((2, 3)), 1.0)
    _closest_obstacle(np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1))


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
    counted: list = field(default_factory=list)
    """Per sample and vehicle: its agent was alive (the fleet leaves out crashed companions)."""
    down: list = field(default_factory=list)
    """Per sample and vehicle: landed and disarmed (recorded only for a mission that lands)."""
    _all_counted: np.ndarray = field(default_factory=lambda: np.ones(0, bool), repr=False)

    def add(self, t_s: float, st: FleetState, sp: FleetSetpoint, slot: np.ndarray, phase: np.ndarray,
            counted: np.ndarray | None = None, down: np.ndarray | None = None) -> None:
        self.t_s.append(t_s)
        self.pos_ned_m.append(st.pos_ned_m.astype(np.float32))
        self.vel_ned_mps.append(st.vel_ned_mps.astype(np.float32))
        self.rot_body_to_ned.append(st.rot_body_to_ned.copy())  # -> quaternions once, in arrays()
        self.omega_body_radps.append(st.omega_body_radps.astype(np.float32))
        self.rotor_speed_radps.append(st.rotor_speed_radps.astype(np.float32))
        self.acc_cmd_ned_mps2.append(sp.acc_ned_mps2.astype(np.float32))
        self.slot_ned_m.append(slot.astype(np.float32))
        self.phase.append(phase.astype(np.int8))
        if counted is None:  # one shared all-true row (arrays() stacks copies of the rows)
            if len(self._all_counted) != len(phase):
                self._all_counted = np.ones(len(phase), bool)
            counted = self._all_counted
        self.counted.append(np.asarray(counted, bool))
        if down is not None:
            self.down.append(np.array(down, bool))

    def arrays(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(v) for k, v in self.__dict__.items()
               if k not in ("rot_body_to_ned", "_all_counted") and not (k == "down" and not v)}
        rot = np.asarray(self.rot_body_to_ned).reshape(-1, 3, 3)
        q = np.empty((len(rot), 4))
        _rot_to_quat(rot, q)  # the compiled twin of frames.rot_to_quat_wxyz
        out["att_q_wxyz"] = q.reshape(len(self.t_s), -1, 4).astype(np.float32)
        return out


@dataclass
class CommandRecord:
    """One swarm command of a run (its `commands:` schedule, or an operator's): what the source
    made of it and when each vehicle had it.

    Attributes:
        seq: the plan's seq (0: the source refused the command; `refused` says why).
        kind: the command (hold, resume, goto, formation, exclude, rejoin, land, rtl, abort).
        issued_s: mission time it was issued, s. effective_s: when every agent applies it, s.
        refused: the source's reason, or "".
        held_s: (N,) when each vehicle first held the whole plan (or a newer one), s (NaN: never).
        applied_s: (N,) when each vehicle's agent flew it (or a newer one) first, s (NaN: never).
    """

    seq: int
    kind: str
    issued_s: float
    effective_s: float
    refused: str
    held_s: np.ndarray
    applied_s: np.ndarray

    def to_json(self) -> dict:
        return {"seq": self.seq, "kind": self.kind, "issued_s": self.issued_s, "effective_s": self.effective_s,
                "refused": self.refused, "held_s": self.held_s.tolist(), "applied_s": self.applied_s.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> "CommandRecord":
        def arr(x):
            return np.array([np.nan if v is None else v for v in x], float)

        return cls(int(d["seq"]), d["kind"], float(d["issued_s"]),
                   math.nan if d["effective_s"] is None else float(d["effective_s"]), d["refused"],
                   arr(d["held_s"]), arr(d["applied_s"]))


@dataclass
class RunResult:
    """Everything one run recorded (MissionTracker.result), what metrics, figures and
    run.json are made from: the log arrays (T, N, ...) at output.log_rate_hz, times in s
    of simulated time (NaN: never happened), positions in the mission frame (NED, m), and
    the run's wall and simulated duration (s). save_run / load_run carry it across processes."""

    cfg: ScenarioConfig
    mission: Mission
    log: dict[str, np.ndarray]
    release_s: np.ndarray
    release_pos_ned_m: np.ndarray
    phase_entry_s: np.ndarray  # (N, len(Phase)) first time each vehicle entered each phase
    safety: SafetyTracker
    t_go_s: float
    t_go_spread_s: float
    """Latest minus earliest transit start held by the vehicles at the end (0 = agreed)."""
    t_all_assembled_s: float
    t_complete_s: float
    wall_s: float
    sim_s: float
    vehicle_steps: int
    link: LinkStats = field(default_factory=LinkStats)
    """Neighbour-transport statistics (NeighbourTransport.stats or the SITL's radio medium)."""
    failed_at_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(N,) mission time of each vehicle's injected rotor failure (NaN: healthy)."""
    t_land_start_s: float = math.nan
    """A mission that lands: when the first counted vehicle began to land (the end of the
    hover, where the formation is judged); NaN otherwise."""
    commands: list[CommandRecord] = field(default_factory=list)
    """The swarm commands of the run, in the order issued (empty without a schedule)."""
    t_landed_early_s: float = math.nan
    """A mission that holds station but whose every counted vehicle landed and disarmed
    before it completed (a swarm LAND, e.g. an operator's from the console): when the last
    was down; the run ends there. NaN otherwise."""




class MissionTracker:
    """Phase entries, assembly, completion, safety and the log of one run.

    Args:
        cfg: the scenario; mission: its Mission.
        log_every: log one sample every this many updates.
    """

    def __init__(self, cfg: ScenarioConfig, mission: Mission, log_every: int):
        n = mission.n
        self.cfg, self.mission, self.log_every = cfg, mission, log_every
        self.rec = Recorder()
        self.safety = SafetyTracker(cfg.safety.separation_m, collision_m=cfg.safety.collision_m)
        self.failed_at_s = np.full(n, np.nan)
        self.phase = np.zeros(n, dtype=np.int8)
        self.phase_entry = np.full((n, len(Phase)), np.nan)
        self.phase_entry[:, Phase.LAUNCH] = 0.0
        self.t_all_assembled = math.nan
        self.t_complete = math.nan
        self.landing = ends_landed(cfg)
        """The mission ends in a landing: it is complete when every counted vehicle is down."""
        self.t_land_start = math.nan
        self.t_landed_early = math.nan
        """A mission that holds station: when every counted vehicle was down before it
        completed (RunResult.t_landed_early_s)."""
        self.t_go_s = math.nan
        self.t_go_spread_s = math.nan
        self.updates = 0
        self._all_ids = np.arange(n)
        self._slot_tau, self._slot = math.nan, np.zeros((n, 3))

    def update(self, t_s: float, state: FleetState, inner_sp: FleetSetpoint, released: np.ndarray,
               phase: np.ndarray, assembled: np.ndarray, t_go_s: np.ndarray,
               counted: np.ndarray | None = None, failed_at_s: np.ndarray | None = None,
               down: np.ndarray | None = None, slot_ned_m: np.ndarray | None = None) -> bool:
        """One sample; returns True once the mission has been complete for completion_hold_s.

        A mission that hovers is complete when every counted vehicle hovers within
        completion_tol_m of its slot. A mission that lands (land_after_hover_s) is complete
        when every counted vehicle has landed and disarmed (down: (N,) bool, from the
        autopilots); its formation is judged at the end of the hover (metrics). A mission
        that hovers but whose every counted vehicle is landing and down before it completed
        (a swarm LAND it was not written with, e.g. the operator's) is over, not complete:
        True completion_hold_s after that too (t_landed_early; down is needed for it).

        counted: (N,) bool, the vehicles completion is judged on (default all); a fleet
        run leaves out vehicles whose agent has died (their autopilot holds and lands).
        failed_at_s: (N,) time of each vehicle's injected rotor failure (NaN healthy):
        a failed vehicle leaves completion and the healthy-pair safety figures from then.
        slot_ned_m: (N, 3) each vehicle's reference now, where swarm commands change it (the
        plan's: formation changes, parking); default the mission's own slots.
        """
        healthy = None
        if failed_at_s is not None:
            self.failed_at_s = failed_at_s  # the injector's array, read each tick (copied into the result)
            healthy = ~(self.failed_at_s <= t_s)
            if not healthy.all():
                counted = healthy if counted is None else (np.asarray(counted, bool) & healthy)
        changed = phase != self.phase
        if changed.any():
            for v in np.flatnonzero(changed):
                self.phase_entry[v, phase[v]] = t_s
            self.phase = np.array(phase, dtype=np.int8)
        c = slice(None) if counted is None else np.asarray(counted, bool)
        if math.isnan(self.t_all_assembled) and np.all(assembled[c]):
            self.t_all_assembled = t_s
        go = np.asarray(t_go_s, float)
        lo = float(np.fmin.reduce(go)) if len(go) else math.nan  # NaN = none held
        if lo == lo:
            self.t_go_s, self.t_go_spread_s = lo, float(np.fmax.reduce(go)) - lo
        m = self.mission
        if released.all():  # (every tick after the last launch: no index copies)
            self.safety.update(t_s, self._all_ids, state.pos_ned_m, m, healthy)
        else:
            airborne = np.flatnonzero(released)
            self.safety.update(t_s, airborne, state.pos_ned_m[airborne], m,
                               None if healthy is None else healthy[airborne])
        log = self.updates % self.log_every == 0
        judge = False
        if self.landing:
            landing = self.phase[c] == _LAND
            if math.isnan(self.t_land_start) and landing.any():
                self.t_land_start = t_s
            if math.isnan(self.t_complete) and down is not None and landing.all() and np.all(down[c]):
                self.t_complete = t_s
        else:
            judge = math.isnan(self.t_complete) and bool((self.phase[c] == _HOVER).all())
            if math.isnan(self.t_complete) and math.isnan(self.t_landed_early) and down is not None \
                    and bool((self.phase[c] == _LAND).all()) and bool(np.all(down[c])):
                self.t_landed_early = t_s  # nothing left to fly: the run ends, the mission not completed
        if log or judge:  # the slots are only needed for these
            if slot_ned_m is not None:
                slot = slot_ned_m
            else:
                tau = m.tau_s(t_s, self.t_go_s)
                if tau != self._slot_tau:  # (unchanged while the transit start is not agreed)
                    self._slot, self._slot_tau = m.slot_ned_m(tau), tau
                slot = self._slot
            if log:
                self.rec.add(t_s, state, inner_sp, slot, self.phase, counted, down if self.landing else None)
            if judge and np.linalg.norm(state.pos_ned_m[c] - slot[c], axis=1).max() < self.cfg.completion_tol_m:
                self.t_complete = t_s
        self.updates += 1
        end = self.t_complete if math.isnan(self.t_landed_early) else self.t_landed_early
        return not math.isnan(end) and t_s >= end + self.cfg.completion_hold_s

    def result(self, release_s: np.ndarray, release_pos_ned_m: np.ndarray, wall_s: float, sim_s: float,
               vehicle_steps: int, link: LinkStats, commands: list[CommandRecord] | None = None) -> "RunResult":
        return RunResult(self.cfg, self.mission, self.rec.arrays(), np.asarray(release_s, float),
                         np.asarray(release_pos_ned_m, float), self.phase_entry, self.safety, self.t_go_s,
                         self.t_go_spread_s, self.t_all_assembled, self.t_complete, wall_s, sim_s, vehicle_steps,
                         link, self.failed_at_s.copy(), self.t_land_start, list(commands or []),
                         self.t_landed_early)


def save_log(result: RunResult, out_dir: Path) -> Path:
    """Write every recorded state of every vehicle to out_dir/telemetry.npz."""
    path = out_dir / "telemetry.npz"
    np.savez_compressed(
        path, release_s=result.release_s, release_pos_ned_m=result.release_pos_ned_m,
        # (numpy's stub: mypy cannot rule out that **log holds the bool allow_pickle; its keys are array names)
        phase_entry_s=result.phase_entry_s, offsets_ned_m=result.mission.offsets_ned_m, **result.log,  # type: ignore[arg-type]
    )
    return path


_SCALARS = ("t_go_s", "t_go_spread_s", "t_all_assembled_s", "t_complete_s", "wall_s", "sim_s", "vehicle_steps",
            "t_land_start_s", "t_landed_early_s")


def save_run(result: RunResult, out_dir: Path) -> None:
    """telemetry.npz plus run.json: enough for load_run in another process. run.json is strict
    JSON: a number that is NaN or infinite (not measured, nothing happened) is written as null,
    and load_run restores it."""

    def strict(value):  # every non-finite float as None (no bare NaN or Infinity in the file)
        if isinstance(value, float):
            return value if math.isfinite(value) else None
        if isinstance(value, dict):
            return {k: strict(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [strict(v) for v in value]
        return value

    save_log(result, out_dir)
    s = result.safety
    info = {name: getattr(result, name) for name in _SCALARS}
    info["link"] = dataclasses.asdict(result.link)
    info["safety"] = s.to_json()
    info["failed_at_s"] = result.failed_at_s.tolist()
    info["commands"] = [c.to_json() for c in result.commands]
    (out_dir / "run.json").write_text(json.dumps(strict(info), indent=1, allow_nan=False))


def load_run(out_dir: Path, cfg: ScenarioConfig) -> RunResult:
    """The RunResult save_run wrote (cfg: the same scenario). A null number is what save_run
    wrote for a NaN, or for the infinity a SafetyTracker minimum starts at (nothing measured).
    Also reads the run.json of older versions, which wrote bare NaN and Infinity."""

    def num(value, missing: float = math.nan) -> float:
        return missing if value is None else value

    info = json.loads((out_dir / "run.json").read_text())
    data = dict(np.load(out_dir / "telemetry.npz"))
    sf = dict(info["safety"])
    unbounded = ("min_pair_dist_m", "min_clearance_m", "min_failed_dist_m")  # start at inf, the rest at NaN
    for key in ("min_pair_time_s", "min_clearance_time_s", *unbounded):
        sf[key] = num(sf.get(key), math.inf if key in unbounded else math.nan)
    safety = SafetyTracker.from_json(sf)
    failed_at = np.array([np.nan if x is None else x for x in info["failed_at_s"]], float)
    extra = ("release_s", "release_pos_ned_m", "phase_entry_s", "offsets_ned_m")
    log = {k: v for k, v in data.items() if k not in extra}
    scalar = {name: num(info.get(name)) for name in _SCALARS if name != "vehicle_steps"}
    return RunResult(cfg, Mission(cfg.mission), log, data["release_s"], data["release_pos_ned_m"],
                     data["phase_entry_s"], safety, scalar["t_go_s"], scalar["t_go_spread_s"],
                     scalar["t_all_assembled_s"], scalar["t_complete_s"], scalar["wall_s"], scalar["sim_s"],
                     info["vehicle_steps"], LinkStats.from_json(info["link"]), failed_at, scalar["t_land_start_s"],
                     [CommandRecord.from_json(c) for c in info.get("commands", [])], scalar["t_landed_early_s"])
