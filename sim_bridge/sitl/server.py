"""The SITL process: N vehicles, one physics loop, clocks, lockstep, endpoints, radio, recorder.

Time: simulation time advances in ticks of `time.tick_s`. Free-running, a tick is
taken every tick_s / speed wall seconds. With `time.start_when_attached` the clock
stays at 0 until that many vehicles have heard from a companion. In lockstep a
tick is only taken once every companion that drives the clock has answered the
current control tick (docs/sitl.md, "Lockstep"); with none, the clock free-runs
at `speed`. HEARTBEATs run on a wall-clock schedule and commands are answered as
they arrive, so client timeouts hold.

I/O: every vehicle has a UDP endpoint (companion.link MavEndpoint: lean codec,
bounded outbox); the loop wakes on readable sockets, handles everything waiting,
and flushes replies; telemetry is flushed once per tick.
"""
from __future__ import annotations

import asyncio
import dataclasses
import math
import os
import signal
import time
from typing import Callable

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.control.geometric import max_thrust_n  # noqa: E402
from companion.frames import geodetic_to_ned, integrate_quat_body_rates  # noqa: E402
from companion.link.dialects import dialect_named  # noqa: E402
from companion.link.endpoints import MavEndpoint, UdpLink  # noqa: E402
from companion.link.msgdef import swarmdrop  # noqa: E402
from companion.link.signing import Signing, SigningCounters, SigningError, TimestampStore, load_key  # noqa: E402
from companion.link.tlog import Tlog  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from companion.mission import Mission  # noqa: E402
from companion.params import GRAVITY_MPS2  # noqa: E402
from companion.state import FleetSetpoint, FleetState  # noqa: E402
from companion.swarm import FLAG_ASSEMBLED, swarm_due  # noqa: E402
from sim_bridge.carrier import carrier_position_ned_m, release_times_s, sample_release_attitudes  # noqa: E402
from sim_bridge.estimator import Estimator, to_true_frame  # noqa: E402
from sim_bridge.faults import RotorFaults, resolve_rotor_failures  # noqa: E402
from sim_bridge.physics import Physics, WindField  # noqa: E402
from sim_bridge.record import MissionTracker, RunResult  # noqa: E402
from sim_bridge.record import warm_up as warm_up_tracker  # noqa: E402
from sim_bridge.results import LinkStats  # noqa: E402
from sim_bridge.sitl.autopilot import SEV_CRITICAL, Autopilot  # noqa: E402
from sim_bridge.sitl.clock import SitlClock  # noqa: E402
from sim_bridge.sitl.config import SitlConfig  # noqa: E402
from sim_bridge.sitl.handler import MessageRouter  # noqa: E402
from sim_bridge.sitl.medium import Medium  # noqa: E402
from sim_bridge.sitl.params_table import ParamTable, default_specs  # noqa: E402
from sim_bridge.sitl.telemetry import (  # noqa: E402
    GLOBAL_POSITION_INT,
    GPS_GLOBAL_ORIGIN,
    GPS_RAW_INT,
    HEARTBEAT,
    LOCAL_POSITION_NED,
    STREAMS,
    IntervalScheduler,
    TelemetryBuilder,
    default_interval_s,
    quantised_origin,
)

RADIO_FLUSH_TICKS = 5
"""Vehicles without a control stream still get their radio copies this often (ticks)."""
SILENT_AGENT_S = 3.0
"""A vehicle whose agent has published nothing for this long (simulated) no longer counts
for the recorder's assembly and completion (a crashed companion must not stall the run)."""


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
    return cfg.vehicle.mass_kg * GRAVITY_MPS2 / max_thrust_n(cfg.vehicle)


class SitlServer(SitlClock):
    """All vehicles of one SITL. Implements the handler's SitlContext.

    Args:
        cfg: the SITL configuration.
        wall_clock: monotonic seconds (injected).
        rng: physics and launch randomness (default: seeded from cfg.seed).
        scenario: a `swarmdrop simulate` scenario (sim_bridge.scenario.ScenarioConfig): with
            it the SITL records the mission (MissionTracker) for metrics and figures.
    """

    def __init__(self, cfg: SitlConfig, wall_clock: Callable[[], float] = time.monotonic,
                 rng: np.random.Generator | None = None, scenario=None):
        self.cfg = cfg
        self.n = n = cfg.vehicles
        self.wall_clock = wall_clock
        self.rng = rng if rng is not None else np.random.default_rng(cfg.seed)
        self.dialect = dialect_named(cfg.dialect)
        self.carrier = cfg.spawn.launch == "carrier"
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
        hover = hover_thrust_fraction(cfg)
        self.params = [ParamTable(default_specs(cfg.inner_loop, k + 1, cfg.dialect, min(0.95, hover)),
                                  self.dialect.param_encoding) for k in range(n)]
        for name, value in cfg.params.items():
            for table in self.params:
                if table.index_of(name) is None:
                    raise ValueError(f"params: unknown parameter {name!r} for the {cfg.dialect} dialect")
                if not table.set(name, value):
                    raise ValueError(f"params: {name}={value} refused (range or read-only)")
        self.sim_s = 0.0
        self.ticks = 0
        self.autopilots = [Autopilot(k, k + 1, self.params[k], self.dialect, self.state, cfg.ground_z_m,
                                     self.home_ned_m[k], docked=self.carrier, now_s=0.0) for k in range(n)]
        self.fleet_sp = FleetSetpoint.empty(n)
        self._sp_synced = np.full(n, -1)
        self._rate_q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        self._rates_only = np.zeros(n, bool)
        self._pos_target = np.full((n, 3), np.nan)
        """Offboard position targets as received; the inner loop flies a carrot toward them."""
        self._carrot_m = np.full((n, 3), np.inf)
        """Per vehicle: how far ahead the carrot may be (xy, up, down), so that the position
        loop's steady speed stays under MPC_XY_VEL_MAX / MPC_Z_VEL_MAX_UP / _DN (PX4 caps the
        velocity its position controller asks for; a 1e30 m target must not be flown flat out)."""
        self.telemetry = TelemetryBuilder(self.state, self.autopilots, cfg.home, self.home_ned_m,
                                          cfg.time.epoch_unix_s,
                                          estimator=Estimator(cfg.estimator, self.n, np.random.default_rng([cfg.seed, 0x455354])))
        # The first GNSS fix of each vehicle (its EKF origin is where it is then); drawn
        # from their own stream so that the launch draws stay those of the seed.
        fix_max = cfg.spawn.gps_fix_delay_max_s
        self._fix_t = np.random.default_rng([cfg.seed, 7]).uniform(0.0, fix_max, n) if fix_max > 0 else np.zeros(n)
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
        self.ap_every = max(1, int(round(1.0 / (tc.autopilot_rate_hz * tc.tick_s))))
        self._physics: dict[tuple, Physics] = {}
        self._group = np.zeros(n, int)
        self._group_keys: list[tuple] = []
        self._grouped = 0
        """Vehicles 0.._grouped-1 have a group (they are assigned in order at start-up)."""
        self._param_versions = np.full(n, -1)
        for k in range(n):
            self._update_group(k)
        self.streams = IntervalScheduler(n, STREAMS, [default_interval_s(cfg.streams, m) for m in STREAMS], 0.0)
        self.heartbeats = IntervalScheduler(n, (HEARTBEAT,), [default_interval_s(cfg.streams, HEARTBEAT)],
                                            wall_clock())
        # lockstep bookkeeping
        self._sp_fresh = np.zeros(n, bool)
        self._companion_us = np.full(n, -1, dtype=np.int64)
        self._companion_wall = np.full(n, -math.inf)
        self._control_us = np.full(n, -1, dtype=np.int64)
        self._pub_tick, self._pub = -1, np.zeros(n, bool)
        """_publish_ticks() of tick _pub_tick."""
        self.attached = np.zeros(n, bool)
        """A companion (any client) has talked to the vehicle's endpoint."""
        self.router = MessageRouter(self)
        self.codec = Codec(mavlink, swarmdrop)
        self.endpoints: list[MavEndpoint] = []
        self.gcs: MavEndpoint | None = None
        self.medium: Medium | None = None
        self.tlog: Tlog | None = None
        self.tracker: MissionTracker | None = None
        if scenario is not None:
            log_every = max(1, int(round(1.0 / (scenario.output.log_rate_hz * tc.tick_s))))
            self.tracker = MissionTracker(scenario, Mission(scenario.mission), log_every)
        self.mission_done = False
        self._link_at_done: LinkStats | None = None
        self._sign_store: TimestampStore | None = None
        self._sign_key = b""
        if cfg.signing.mode != "off":  # a bad key is a configuration error, before any port opens
            if not cfg.signing.key_file:
                raise SigningError(f"signing {cfg.signing.mode!r} needs a key file (--signing-key FILE)")
            self._sign_key = load_key(cfg.signing.key_file)
        """The radio's counters when the mission completed: states still in flight while the
        processes stop depend on the wall clock, and a lockstep run must report the same figures."""
        self._stop_when_done = False
        self._stop_at_s: float | None = None
        self._stop: asyncio.Event | None = None
        self._sp_event: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.busy_wall_s = 0.0
        """Wall time spent inside ticks (physics, autopilots, telemetry building)."""
        self.wall_started: float | None = None
        self.sim_started_s = 0.0
        self._update_fixes()
        for k in range(n):
            self._sync(k)

    # ---- SitlContext ---------------------------------------------------------------
    def send(self, k: int, msg, endpoint: MavEndpoint, addr) -> None:
        endpoint.queue(msg, addr, sysid=k + 1, compid=1)

    def broadcast(self, k: int, msg) -> None:
        """Telemetry of vehicle k to its own endpoint and the shared GCS endpoint."""
        if self.endpoints:
            self.endpoints[k].queue(msg, sysid=k + 1, compid=1)
        if self.gcs is not None:
            self.gcs.queue(msg, sysid=k + 1, compid=1)

    def set_message_interval(self, k: int, msgid: int, interval_s: float | None) -> None:
        if msgid == HEARTBEAT:
            self.heartbeats.set_interval(k, msgid, interval_s, self.wall_clock())
        else:
            self.streams.set_interval(k, msgid, interval_s, self.sim_s)

    def message_interval_s(self, k: int, msgid: int) -> float:
        sched = self.heartbeats if msgid == HEARTBEAT else self.streams
        return sched.interval(k, msgid)

    def on_setpoint(self, k: int) -> None:
        self._sp_fresh[k] = True
        self._wake_lockstep()

    def on_companion_tick(self, k: int, time_usec: int) -> None:
        """A lockstep companion has finished the control tick at time_usec (Unix µs)."""
        self._companion_us[k] = max(self._companion_us[k], int(time_usec))
        self._companion_wall[k] = self.wall_clock()
        self._wake_lockstep()

    def set_origin_geodetic(self, k: int, lat_e7: int, lon_e7: int, alt_mm: int) -> None:
        h = self.cfg.home
        world = geodetic_to_ned(lat_e7 * 1e-7, lon_e7 * 1e-7, alt_mm * 1e-3, h.lat_deg, h.lon_deg, h.alt_amsl_m)
        if self.autopilots[k].set_origin(world, self.sim_s, requested=True):
            self.telemetry.origin_e7[k] = (int(lat_e7), int(lon_e7), int(alt_mm))
            self.broadcast(k, self.telemetry.build(k, GPS_GLOBAL_ORIGIN, self.sim_s))

    def after_change(self, k: int) -> None:
        """Publish whatever vehicle k's autopilot changed: events, heartbeat, setpoint, gains."""
        ap = self.autopilots[k]
        if ap.events:
            for severity, text in ap.events:
                self.broadcast(k, self.telemetry.statustext(severity, text))
            ap.events.clear()
        if ap.changed:
            ap.changed = False
            self.broadcast(k, self.telemetry.heartbeat(k))
        self._sync(k)
        if self.params[k].version != self._param_versions[k]:
            self._update_group(k)

    def _wake_lockstep(self) -> None:
        if self._sp_event is not None:
            self._sp_event.set()

    # ---- simulation ----------------------------------------------------------------
    def _sync(self, k: int) -> None:
        ap = self.autopilots[k]
        if ap.sp_version == self._sp_synced[k]:
            return
        self._sp_synced[k] = ap.sp_version
        self.fleet_sp.assign(slice(k, k + 1), ap.sp)
        self._pos_target[k] = self.fleet_sp.pos_ned_m[k]
        if np.isfinite(self._pos_target[k]).any():
            lim, t = ap.knobs.limits(), self.params[k]
            ratio = t["SD_GEO_KV"] / t["SD_GEO_KX"] if t["SD_GEO_KX"] > 0 else math.inf
            self._carrot_m[k] = (lim.xy_vel_max_mps * ratio, lim.z_vel_max_up_mps * ratio,
                                 lim.z_vel_max_dn_mps * ratio)
        self._rates_only[k] = ap.rates_only
        if ap.rates_only and ap.rate_q_reset:
            ap.rate_q_reset = False
            self._rate_q[k] = ap.sp.att_q_wxyz[0]

    def _update_group(self, k: int) -> None:
        table = self.params[k]
        self._param_versions[k] = table.version
        key = table.gain_key()
        old = self._group_keys[self._group[k]] if k < self._grouped else None
        if key not in self._physics:
            self._physics[key] = Physics(self.cfg.vehicle, table.inner_loop(self.cfg.inner_loop),
                                         dt_s=self.physics_dt_s, ground_z_m=self.cfg.ground_z_m,
                                         wind=self.wind_field, rng=np.random.default_rng(self.rng.integers(2**63)))
            self._group_keys.append(key)
        self._group[k] = self._group_keys.index(key)
        self._grouped = max(self._grouped, k + 1)
        if old is not None and old != key and not (self._group[:self._grouped] == self._group_keys.index(old)).any():
            # Nobody flies these gains any more: free the group, or every distinct value a client
            # ever sets would cost a batch step per tick for the rest of the run.
            gone = self._group_keys.index(old)
            del self._physics[old], self._group_keys[gone]
            self._group[self._group > gone] -= 1

    def _update_fixes(self) -> None:
        """Vehicles whose first fix is due get their EKF origin where they are now."""
        due = self._fix_pending & (self._fix_t <= self.sim_s + 1e-9)
        self._fix_pending &= ~due
        for k in np.flatnonzero(due).tolist():
            ap = self.autopilots[k]
            if ap.origin_ned_m is not None:
                continue
            world, q = quantised_origin(self.cfg.home, self.state.pos_ned_m[k])
            ap.set_origin(world, self.sim_s)
            self.telemetry.origin_e7[k] = q
            if self.endpoints:
                self.broadcast(k, self.telemetry.build(k, GPS_GLOBAL_ORIGIN, self.sim_s))
                self.after_change(k)

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
                self.after_change(k)
            else:
                self.state.pos_ned_m[k] = cpos

    def _fly_carrots(self) -> None:
        """Position targets further than the carrot distance are flown toward, not jumped to."""
        tgt = self._pos_target
        rows = np.flatnonzero(np.isfinite(tgt[:, 0]) | np.isfinite(tgt[:, 2]))
        if not len(rows):
            return
        pos = self.state.pos_ned_m[rows]
        err = tgt[rows] - pos
        d = self._carrot_m[rows]
        h = np.hypot(err[:, 0], err[:, 1])
        scale = np.where(h > d[:, 0], d[:, 0] / np.maximum(h, 1e-12), 1.0)
        err[:, :2] *= scale[:, None]
        err[:, 2] = np.clip(err[:, 2], -d[:, 1], d[:, 2])
        self.fleet_sp.pos_ned_m[rows] = pos + err  # NaN axes stay NaN

    def step_once(self) -> None:
        """Advance simulation time by one tick (physics, carrier, autopilots)."""
        t0 = time.perf_counter()
        if self._rates_only.any():
            m = self._rates_only
            self._rate_q[m] = integrate_quat_body_rates(self._rate_q[m], self.fleet_sp.body_rate_radps[m],
                                                        self.tick_s)
            self.fleet_sp.att_q_wxyz[m] = self._rate_q[m]
        self._fly_carrots()
        for f in self.rotor_faults.update(self.sim_s):  # what a GCS would see of an ESC that quits
            self.autopilots[f.vehicle].events.append((SEV_CRITICAL, f"motor {f.rotor + 1} failed (scenario fault)"))
            self.after_change(f.vehicle)
        active = np.fromiter((ap.needs_physics for ap in self.autopilots), bool, self.n)
        self.vehicle_steps += int(active.sum()) * self.steps_per_tick
        if active.any():
            self.wind_field.advance(self.steps_per_tick)
            sp, est = self.fleet_sp, self.telemetry.estimator
            if est is not None and est.cfg.active:  # each autopilot flies on its own estimate
                sp = dataclasses.replace(sp, pos_ned_m=to_true_frame(sp.pos_ned_m, est.offset_ned_m))
            for g, key in enumerate(self._group_keys):
                mask = active & (self._group == g) if len(self._group_keys) > 1 else active
                if mask.any():
                    self._physics[key].step(self.state, sp, self.steps_per_tick, active=mask,
                                            rotor_scale=self.rotor_faults.scale)
        self.ticks += 1
        self.sim_s = self.ticks * self.tick_s
        if self.carrier:
            self._carrier_update()
        if self._fix_pending.any():
            self._update_fixes()
        armed = np.fromiter((ap.armed for ap in self.autopilots), bool, self.n)
        self.telemetry.flight_time_s[armed] += self.tick_s
        if not self.carrier and np.isnan(self.released_at_s).any():  # a ground launch "releases" at lift-off
            for k in np.flatnonzero(np.isnan(self.released_at_s)).tolist():
                if not self.autopilots[k].landed:
                    self.released_at_s[k], self.released_pos_ned_m[k] = self.sim_s, self.state.pos_ned_m[k]
        if self.ticks % self.ap_every == 0:
            for k, ap in enumerate(self.autopilots):
                ap.tick(self.sim_s)
                if ap.events or ap.changed or ap.sp_version != self._sp_synced[k]:
                    self.after_change(k)
        self._record()
        self.busy_wall_s += time.perf_counter() - t0

    def _record(self) -> None:
        if self.tracker is None:
            return
        released = ~np.fromiter((ap.docked for ap in self.autopilots), bool, self.n)
        md = self.medium
        phase = md.phase if md is not None else np.zeros(self.n, np.int8)
        assembled = (md.flags & FLAG_ASSEMBLED) != 0 if md is not None else np.zeros(self.n, bool)
        t_go = md.t_go_s if md is not None else np.full(self.n, np.nan)
        counted = None
        if md is not None:  # vehicles whose agent fell silent are not waited for (their autopilot holds)
            silent_us = (self._unix_us(self.sim_s) - md.latest_stamp_us) > SILENT_AGENT_S * 1e6
            counted = ~(silent_us & (md.latest_stamp_us >= 0))
        if self.tracker.update(self.sim_s, self.state, self.fleet_sp, released, phase, assembled, t_go, counted,
                               failed_at_s=self.rotor_faults.failed_at_s):
            if not self.mission_done and md is not None:
                self._link_at_done = md.stats(self.sim_s)
            self.mission_done = True

    def run_result(self) -> RunResult | None:
        """What the recorder has (None without a scenario, or when stopped before its first sample)."""
        if self.tracker is None or not self.tracker.rec.t_s:
            return None
        wall = 0.0 if self.wall_started is None else self.wall_clock() - self.wall_started
        link = self._link_at_done or (self.medium.stats(self.sim_s) if self.medium is not None else LinkStats())
        rel_s = np.where(np.isnan(self.released_at_s), np.inf, self.released_at_s)
        return self.tracker.result(rel_s, self.released_pos_ned_m, wall, self.sim_s, self.vehicle_steps, link)

    def emit_streams(self) -> None:
        t0 = time.perf_counter()
        ks, js = self.streams.due(self.sim_s)
        if len(ks):
            self.telemetry.snapshot(self.sim_s)
            msgids = self.streams.msgids
            t_us = int(round(self.sim_s * 1e6))
            geo = [k for k, j in zip(ks.tolist(), js.tolist()) if msgids[j] in (GLOBAL_POSITION_INT, GPS_RAW_INT)]
            self.telemetry.prepare_geodetic(geo)
            for k, j in zip(ks.tolist(), js.tolist()):
                msg = self.telemetry.build(k, msgids[j], self.sim_s)
                if msg is not None:
                    self.broadcast(k, msg)
                    if msgids[j] == LOCAL_POSITION_NED:
                        self._control_us[k] = t_us
        self.busy_wall_s += time.perf_counter() - t0

    def _unix_us(self, sim_s: float) -> int:
        return int(round((self.telemetry.epoch_unix_s + sim_s) * 1e6))

    # ---- asyncio process -------------------------------------------------------------
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._sp_event = asyncio.Event()
        for physics in self._physics.values():
            physics.warm_up()  # a first compile in flight would stall heartbeats for seconds
        if self.tracker is not None:
            warm_up_tracker()
        ec = self.cfg.endpoints
        if self.cfg.tlog_path:
            self.tlog = Tlog(self.cfg.tlog_path, clock=lambda: self.telemetry.epoch_unix_s + self.sim_s)
        for k in range(self.n):
            local = ec.local_base_port + k if ec.local_base_port else 0
            link = UdpLink(bind=(ec.bind_host, local), remote=(ec.remote_host, ec.vehicle_remote_port(k)))
            ep = MavEndpoint(link, self.codec, k + 1, 1, self.tlog, signing=self._signing(k))
            self.endpoints.append(ep)
            self._loop.add_reader(link.fileno(), self._on_readable, ep, k)
        if ec.gcs_enabled:
            link = UdpLink(bind=(ec.bind_host, ec.gcs_local_port), remote=(ec.remote_host, ec.gcs_remote_port))
            self.gcs = MavEndpoint(link, self.codec, 1, 1, self.tlog, signing=self._signing(self.n))
            self._loop.add_reader(link.fileno(), self._on_readable, self.gcs, None)
        mc = self.cfg.medium
        if mc.enabled:
            ports = [mc.agent_base_port + k for k in range(self.n)] if mc.agent_base_port else None
            self.medium = Medium(self.n, mc.link, self.cfg.seed, self.telemetry.epoch_unix_s,
                                 (ec.bind_host, mc.port), ports, ec.remote_host, signing=self._signing(200))
            self._loop.add_reader(self.medium.fileno(), self._on_medium)

    def _signing(self, link_id: int) -> Signing | None:
        """The signing layer of one endpoint (its own replay table; link id = vehicle index,
        n for the GCS endpoint); one timestamp file for the process."""
        sc = self.cfg.signing
        if sc.mode == "off":
            return None
        if self._sign_store is None:
            self._sign_store = TimestampStore(sc.timestamp_file or f"{sc.key_file}.timestamp")
        return Signing(sc.mode, self._sign_key, link_id=link_id & 0xFF, store=self._sign_store,
                       crc_extra=self.codec.crc_extra)

    def signing_stats(self) -> dict[str, SigningCounters]:
        """Per endpoint (vehicle index, or "gcs"): what signing dropped (a copy)."""
        out = {}
        for name, ep in [(str(k), e) for k, e in enumerate(self.endpoints)] + ([("gcs", self.gcs)] if self.gcs else []):
            if ep.signing is not None:
                out[name] = dataclasses.replace(ep.signing.counters)
        return out

    def _on_readable(self, ep: MavEndpoint, k: int | None) -> None:
        for msg, addr in ep.poll():
            if k is not None:
                self.attached[k] = True
            try:
                self.router.handle(ep, msg, addr, k)
            except Exception:  # bad content must never take the SITL down
                ep.bad_frames += 1
        ep.flush()

    def _on_medium(self) -> None:
        self.medium.receive()
        self._wake_lockstep()

    def _publish_ticks(self) -> np.ndarray:
        """(N,) bool: vehicles at a control tick now that is also one of their swarm ticks
        (`companion.swarm.swarm_due`, with each vehicle's own control period): when their
        agent publishes, plans and reads the radio. Worked out once per tick (the radio
        and the lockstep gate both ask)."""
        if self._pub_tick == self.ticks:
            return self._pub
        t_us = int(round(self.sim_s * 1e6))
        at = self._control_us == t_us
        if not at.any():
            self._pub_tick, self._pub = self.ticks, at
            return at
        unix_us = self._unix_us(self.sim_s)
        period_s = self.streams.interval_s[:, self.streams.col[LOCAL_POSITION_NED]]
        for k in np.flatnonzero(at).tolist():
            p = period_s[k]
            at[k] = bool(np.isfinite(p)) and bool(swarm_due(unix_us, self.cfg.medium.swarm_rate_hz, k,
                                                            int(round(p * 1e6))))
        self._pub_tick, self._pub = self.ticks, at
        return at

    def _radio_tick(self, lockstep: bool) -> None:
        """Schedule what agents sent; deliver to each agent at its swarm ticks (one datagram,
        ending with the lockstep marker): an agent reads the radio when it plans, at the
        swarm rate, so copies in between would only cost wake-ups. Agents without a
        control stream get theirs every RADIO_FLUSH_TICKS ticks."""
        md = self.medium
        md.schedule(self.sim_s, self.state.pos_ned_m)
        at_tick = self._publish_ticks()
        if self.ticks % RADIO_FLUSH_TICKS == 0:
            at_tick = at_tick | (self._control_us < 0)
        md.deliver(self.sim_s, at_tick, tick_marker=lockstep)

    def describe_endpoints(self) -> list[str]:
        ec = self.cfg.endpoints
        lines = [f"vehicle {k} sysid {k + 1} compid 1: udp {ec.bind_host}:{ep.link.local_port} -> "
                 f"{ep.link.remote[0]}:{ep.link.remote[1]}" for k, ep in enumerate(self.endpoints)]
        if self.gcs is not None:
            lines.append(f"gcs (all vehicles): udp {ec.bind_host}:{self.gcs.link.local_port} -> "
                         f"{self.gcs.link.remote[0]}:{self.gcs.link.remote[1]}")
        if self.medium is not None:
            lines.append(f"swarm radio: udp {ec.bind_host}:{self.medium.port}")
        return lines

    def request_stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    def _flush_all(self) -> None:
        for ep in self.endpoints:
            if ep.pending:
                ep.flush()
        if self.gcs is not None and self.gcs.pending:
            self.gcs.flush()

    async def run(self, on_ready: Callable[["SitlServer"], None] | None = None,
                  handle_signals: bool = False, status_out=None, stop_when_done: bool = False,
                  stop_at_s: float | None = None) -> None:
        await self.start()
        if handle_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(sig, self._stop.set)
        if on_ready is not None:
            on_ready(self)
        tasks = [self._sim_task(), self._heartbeat_task()]
        if status_out is not None:
            tasks.append(self._status_task(status_out))
        self._stop_when_done, self._stop_at_s = stop_when_done, stop_at_s
        try:
            await asyncio.gather(*tasks)
        finally:
            for ep in self.endpoints + ([self.gcs] if self.gcs else []):
                self._loop.remove_reader(ep.link.fileno())
                ep.close()
            if self.medium is not None:
                self._loop.remove_reader(self.medium.fileno())
                self.medium.close()
            if self.tlog is not None:
                self.tlog.close()


from sim_bridge.sitl.background import BackgroundSitl  # noqa: E402,F401  (its home before the split)
