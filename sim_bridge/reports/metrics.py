"""Scoring a run: what it achieved, in SI units, with the must-show checks (typed in results.py)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion import frames
from companion.agent import IN_FORMATION, Phase
from sim_bridge.reports.launch_so3 import So3Study
from sim_bridge.reports.launch_study import LaunchComparison
from sim_bridge.reports.record import RunResult
from sim_bridge.reports.results import (
    Assembly,
    CommandOutcome,
    CommandsOutcome,
    FormationDeviation,
    LandingOutcome,
    MissionOutcome,
    ObstacleClearance,
    Performance,
    RotorFailureOutcome,
    RunMetrics,
    Separation,
    Series,
    Stabilisation,
    VehicleSettle,
)
from sim_bridge.reports.results import finite_or_none as _f
from sim_bridge.scenario import ends_landed


def formation_deviation(result: RunResult) -> tuple[np.ndarray, np.ndarray]:
    """Max over formation-phase vehicles of |p_i - h_i(t)| per log sample. Vehicles whose
    agent had fallen silent (a fleet run with a crashed companion) are left out.

    Returns: t_s (T,), max_dev_m (T,) (NaN where no vehicle is in formation).
    """
    log = result.log
    dev = np.linalg.norm(log["pos_ned_m"] - log["slot_ned_m"], axis=2)
    in_form = IN_FORMATION[log["phase"]]
    if "counted" in log:
        in_form = in_form & log["counted"]
    masked = np.where(in_form, dev, -np.inf).max(axis=1)
    return log["t_s"], np.where(np.isfinite(masked), masked, np.nan)


def stabilisation(result: RunResult) -> list[VehicleSettle]:
    """Per vehicle: settle time after release and drift from the release point."""
    cfg = result.cfg.mission.phases
    log = result.log
    t = log["t_s"]
    tilt = frames.tilt_rad(frames.quat_wxyz_to_rot(log["att_q_wxyz"].astype(float)))
    speed = np.linalg.norm(log["vel_ned_mps"], axis=2)
    calm = (tilt < np.radians(cfg.stable_tilt_deg)) & (speed < cfg.stable_speed_mps)
    rows = []
    for v in range(result.mission.n):
        t_rel = float(result.release_s[v])
        t_asm = result.phase_entry_s[v, Phase.ASSEMBLE]
        # (a vehicle never released has no window)
        window: np.ndarray | list = np.flatnonzero((t >= t_rel - 1e-9) & (t <= t_asm + 1e-9)) if not math.isnan(t_asm) else []
        if not len(window):
            rows.append(VehicleSettle(vehicle=v + 1, release_s=t_rel, stabilised=False))
            continue
        bad = window[~calm[window, v]]
        k = window[0] if len(bad) == 0 else min(bad[-1] + 1, window[-1])
        disp = log["pos_ned_m"][k, v] - result.release_pos_ned_m[v]
        rows.append(VehicleSettle(
            vehicle=v + 1, release_s=t_rel, stabilised=True, settle_time_s=float(t[k] - t_rel),
            drift_m=float(np.linalg.norm(disp)), drift_horizontal_m=float(np.linalg.norm(disp[:2])),
            altitude_loss_m=float(max(0.0, disp[2])),
        ))
    return rows


def rotor_failures(result: RunResult) -> list[RotorFailureOutcome]:
    """Per injected failure: detection by the vehicle's own agent and where it ended."""
    out = []
    ground = result.cfg.physics.ground_z_m
    for v in np.flatnonzero(np.isfinite(result.failed_at_s)):
        t_fail = float(result.failed_at_s[v])
        t_det = _f(result.phase_entry_s[v, Phase.FAILED])
        z = float(result.log["pos_ned_m"][-1, v, 2]) if len(result.log["t_s"]) else math.nan
        out.append(RotorFailureOutcome(
            vehicle=int(v) + 1, failed_at_s=t_fail, detected_at_s=t_det,
            detection_latency_s=None if t_det is None else t_det - t_fail,
            final_height_m=_f(ground - z) if ground is not None else None))
    return out


def _hover_end_index(result: RunResult) -> int:
    """The log sample where the formation is judged: the last one, or for a mission that
    lands the last before the first vehicle began to land (-1: no such sample)."""
    t = result.log["t_s"]
    if not math.isfinite(result.t_land_start_s):
        return len(t) - 1
    return int(np.searchsorted(t, result.t_land_start_s, side="left")) - 1


def commands_outcome(result: RunResult) -> CommandsOutcome | None:
    """The swarm commands of a run, with each vehicle's lag after each effective time (None:
    a run without commands). A vehicle whose rotor failed before a command is not judged on it."""
    if not result.commands:
        return None
    out, lags_all, in_time = [], [], True
    for c in result.commands:
        if c.seq == 0:
            out.append(CommandOutcome(0, c.kind, c.issued_s, None, c.refused, len(c.applied_s), 0, 0, None, None,
                                      None, 0))
            continue
        judged = ~(result.failed_at_s <= c.effective_s) if len(result.failed_at_s) else np.ones(len(c.applied_s), bool)
        lag = c.applied_s[judged] - c.effective_s
        done = lag[np.isfinite(lag)]
        ok = int(np.sum(done <= 1.0 + 1e-9))
        in_time &= ok == int(judged.sum())
        lags_all.append(done)
        out.append(CommandOutcome(
            c.seq, c.kind, c.issued_s, _f(c.effective_s), None, int(judged.sum()), int(np.isfinite(c.held_s[judged]).sum()),
            len(done), _f(np.percentile(done, 50)) if len(done) else None,
            _f(np.percentile(done, 95)) if len(done) else None, _f(done.max()) if len(done) else None, ok))
    every = np.concatenate(lags_all) if lags_all else np.zeros(0)
    return CommandsOutcome(out, _f(np.percentile(every, 50)) if len(every) else None,
                           _f(np.percentile(every, 95)) if len(every) else None,
                           _f(every.max()) if len(every) else None, bool(in_time),
                           sum(1 for c in result.commands if c.seq == 0))


def landing(result: RunResult) -> LandingOutcome | None:
    """The landing of a mission that lands (None for one that holds station): who is down,
    and how close two vehicles came while any was descending. Judged on the vehicles
    that are counted (a live agent) and healthy (no rotor failure) at the end."""
    if not ends_landed(result.cfg):
        return None
    log = result.log
    t = log["t_s"]
    if not len(t):
        return LandingOutcome(None, 0, 0, None, None, 0)
    judged = log["counted"][-1] & ~(result.failed_at_s <= t[-1]) if len(result.failed_at_s) else log["counted"][-1]
    down = log["down"][:, judged] if "down" in log else np.zeros((len(t), int(judged.sum())), bool)
    all_down = np.flatnonzero(down.all(axis=1)) if down.shape[1] else np.zeros(0, int)
    landing_now = (log["phase"][:, judged] == Phase.LAND).any(axis=1)
    d_min, below = math.inf, set()
    pos = log["pos_ned_m"][landing_now][:, judged].astype(float)
    ids = np.flatnonzero(judged)
    sep = result.cfg.safety.separation_m
    for p in pos:  # (samples while landing) x (pairs)
        d = np.linalg.norm(p[:, None, :] - p[None], axis=2)
        iu = np.triu_indices(len(p), 1)
        if len(iu[0]):
            d_min = min(d_min, float(d[iu].min()))
            for a, b in zip(*(x[d[iu] < sep] for x in iu)):
                below.add((int(ids[a]), int(ids[b])))
    return LandingOutcome(
        land_start_s=_f(result.t_land_start_s), vehicles_down=int(down[-1].sum()) if len(down) else 0,
        vehicles_judged=int(judged.sum()), all_down_s=float(t[all_down[0]]) if len(all_down) else None,
        min_pair_distance_descending_m=d_min if math.isfinite(d_min) else None,
        pairs_below_safety_distance_descending=len(below))


def _stat(values: list[float], fn) -> float | None:
    return _f(fn(values)) if values else None


def compute_metrics(result: RunResult, launch_study: list[LaunchComparison] | None,
                    launch_so3: So3Study | None = None, ended_early: str | None = None) -> RunMetrics:
    """Score one run (headless or fleet) against the paper's figures and the checks.

    Args:
        ended_early: "interrupted" or "aborted" for a run stopped before its end: scored as
            far as it got, but never as a completed mission.
    """
    cfg = result.cfg
    t, dev = formation_deviation(result)
    judged_at = _hover_end_index(result)
    stab = stabilisation(result)
    settle = [r.settle_time_s for r in stab if r.settle_time_s is not None]
    drift = [r.drift_m for r in stab if r.drift_m is not None]
    t_go = result.t_go_s
    transit = (t >= t_go) if not math.isnan(t_go) else np.zeros_like(t, dtype=bool)
    s = result.safety
    every = max(1, int(round(cfg.output.log_rate_hz)))  # ~1 Hz series in the JSON
    m = RunMetrics(
        scenario=cfg.name, seed=cfg.seed, n_vehicles=result.mission.n,
        inner_loop_controller=cfg.inner_loop.controller,
        stabilisation=Stabilisation(
            all_stabilised=all(r.stabilised for r in stab),
            max_settle_time_s=_stat(settle, max), mean_settle_time_s=_stat(settle, np.mean),
            max_drift_m=_stat(drift, max), mean_drift_m=_stat(drift, np.mean), per_vehicle=stab,
        ),
        assembly=Assembly(
            all_assembled_s=_f(result.t_all_assembled_s),
            assembly_time_after_last_release_s=_f(result.t_all_assembled_s - result.release_s.max()),
            transit_start_s=_f(t_go), transit_start_spread_s=_f(result.t_go_spread_s),
        ),
        link=result.link,
        formation_deviation=FormationDeviation(
            final_max_m=_f(dev[judged_at]) if len(dev) and judged_at >= 0 else None,
            max_during_transit_m=_f(np.nanmax(dev[transit])) if transit.any() else None,
            series_1hz=Series(t_s=t[::every].round(3).tolist(), max_m=[_f(x) for x in dev[::every]]),
        ),
        separation=Separation(
            safety_distance_m=cfg.safety.separation_m, min_pair_distance_m=_f(s.min_pair_dist_m),
            min_pair_time_s=_f(s.min_pair_time_s), min_pair_vehicles=[s.min_pair[0] + 1, s.min_pair[1] + 1],
            pairs_below_safety_distance=len(s.violating_pairs), sampled_at_hz=cfg.agent.rate_hz,
            collision_distance_m=s.collision_m, collisions=len(s.colliding_pairs),
            min_failed_distance_m=_f(s.min_failed_dist_m) if math.isfinite(s.min_failed_dist_m) else None,
            failed_contacts=len(s.failed_contacts),
        ),
        rotor_failures=rotor_failures(result),
        obstacles=ObstacleClearance(
            min_clearance_m=_f(s.min_clearance_m) if math.isfinite(s.min_clearance_m) else None,
            min_clearance_time_s=_f(s.min_clearance_time_s),
            min_clearance_vehicle=s.min_clearance_vehicle + 1 if s.min_clearance_vehicle >= 0 else None,
            margin_m=cfg.safety.obstacle_margin_m,
        ),
        mission=MissionOutcome(completed=ended_early is None and not math.isnan(result.t_complete_s),
                               completion_time_s=_f(result.t_complete_s) if ended_early is None else None,
                               ended_early=ended_early, landed_early_s=_f(result.t_landed_early_s)
                               if math.isfinite(result.t_landed_early_s) else None),
        landing=landing(result),
        commands=commands_outcome(result),
        performance=Performance(
            wall_s=result.wall_s, sim_s=result.sim_s,
            real_time_factor=result.sim_s / result.wall_s if result.wall_s > 0 else None,
            vehicle_steps=result.vehicle_steps,
            vehicle_steps_per_s=result.vehicle_steps / result.wall_s if result.wall_s > 0 else None,
            physics_rate_hz=cfg.physics.rate_hz, agent_rate_hz=cfg.agent.rate_hz,
        ),
        launch_study=launch_study, launch_so3=launch_so3,
    )
    return dataclasses.replace(m, checks=_checks(m, cfg))


def _checks(m: RunMetrics, cfg) -> dict[str, bool]:
    """The issue's acceptance criteria, evaluated on this run."""
    clearance = m.obstacles.min_clearance_m
    checks = {
        "all_stabilised": m.stabilisation.all_stabilised,
        "mission_completed": m.mission.completed,
        "final_formation_deviation_below_tol": (m.formation_deviation.final_max_m or math.inf) < cfg.completion_tol_m,
        "min_separation_ok": (m.separation.min_pair_distance_m or 0.0) >= cfg.safety.separation_m,
        "no_collisions": m.separation.collisions == 0,
        "obstacle_clearance_ok": clearance is None or clearance >= cfg.safety.obstacle_margin_m,
    }
    if m.landing is not None:  # the formation is judged at the end of the hover, the landing here
        checks["landing_all_down"] = m.landing.all_down_s is not None
        checks["landing_separation_ok"] = (m.landing.min_pair_distance_descending_m or math.inf) >= \
            cfg.safety.separation_m
    if m.commands is not None:  # issue 19: every vehicle applies every command within 1 s
        checks["commands_applied_within_1s"] = m.commands.all_applied_within_1s
        checks["commands_accepted"] = m.commands.refused == 0
    if m.rotor_failures:  # every failed vehicle's agent declared it, so its neighbours could drop it
        checks["rotor_failures_detected"] = all(r.detection_latency_s is not None for r in m.rotor_failures)
    for c in m.launch_study or []:
        g = c.geometric
        if c.roll_deg == 90.0:  # issue 9: within 1.0 s, and better than PID on all three figures
            checks["geometric_roll90_settles_within_1s_and_beats_pid"] = bool(
                g.settling_time_s is not None and g.settling_time_s <= 1.0 and c.geometric_beats_pid())
        elif c.roll_deg == 179.0:  # issue 9: at most 5 m lost, and better than PID on all three
            checks["geometric_roll179_loses_under_5m_and_beats_pid"] = bool(
                g.altitude_loss_m <= 5.0 and c.geometric_beats_pid())
    if m.launch_so3 is not None and m.launch_so3.draws.n:
        checks["so3_launches_all_recover_and_geometric_beats_pid"] = m.launch_so3.geometric_wins()
    return checks
