"""The SITL's simulated vehicles: their state, autopilots, parameter tables and physics,
stepped one tick at a time. No I/O: what a ground station must hear of (an autopilot's
events, a mode change, a new EKF origin) is handed to a `FleetListener` as it happens,
in the order it happens (sim_bridge.sitl.server publishes it).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Protocol

import numpy as np

from companion.frames import integrate_quat_body_rates
from companion.state import FleetSetpoint, FleetState
from sim_bridge.sitl.autopilot import SEV_CRITICAL, Autopilot
from sim_bridge.sitl.autopilots import autopilot_named
from sim_bridge.sitl.config import SitlConfig
from sim_bridge.sitl.params_table import ParamTable
from sim_bridge.sitl.telemetry import quantised_origin
from sim_bridge.world.autopilot_model import hover_thrust_errors, on_ground_and_slow
from sim_bridge.world.carrier import carrier_position_ned_m, release_times_s, sample_release_attitudes
from sim_bridge.world.estimator import Estimator, bias_disturbance_ned_mps2, to_true_frame
from sim_bridge.world.faults import RotorFaults, resolve_rotor_failures
from sim_bridge.world.physics import Physics, WindField, hover_thrust_norm
from sim_bridge.world.position_loop import PositionController


class FleetListener(Protocol):
    """Who hears what the vehicles do (the server, which tells the ground stations)."""

    def vehicle_changed(self, k: int) -> None:
        """Vehicle k's autopilot has events, a mode or arming change, or a new setpoint:
        publish them, then let the fleet take the setpoint (SimulatedFleet.sync)."""

    def origin_set(self, k: int) -> None:
        """Vehicle k's EKF has (or moved) its origin (GPS_GLOBAL_ORIGIN is due)."""


def spawn_positions_ned_m(cfg: SitlConfig) -> np.ndarray:
    """Ground spawn: a square grid centred on the origin, on the ground plane."""
    n = cfg.vehicles
    cols = int(math.ceil(math.sqrt(n)))
    k = np.arange(n)
    pos = np.zeros((n, 3))
    pos[:, 0] = (k // cols - (cols - 1) / 2) * cfg.spawn.grid_spacing_m
    pos[:, 1] = (k % cols - (cols - 1) / 2) * cfg.spawn.grid_spacing_m
    pos[:, 2] = cfg.ground_z_m
    return pos


def hover_thrust_fraction(cfg: SitlConfig) -> float:
    """Collective thrust that carries the simulated vehicle, as a fraction of maximum."""
    return hover_thrust_norm(cfg.vehicle)


class SimulatedFleet:
    """N vehicles of one autopilot family, stepped together (physics groups share a batch
    step per set of inner-loop gains; each vehicle's position loops have their own gains,
    from its table, and the physics runs them).

    Args:
        cfg: the SITL configuration (its scenario is the world).
        rng: physics and launch randomness (default: seeded from cfg.seed).
        listener: told of what a ground station must hear, as it happens.
    Raises:
        ValueError: a parameter override (cfg.params) that is unknown or refused.
    """

    def __init__(self, cfg: SitlConfig, listener: FleetListener, rng: np.random.Generator | None = None):
        self.cfg = cfg
        self.listener = listener
        self.n = n = cfg.vehicles
        self.rng = rng if rng is not None else np.random.default_rng(cfg.seed)
        self.behaviour = autopilot_named(cfg.dialect)
        """How every vehicle's autopilot behaves (sim_bridge/sitl/autopilots/)."""
        self.dialect = self.behaviour.dialect
        self.carrier = cfg.launch == "carrier"
        self.state = FleetState.zeros(n)
        if self.carrier:
            self.state.pos_ned_m[:] = carrier_position_ned_m(cfg.carrier, 0.0)
            self.state.vel_ned_mps[:] = cfg.carrier.vel_ned_mps
            self.home_ned_m = np.zeros((n, 3))
            self.home_ned_m[:, 2] = cfg.ground_z_m
            self._release_rot, self._release_omega = sample_release_attitudes(cfg.carrier, n, self.rng)
            self._release_t = (release_times_s(cfg.carrier, n) if cfg.carrier.release == "schedule"
                               else np.full(n, math.inf))
        else:
            self.state.pos_ned_m[:] = spawn_positions_ned_m(cfg)
            self.home_ned_m = self.state.pos_ned_m.copy()
        self.released_at_s = np.full(n, np.nan)
        self.released_pos_ned_m = np.full((n, 3), np.nan)
        self.home_alt_amsl_m = cfg.home.alt_amsl_m - cfg.ground_z_m
        self.hover_thrust = hover = hover_thrust_fraction(cfg)
        """The airframe's true hover thrust (fraction of maximum)."""
        # Each autopilot's hover-thrust parameter is off by its own fraction (scenario autopilot.hover_thrust_error)
        self.hover_thrust_error = hover_thrust_errors(cfg.scenario.autopilot.hover_thrust_error, n, cfg.seed)
        self.params = [ParamTable(self.behaviour.param_specs(cfg.inner_loop, k + 1,
                                                             min(0.95, hover * (1.0 + self.hover_thrust_error[k]))),
                                  self.dialect.param_encoding) for k in range(n)]
        for name, value in cfg.params.items():
            for table in self.params:
                if table.index_of(name) is None:
                    raise ValueError(f"params: unknown parameter {name!r} for the {cfg.dialect} dialect")
                if not table.set(name, value):
                    raise ValueError(f"params: {name}={value} refused (range or read-only)")
        self.sim_s = 0.0
        self.ticks = 0
        self.autopilots = [Autopilot(k, k + 1, self.params[k], self.behaviour, self.state, cfg.ground_z_m,
                                     self.home_ned_m[k], docked=self.carrier, now_s=0.0) for k in range(n)]
        self.fleet_sp = FleetSetpoint.empty(n)
        """The inner loop's setpoint of every vehicle (what its autopilot asks for)."""
        self._sp_synced = np.full(n, -1)
        self._rate_q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        self._rates_only = np.zeros(n, bool)
        self.loop = PositionController(n)
        """Every vehicle's position and velocity loops (its autopilot's gains, from its table)."""
        self.estimator = Estimator(cfg.estimator, n, np.random.default_rng([cfg.seed, 0x455354]))
        """GPS/estimator errors and latency on what the autopilots report (and fly on)."""
        self.bias_acc_ned_mps2 = bias_disturbance_ned_mps2(cfg.estimator, n, cfg.seed)
        """(N, 3) what each estimator's bias does to its flying vehicle (as headless)."""
        self.origin_e7: list[tuple[int, int, int] | None] = [None] * n
        """GPS_GLOBAL_ORIGIN (lat 1e7, lon 1e7, alt mm) of each vehicle, None before its fix."""
        self.flight_time_s = np.zeros(n)
        """Armed time of each vehicle, s (the battery model reads it)."""
        # The first GNSS fix of each vehicle (its EKF origin is where it is then); drawn
        # from their own stream so that the launch draws stay those of the seed.
        fix_max = cfg.spawn.gps_fix_delay_max_s
        self.fix_t = np.random.default_rng([cfg.seed, 7]).uniform(0.0, fix_max, n) if fix_max > 0 else np.zeros(n)
        """Simulated time of each vehicle's first GNSS fix, s."""
        self._fix_pending = np.ones(n, bool)
        tc = cfg.time
        self.tick_s = tc.tick_s
        self.steps_per_tick = max(1, int(round(tc.tick_s * tc.physics_rate_hz)))
        self.physics_dt_s = tc.tick_s / self.steps_per_tick
        # One wind for the whole fleet (its own random stream), advanced once per tick and
        # shared by every parameter group's Physics, as headless.
        self.wind_field = WindField(cfg.wind, self.physics_dt_s, np.random.default_rng([cfg.seed, 0x57494E44]))
        self.rotor_faults = RotorFaults(resolve_rotor_failures(cfg.faults, n, cfg.seed), n)
        """Injected rotor failures: from the config (as headless) or MAV_CMD_INJECT_FAILURE."""
        self.vehicle_steps = 0
        """Physics steps taken, summed over vehicles (docked vehicles take none)."""
        self.busy_wall_s = 0.0
        """Wall time spent stepping (physics and autopilots)."""
        self.ap_every = max(1, int(round(1.0 / (tc.autopilot_rate_hz * tc.tick_s))))
        self.physics_groups: dict[tuple, Physics] = {}
        """One Physics per distinct set of inner-loop gains (ParamTable.gain_key)."""
        self.group = np.zeros(n, int)
        """Vehicle k steps with physics_groups[group_keys[group[k]]]."""
        self.group_keys: list[tuple] = []
        self._grouped = 0
        """Vehicles 0.._grouped-1 have a group (they are assigned in order at start-up)."""
        self._param_versions = np.full(n, -1)
        for k in range(n):
            self._update_group(k)

    # ---- what the server asks ---------------------------------------------------------
    def start(self) -> None:
        """First fixes due at time 0, and every vehicle's first setpoint (before the first tick)."""
        self._update_fixes()
        for k in range(self.n):
            self.sync(k)

    def warm_up(self) -> None:
        """Compile (or load) every physics group's stepper now: a first compile in flight
        would stall a real-time loop for seconds."""
        for physics in self.physics_groups.values():
            physics.warm_up()

    def sync(self, k: int) -> None:
        """Take vehicle k's latest setpoint from its autopilot, and its gains if they changed."""
        ap = self.autopilots[k]
        if ap.sp_version != self._sp_synced[k]:
            self._sp_synced[k] = ap.sp_version
            self.fleet_sp.assign(slice(k, k + 1), ap.sp)
            self._rates_only[k] = ap.rates_only
            if ap.rates_only and ap.rate_q_reset:
                ap.rate_q_reset = False
                self._rate_q[k] = ap.sp.att_q_wxyz[0]
        if ap.loop_reset:
            ap.loop_reset = False
            self.loop.reset(k)
        if self.params[k].version != self._param_versions[k]:
            self._update_group(k)

    def has_news(self, k: int) -> bool:
        """Vehicle k's autopilot has something to publish or a setpoint to hand over."""
        ap = self.autopilots[k]
        return bool(ap.events or ap.changed or ap.sp_version != self._sp_synced[k])

    def set_origin(self, k: int, world_ned_m: np.ndarray, origin_e7: tuple[int, int, int]) -> bool:
        """A client asks vehicle k's EKF to move its origin (SET_GPS_GLOBAL_ORIGIN); True if it did."""
        if self.autopilots[k].set_origin(world_ned_m, self.sim_s, requested=True):
            self.origin_e7[k] = origin_e7
            return True
        return False

    # ---- one tick ---------------------------------------------------------------------
    def step(self) -> None:
        """Advance simulation time by one tick (physics, carrier, fixes, autopilots)."""
        t0 = time.perf_counter()
        if self._rates_only.any():
            m = self._rates_only
            self._rate_q[m] = integrate_quat_body_rates(self._rate_q[m], self.fleet_sp.body_rate_radps[m],
                                                        self.tick_s)
            self.fleet_sp.att_q_wxyz[m] = self._rate_q[m]
        for f in self.rotor_faults.update(self.sim_s):  # what a GCS would see of an ESC that quits
            self.autopilots[f.vehicle].events.append((SEV_CRITICAL, f"motor {f.rotor + 1} failed (scenario fault)"))
            self.listener.vehicle_changed(f.vehicle)
        active = np.fromiter((ap.needs_physics for ap in self.autopilots), bool, self.n)
        self.vehicle_steps += int(active.sum()) * self.steps_per_tick
        if active.any():
            # As PX4 and ArduPilot, the position loops' integrators do not run on the ground (judged
            # every tick from the state, so that a lockstep run does not depend on the phase of the
            # 50 Hz autopilot logic)
            st = self.state
            self.loop.reset(on_ground_and_slow(st.pos_ned_m[:, 2], np.linalg.norm(st.vel_ned_mps, axis=1),
                                               self.cfg.ground_z_m))
            self.wind_field.advance(self.steps_per_tick)
            sp, est = self.fleet_sp, self.estimator
            if est.cfg.active:  # each autopilot flies on its own estimate
                sp = dataclasses.replace(sp, pos_ned_m=to_true_frame(sp.pos_ned_m, est.offset_ned_m))
            for g, key in enumerate(self.group_keys):
                mask = active & (self.group == g) if len(self.group_keys) > 1 else active
                if mask.any():
                    self.physics_groups[key].step(self.state, sp, self.steps_per_tick, active=mask,
                                                  rotor_scale=self.rotor_faults.scale,
                                                  acc_ext_ned_mps2=self.bias_acc_ned_mps2, loop=self.loop)
        self.ticks += 1
        self.sim_s = self.ticks * self.tick_s
        if self.carrier:
            self._carrier_update()
        if self._fix_pending.any():
            self._update_fixes()
        armed = np.fromiter((ap.armed for ap in self.autopilots), bool, self.n)
        self.flight_time_s[armed] += self.tick_s
        if not self.carrier and np.isnan(self.released_at_s).any():  # a ground launch "releases" at lift-off
            for k in np.flatnonzero(np.isnan(self.released_at_s)).tolist():
                if not self.autopilots[k].landed:
                    self.released_at_s[k], self.released_pos_ned_m[k] = self.sim_s, self.state.pos_ned_m[k]
        if self.ticks % self.ap_every == 0:
            for k, ap in enumerate(self.autopilots):
                ap.tick(self.sim_s)
                if self.has_news(k):
                    self.listener.vehicle_changed(k)
        self.busy_wall_s += time.perf_counter() - t0

    # ---- internals -------------------------------------------------------------------
    def _update_group(self, k: int) -> None:
        table = self.params[k]
        self._param_versions[k] = table.version
        self.loop.set_gains(k, self.behaviour.position_loop(table, self.hover_thrust))
        key = table.gain_key()
        old = self.group_keys[self.group[k]] if k < self._grouped else None
        if key not in self.physics_groups:
            self.physics_groups[key] = Physics(self.cfg.vehicle, table.inner_loop(self.cfg.inner_loop),
                                               dt_s=self.physics_dt_s, ground_z_m=self.cfg.ground_z_m,
                                               wind=self.wind_field,
                                               rng=np.random.default_rng(self.rng.integers(2**63)))
            self.group_keys.append(key)
        self.group[k] = self.group_keys.index(key)
        self._grouped = max(self._grouped, k + 1)
        if old is not None and old != key and not (self.group[:self._grouped] == self.group_keys.index(old)).any():
            # Nobody flies these gains any more: free the group, or every distinct value a client
            # ever sets would cost a batch step per tick for the rest of the run.
            gone = self.group_keys.index(old)
            del self.physics_groups[old], self.group_keys[gone]
            self.group[self.group > gone] -= 1

    def _update_fixes(self) -> None:
        """Vehicles whose first fix is due get their EKF origin where they are now."""
        due = self._fix_pending & (self.fix_t <= self.sim_s + 1e-9)
        self._fix_pending &= ~due
        for k in np.flatnonzero(due).tolist():
            ap = self.autopilots[k]
            if ap.origin_ned_m is not None:
                continue
            world, q = quantised_origin(self.cfg.home, self.state.pos_ned_m[k])
            ap.set_origin(world, self.sim_s)
            self.origin_e7[k] = q
            self.listener.origin_set(k)

    def _carrier_update(self) -> None:
        t = self.sim_s
        cpos = carrier_position_ned_m(self.cfg.carrier, t)
        for k, ap in enumerate(self.autopilots):
            if not ap.docked:
                continue
            if t >= self._release_t[k] or ap.release_requested:
                st = self.state
                st.pos_ned_m[k] = cpos
                st.vel_ned_mps[k] = self.cfg.carrier.vel_ned_mps
                st.rot_body_to_ned[k] = self._release_rot[k]
                st.omega_body_radps[k] = self._release_omega[k]
                self.released_at_s[k], self.released_pos_ned_m[k] = t, cpos
                ap.on_released(t)
                self.listener.vehicle_changed(k)
            else:
                self.state.pos_ned_m[k] = cpos
