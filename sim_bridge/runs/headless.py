"""Headless runner: the paper's whole scenario in-process, far faster than real time.

The loop is: release due vehicles from the carrier -> deliver the neighbour
states the transport has due -> one batched Agent.step for every vehicle (the
same Agent the MAVLink companion runs for one vehicle, its loops compiled) ->
the autopilot model turns agent setpoints into inner-loop setpoints (throw
recovery, hold, offboard, what the autopilot does when an agent falls silent) ->
publish states at the swarm rate -> injected rotor failures due -> record ->
Physics.step for physics_rate/agent_rate steps with the setpoints held (the
autopilot's position loops, with the gains of the autopilot the scenario names,
`autopilot.name`, and the inner-loop geometric or PID controller run at the physics
rate; each estimator's bias disturbs its vehicle there).

`run_batch` flies several seeds of one scenario side by side: their vehicles are
rows of the same Agent.step and autopilot-model call; everything else is per run.
A sweep uses it to pay the per-tick Python cost once for many runs.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np
from tqdm import tqdm

from companion import frames
from companion.agent import Agent, OwnState, Phase
from companion.config import ConfigError
from companion.control.geometric import pack_setpoint
from companion.link.dialects.base import PositionLoop
from companion.link.limits import SetpointLimits
from companion.mission import Mission
from companion.output import output_stage_for
from companion.state import FleetSetpoint, FleetState
from companion.swarm import SwarmStates, SwarmView, receive_rows, swarm_due, tick_index
from sim_bridge.reports.record import MissionTracker, RunResult
from sim_bridge.runs.commands import ScheduledCommands
from sim_bridge.scenario import ScenarioConfig, expected_end_s
from sim_bridge.sitl.autopilots import UnknownAutopilotBehaviour, autopilot_named
from sim_bridge.sitl.params_table import ParamTable
from sim_bridge.world.autopilot_model import AutopilotModel, hover_thrust_errors
from sim_bridge.world.carrier import carrier_position_ned_m, release_times_s, sample_release_attitudes
from sim_bridge.world.estimator import Estimator, bias_disturbance_ned_mps2, to_true_frame
from sim_bridge.world.faults import RotorFaults, resolve_rotor_failures
from sim_bridge.world.jit import agent_kernels, compiled, output_kernels
from sim_bridge.world.physics import Physics, hover_rotor_speed_radps, hover_thrust_norm
from sim_bridge.world.position_loop import PositionController
from sim_bridge.world.transport import NeighbourTransport, make_transport

TICK_OBSERVERS: list[Callable[[float, SwarmStates | None], None]] = []
"""Called every agent tick with (mission time, the states published then, or None) while
registered: sim_bridge.runs.live streams a run to a console this way. Empty: no cost."""


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


def run_scenario(cfg: ScenarioConfig, progress: bool = True, clock=None,
                 transport: NeighbourTransport | None = None) -> RunResult:
    """Fly the scenario headless and return the recorded run (a batch of one: run_batch).

    Args:
        cfg: validated scenario.
        progress: show a tqdm progress bar over simulated time.
        clock: wall-clock function (seconds) for the timing figures; time.perf_counter by default.
        transport: how published states reach the other vehicles; default from cfg.link
            (seeded from cfg.seed, independent of the physics' random draws).
    Raises:
        FormationUnstableError: the mission's consensus gains are not stabilising.
        ConfigError: a ground-launch mission (only the fleet flies those).
    """
    return run_batch([cfg], progress, clock, None if transport is None else [transport])[0]


class _Run:
    """One seed of a batch: its rows of the batch's arrays, its own random streams,
    physics (wind), link, estimator, faults and record. Everything here is what a
    single run has; only the agent and the autopilot model are shared, row by row."""

    def __init__(self, cfg: ScenarioConfig, mission: Mission, rows: slice, state: FleetState, view: SwarmView,
                 released: np.ndarray, transport: NeighbourTransport | None, log_every: int):
        n = mission.n
        self.cfg, self.rows = cfg, rows
        self.rng = np.random.default_rng(cfg.seed)
        self.physics = Physics(cfg.vehicle, cfg.inner_loop, dt_s=1.0 / cfg.physics.rate_hz, wind=cfg.physics.wind,
                               ground_z_m=cfg.physics.ground_z_m, rng=self.rng)
        self.transport = transport or make_transport(cfg.link, n, cfg.seed)
        self.estimator = Estimator(cfg.estimator, n, np.random.default_rng([cfg.seed, 0x455354])) \
            if cfg.estimator.active else None
        self.faults = RotorFaults(resolve_rotor_failures(cfg.faults, n, cfg.seed), n) if cfg.faults.active else None
        self.bias_acc_ned_mps2 = bias_disturbance_ned_mps2(cfg.estimator, n, cfg.seed) \
            if cfg.estimator.biased else None
        """(n, 3) what each estimator's bias does to its vehicle (as the SITL), or None."""
        self.loop: PositionController | None = None
        """This run's rows of the autopilot model's position loops."""
        # Row views of the batch's arrays: what this run's parts write lands in the batch.
        self.state = FleetState(*(getattr(state, f)[rows] for f in FleetState.__dataclass_fields__))
        # (mypy cannot count the *args: they are the eight arrays of _VIEW_ARRAYS, receive_kernel the next field)
        self.view = SwarmView(*(getattr(view, f)[rows] for f in _VIEW_ARRAYS),  # type: ignore[misc]
                              receive_kernel=view.receive_kernel)
        self.tracker = MissionTracker(cfg, mission, log_every)
        self.commands = ScheduledCommands(cfg, mission, rows) if cfg.commands else None
        """The run's `commands:` schedule (issued, carried on the radio, recorded)."""
        self.released = released[rows]
        self.rel_s = release_times_s(cfg.carrier, n)
        self.next_release = min(self.rel_s) if n else math.inf  # (a float compare per tick)
        self.n_released = 0
        self.vehicle_steps = 0
        self.result: RunResult | None = None


_VIEW_ARRAYS = ("pos_ned_m", "vel_ned_mps", "stamp_s", "phase", "flags", "t_go_s", "received", "ignored_old")


def run_batch(cfgs: list[ScenarioConfig], progress: bool = False, clock=None,
              transports: list[NeighbourTransport] | None = None) -> list[RunResult]:
    """Fly several runs of one scenario that differ only in their seed, side by side.

    Each run's vehicles are rows of one batch: one Agent.step and one autopilot-model
    call cover every run's vehicles (both work row by row, so a row's result does not
    depend on its neighbours in the batch), while every run keeps its own random
    streams, physics, link, estimator, faults and record. So a run's result is the same,
    to the last bit, alone or in any batch (tests/test_headless_batch.py); what a batch
    saves is the per-tick cost of the Python and numpy calls, paid once for all runs.
    A run that completes stops there; the batch goes on until every run has.

    Args:
        cfgs: validated scenarios, equal except for their seed.
        progress: tqdm progress bar over simulated time.
        clock: wall-clock function (s); time.perf_counter by default. Each run's wall_s is
            the batch's wall time until that run ended, divided by the batch size.
        transports: one per run (default: from each cfg.link and seed).
    Returns:
        One RunResult per cfg, in order.
    Raises:
        ValueError: the scenarios differ in more than their seed, or no scenario.
        FormationUnstableError: the mission's consensus gains are not stabilising.
        ConfigError: a ground-launch mission (only the fleet flies those).
    """
    if not cfgs:
        raise ValueError("run_batch needs at least one scenario")
    cfg = cfgs[0]
    if any(dataclasses.replace(c, seed=cfg.seed) != cfg for c in cfgs[1:]):
        raise ValueError("run_batch: the scenarios must differ in their seed only")
    if cfg.mission.launch != "carrier":
        raise ConfigError(f"{cfg.name}: mission.launch is {cfg.mission.launch!r}: the headless runner flies carrier "
                          "launches only; fly a ground launch with `swarmdrop run` (the SITL and agents)")
    clock = clock or time.perf_counter
    mission = Mission(cfg.mission)
    n, n_runs = mission.n, len(cfgs)
    ids = np.arange(n)
    agent = Agent(mission, np.tile(ids, n_runs), kernels=agent_kernels())
    # The agent's output stage (companion.output): the same lines as `swarmdrop agent`'s tick.
    output = output_stage_for(cfg.mission, n * n_runs, limits=SetpointLimits(), kernels=output_kernels())
    view = SwarmView.unknown(n * n_runs, n, receive_kernel=compiled(receive_rows))
    autopilot, loops = _autopilot_model(cfgs, n)
    for row, loop in enumerate(loops):  # what `swarmdrop agent` reads from its autopilot at set-up
        agent.set_autopilot_loop([row], loop)
        output.set_loop([row], loop)
    dt_agent = 1.0 / cfg.agent.rate_hz
    sub_steps = int(round(cfg.physics.rate_hz / cfg.agent.rate_hz))
    log_every = int(round(cfg.agent.rate_hz / cfg.output.log_rate_hz))
    state = FleetState.zeros(n * n_runs)
    released = np.zeros(n * n_runs, dtype=bool)
    runs = [_Run(c, mission, slice(k * n, (k + 1) * n), state, view, released,
                 None if transports is None else transports[k], log_every) for k, c in enumerate(cfgs)]
    for r in runs:
        r.loop = autopilot.loop.view(r.rows)
    to_quat, q_own = compiled(frames.rot_to_quat_rows), np.empty((n * n_runs, 4))  # 1 us, numpy's twin 100 us
    q_known = np.ones(n * n_runs, bool)  # (the simulated attitude is always known)
    estimated = runs[0].estimator is not None  # (the same estimator config in every run)
    p_obs, v_obs, r_obs = np.empty((n * n_runs, 3)), np.empty((n * n_runs, 3)), np.empty((n * n_runs, 3, 3))
    wall0 = clock()
    n_ticks = int(math.ceil(cfg.duration_s / dt_agent))
    # The bar runs to the mission's expected end (from the agreed transit start once there is one).
    bar = tqdm(total=round(expected_end_s(cfg)), unit="sim-s", disable=not progress, desc=cfg.name, mininterval=0.5)
    bar_go = math.nan
    # Who publishes at tick k depends on k modulo the ticks per swarm period only: one
    # mask per offset, from swarm_due itself.
    period_us = round(dt_agent * 1e6)
    n_offsets = max(1, int(round(1e6 / (cfg.mission.swarm.rate_hz * period_us))))
    publish_at = [swarm_due(j * period_us, cfg.mission.swarm.rate_hz, ids, period_us) for j in range(n_offsets)]
    publish_all = [np.tile(m, n_runs) for m in publish_at]
    live = list(runs)
    for k in range(n_ticks + 1):
        t = k * dt_agent
        for r in live:
            if r.next_release <= t + 1e-9:
                due = ~r.released & (r.rel_s <= t + 1e-9)
                release_into(r.state, np.flatnonzero(due), r.cfg, t, r.rng)
                autopilot.release(r.rows.start + np.flatnonzero(due), state)
                r.released |= due  # (a view: the batch's released too)
                r.n_released = int(r.released.sum())
                r.next_release = min(r.rel_s[~r.released], default=math.inf)
            if r.n_released < n:
                docked = ~r.released
                r.state.pos_ned_m[docked] = carrier_position_ned_m(r.cfg.carrier, t)
                r.state.vel_ned_mps[docked] = r.cfg.carrier.vel_ned_mps
            r.transport.deliver(t, r.view)
            if r.commands is not None:  # the schedule's plans on the radio, into the agents' books
                r.commands.step(t, agent.plans, r.state.pos_ned_m, agent.t_go_s[r.rows])
            if r.estimator is not None:  # what the autopilot's estimator would report (as the SITL does)
                p_obs[r.rows], v_obs[r.rows], r_obs[r.rows] = r.estimator.observe(
                    t, r.state.pos_ned_m, r.state.vel_ned_mps, r.state.rot_body_to_ned)
        if estimated:
            to_quat(r_obs, q_own)
            own = OwnState(p_obs, v_obs, q_own, np.full(n * n_runs, t), released, autopilot.ready)
        else:
            to_quat(state.rot_body_to_ned, q_own)
            own = OwnState(state.pos_ned_m, state.vel_ned_mps, q_own, np.full(n * n_runs, t), released,
                           autopilot.ready)
        out = agent.step(t, own, view)
        offset = tick_index(round(t * 1e6), period_us) % n_offsets
        per_run = int(publish_at[offset].sum())
        published = out.published.select(publish_all[offset]) if per_run else None
        for observe in TICK_OBSERVERS:
            observe(t, published)
        output.set_plan(t, out.setpoint, q_known, out.drive_ned_m, out.acc_ff_max_mps2, out.acc_bias_ned_mps2)
        output.step(t, own.pos_ned_m, own.vel_ned_mps, own.att_q_wxyz)
        sp = autopilot.setpoint(state, output.setpoint, t)
        autopilot.detect_landing(t, state)
        if estimated:  # the autopilot flies on its estimate (sim_bridge/world/estimator.py)
            for r in live:
                if r.estimator is not None:
                    sp.pos_ned_m[r.rows] = to_true_frame(sp.pos_ned_m[r.rows], r.estimator.offset_ned_m)
        packed = pack_setpoint(sp)  # once for every run
        for r in list(live):
            i = r.rows.start // n
            if published is not None:  # the selected rows come run by run, per_run each
                r.transport.publish(t, published.rows(slice(i * per_run, (i + 1) * per_run)), r.state.pos_ned_m)
            if r.faults is not None:
                r.faults.update(t)
            sp_r = FleetSetpoint(*(getattr(sp, f)[r.rows] for f in FleetSetpoint.__dataclass_fields__))
            done = r.tracker.update(t, r.state, sp_r, r.released, out.phase[r.rows], out.assembled[r.rows],
                                    out.t_go_s[r.rows], failed_at_s=None if r.faults is None else r.faults.failed_at_s,
                                    down=autopilot.disarmed[r.rows],
                                    slot_ned_m=None if r.commands is None else out.slot_ned_m[r.rows])
            if r.commands is not None:
                done = done and r.commands.done  # (a schedule runs to its end)
            if done or k == n_ticks:
                r.result = r.tracker.result(r.rel_s, carrier_position_ned_m(r.cfg.carrier, r.rel_s),
                                            (clock() - wall0) / n_runs, t, r.vehicle_steps, r.transport.stats(),
                                            None if r.commands is None else r.commands.records)
                live.remove(r)
                continue
            r.physics.step(r.state, packed[r.rows], n_steps=sub_steps, active=r.released & ~autopilot.disarmed[r.rows],
                           rotor_scale=None if r.faults is None else r.faults.scale,
                           acc_ext_ned_mps2=r.bias_acc_ned_mps2, loop=r.loop)
            r.vehicle_steps += sub_steps * r.n_released
        if not live:
            break
        if int(t + dt_agent) != int(t):
            if progress and math.isnan(bar_go):
                go = out.t_go_s[:n]
                if not np.isnan(go).all():
                    bar_go = float(np.nanmin(go))
                    bar.total = round(expected_end_s(cfg, bar_go))
            bar.total = max(bar.total, bar.n + 1)  # (a mission that runs late)
            bar.update(1)
            bar.set_postfix_str(_phase_summary(out.phase))
    bar.total = bar.n  # finished early (mission complete): close the bar at 100 %
    bar.close()
    results = []
    for r in runs:
        assert r.result is not None  # (every run gets its result by the last tick, k == n_ticks)
        results.append(r.result)
    return results


def _autopilot_model(cfgs: list[ScenarioConfig], n: int) -> tuple[AutopilotModel, list[PositionLoop | None]]:
    """The stand-in for the autopilot the scenarios name (autopilot.name): its SITL
    behaviour's default parameter table gives the position loops' gains and the loss
    behaviour; each vehicle's hover-thrust parameter is off by its run's draw. Also each
    row's position loops as the agent's dialect reads them from that table (what
    `swarmdrop agent` reads from its autopilot at set-up).

    Raises:
        ConfigError: no SITL behaviour has that name (its gains and parameters are unknown).
    """
    cfg = cfgs[0]
    try:
        behaviour = autopilot_named(cfg.autopilot.name)
    except UnknownAutopilotBehaviour as e:
        raise ConfigError(f"{cfg.name}: autopilot.name: {e}") from None
    hover = hover_thrust_norm(cfg.vehicle)
    model = AutopilotModel.docked(n * len(cfgs), cfg.physics.ground_z_m)
    model.upright_first = behaviour.throw_uprights_first
    loss = None
    loops: list[PositionLoop | None] = []
    for r, c in enumerate(cfgs):
        errors = hover_thrust_errors(c.autopilot.hover_thrust_error, n, c.seed)
        for k in range(n):
            table = ParamTable(behaviour.param_specs(c.inner_loop, k + 1, min(0.95, hover * (1.0 + errors[k]))),
                               behaviour.dialect.param_encoding)
            model.loop.set_gains(r * n + k, behaviour.position_loop(table, hover))
            loops.append(behaviour.dialect.position_loop({p: table[p] for p in behaviour.dialect.loop_params}))
            loss = loss or behaviour.loss_behaviour(table)
    if loss is not None:
        model.loss = loss
    return model, loops


def _phase_summary(phase: np.ndarray) -> str:
    counts = np.bincount(phase, minlength=len(Phase))
    return " ".join(f"{p.name.lower()}:{counts[p]}" for p in Phase if counts[p])


