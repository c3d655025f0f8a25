"""The SITL process: N vehicles, one physics loop, clocks, lockstep, endpoints, tlog.

Time: simulation time advances in ticks of `time.tick_s`. Free-running, a tick is
taken every tick_s / speed wall seconds. In lockstep, while any vehicle is in
Offboard, a tick is only taken once every Offboard vehicle has received a setpoint
since the previous tick (no pacing then: the clients drive the clock); with no
Offboard vehicle the clock free-runs at `speed`. HEARTBEATs run on a wall-clock
schedule and commands are answered as they arrive, so client timeouts hold.
"""
from __future__ import annotations

import asyncio
import math
import signal
import threading
import time
from typing import Callable

import numpy as np

from companion.state import FleetSetpoint, FleetState
from sim_bridge.carrier import carrier_position_ned_m, release_times_s, sample_release_attitudes
from sim_bridge.physics import Physics
from companion.frames import integrate_quat_body_rates
from sim_bridge.sitl.autopilot import Autopilot, Mode
from sim_bridge.sitl.config import SitlConfig
from sim_bridge.sitl.endpoints import Tlog, UdpEndpoint
from sim_bridge.sitl.handler import MessageRouter
from sim_bridge.sitl.params_table import ParamTable, default_specs
from sim_bridge.sitl.telemetry import HEARTBEAT, STREAMS, IntervalScheduler, TelemetryBuilder, default_interval_s

HEARTBEAT_POLL_S = 0.02


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


class SitlServer:
    """All vehicles of one SITL. Implements the handler's SitlContext."""

    def __init__(self, cfg: SitlConfig, wall_clock: Callable[[], float] = time.monotonic,
                 rng: np.random.Generator | None = None):
        self.cfg = cfg
        self.n = n = cfg.vehicles
        self.wall_clock = wall_clock
        self.rng = rng if rng is not None else np.random.default_rng(cfg.seed)
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
        self.home_alt_amsl_m = cfg.home.alt_amsl_m - cfg.ground_z_m
        self.params = [ParamTable(default_specs(cfg.inner_loop, k + 1)) for k in range(n)]
        for name, value in cfg.params.items():
            for table in self.params:
                if table.index_of(name) is None:
                    raise ValueError(f"params: unknown parameter {name!r}")
                if not table.set(name, value):
                    raise ValueError(f"params: {name}={value} refused (range or read-only)")
        self.sim_s = 0.0
        self.ticks = 0
        self.autopilots = [Autopilot(k, k + 1, self.params[k], self.state, cfg.ground_z_m, self.home_ned_m[k],
                                     docked=self.carrier, now_s=0.0) for k in range(n)]
        self.fleet_sp = FleetSetpoint.empty(n)
        self._sp_synced = np.full(n, -1)
        self._rate_q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        self._rates_only = np.zeros(n, bool)
        self.telemetry = TelemetryBuilder(self.state, self.autopilots, cfg.home, self.home_ned_m)
        tc = cfg.time
        self.tick_s = tc.tick_s
        self.steps_per_tick = max(1, int(round(tc.tick_s * tc.physics_rate_hz)))
        self.physics_dt_s = tc.tick_s / self.steps_per_tick
        self.ap_every = max(1, int(round(1.0 / (tc.autopilot_rate_hz * tc.tick_s))))
        self._physics: dict[tuple, Physics] = {}
        self._group = np.zeros(n, int)
        self._group_keys: list[tuple] = []
        self._param_versions = np.full(n, -1)
        for k in range(n):
            self._update_group(k)
        self.streams = IntervalScheduler(n, STREAMS, [default_interval_s(cfg.streams, m) for m in STREAMS], 0.0)
        self.heartbeats = IntervalScheduler(n, (HEARTBEAT,), [default_interval_s(cfg.streams, HEARTBEAT)],
                                            wall_clock())
        self._sp_fresh = np.zeros(n, bool)
        self.router = MessageRouter(self)
        self.endpoints: list[UdpEndpoint] = []
        self.gcs: UdpEndpoint | None = None
        self.tlog: Tlog | None = None
        self._stop: asyncio.Event | None = None
        self._sp_event: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.busy_wall_s = 0.0
        """Wall time spent inside ticks (physics, autopilots, telemetry building)."""
        for k in range(n):
            self._sync(k)

    # ---- SitlContext ---------------------------------------------------------------
    def send(self, k: int, msg, endpoint, addr) -> None:
        endpoint.send(k + 1, msg, addr)

    def broadcast(self, k: int, msg) -> None:
        """Telemetry of vehicle k to its own endpoint and the shared GCS endpoint."""
        if self.endpoints:
            self.endpoints[k].send(k + 1, msg)
        if self.gcs is not None:
            self.gcs.send(k + 1, msg)

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
        if self._sp_event is not None:
            self._sp_event.set()

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

    # ---- simulation ----------------------------------------------------------------
    def _sync(self, k: int) -> None:
        ap = self.autopilots[k]
        if ap.sp_version == self._sp_synced[k]:
            return
        self._sp_synced[k] = ap.sp_version
        self.fleet_sp.assign(slice(k, k + 1), ap.sp)
        self._rates_only[k] = ap.rates_only
        if ap.rates_only and ap.rate_q_reset:
            ap.rate_q_reset = False
            self._rate_q[k] = ap.sp.att_q_wxyz[0]

    def _update_group(self, k: int) -> None:
        table = self.params[k]
        self._param_versions[k] = table.version
        key = tuple(table[name] for name in ("SD_GEO_KX", "SD_GEO_KV", "SD_GEO_KR", "SD_GEO_KOM",
                                             "MPC_TILTMAX_AIR", "SD_ACC_MAX"))
        if key not in self._physics:
            self._physics[key] = Physics(self.cfg.vehicle, table.inner_loop(self.cfg.inner_loop),
                                         dt_s=self.physics_dt_s, ground_z_m=self.cfg.ground_z_m,
                                         rng=np.random.default_rng(self.rng.integers(2**63)))
            self._group_keys.append(key)
        self._group[k] = self._group_keys.index(key)

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
                ap.on_released(t)
                self.after_change(k)
            else:
                self.state.pos_ned_m[k] = cpos

    def step_once(self) -> None:
        """Advance simulation time by one tick (physics, carrier, autopilots)."""
        t0 = time.perf_counter()
        if self._rates_only.any():
            m = self._rates_only
            self._rate_q[m] = integrate_quat_body_rates(self._rate_q[m], self.fleet_sp.body_rate_radps[m],
                                                        self.tick_s)
            self.fleet_sp.att_q_wxyz[m] = self._rate_q[m]
        active = np.fromiter((ap.needs_physics for ap in self.autopilots), bool, self.n)
        if active.any():
            for g, key in enumerate(self._group_keys):
                mask = active & (self._group == g) if len(self._group_keys) > 1 else active
                if mask.any():
                    self._physics[key].step(self.state, self.fleet_sp, self.steps_per_tick, active=mask)
        self.ticks += 1
        self.sim_s = self.ticks * self.tick_s
        if self.carrier:
            self._carrier_update()
        armed = np.fromiter((ap.armed for ap in self.autopilots), bool, self.n)
        self.telemetry.flight_time_s[armed] += self.tick_s
        if self.ticks % self.ap_every == 0:
            for k, ap in enumerate(self.autopilots):
                ap.tick(self.sim_s)
                if ap.events or ap.changed or ap.sp_version != self._sp_synced[k]:
                    self.after_change(k)
        self.busy_wall_s += time.perf_counter() - t0

    def emit_streams(self) -> None:
        t0 = time.perf_counter()
        ks, js = self.streams.due(self.sim_s)
        if len(ks):
            self.telemetry.snapshot(self.sim_s)
            msgids = self.streams.msgids
            for k, j in zip(ks.tolist(), js.tolist()):
                msg = self.telemetry.build(k, msgids[j], self.sim_s)
                if msg is not None:
                    self.broadcast(k, msg)
        self.busy_wall_s += time.perf_counter() - t0

    def lockstep_waiting(self) -> bool:
        """True while some Offboard vehicle has no setpoint for the next tick."""
        for k, ap in enumerate(self.autopilots):
            if ap.mode == Mode.OFFBOARD and not self._sp_fresh[k]:
                return True
        return False

    def any_offboard(self) -> bool:
        return any(ap.mode == Mode.OFFBOARD for ap in self.autopilots)

    # ---- asyncio process -------------------------------------------------------------
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._sp_event = asyncio.Event()
        ec = self.cfg.endpoints
        if self.cfg.tlog_path:
            self.tlog = Tlog(self.cfg.tlog_path)
        for k in range(self.n):
            local = ec.local_base_port + k if ec.local_base_port else 0
            ep = UdpEndpoint(f"vehicle{k + 1}", (ec.bind_host, local), (ec.remote_host, ec.vehicle_remote_port(k)),
                             self._vehicle_handler(k), self.tlog)
            await ep.start()
            self.endpoints.append(ep)
        if ec.gcs_enabled:
            self.gcs = UdpEndpoint("gcs", (ec.bind_host, ec.gcs_local_port), (ec.remote_host, ec.gcs_remote_port),
                                   lambda ep, msg, addr: self.router.handle(ep, msg, addr, None), self.tlog)
            await self.gcs.start()

    def _vehicle_handler(self, k: int):
        return lambda ep, msg, addr: self.router.handle(ep, msg, addr, k)

    def describe_endpoints(self) -> list[str]:
        ec = self.cfg.endpoints
        lines = [f"vehicle {k} sysid {k + 1} compid 1: udp {ec.bind_host}:{ep.local_port} -> "
                 f"{ep.remote[0]}:{ep.remote[1]}" for k, ep in enumerate(self.endpoints)]
        if self.gcs is not None:
            lines.append(f"gcs (all vehicles): udp {ec.bind_host}:{self.gcs.local_port} -> "
                         f"{self.gcs.remote[0]}:{self.gcs.remote[1]}")
        return lines

    def request_stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    async def _heartbeat_task(self) -> None:
        while not self._stop.is_set():
            ks, _ = self.heartbeats.due(self.wall_clock())
            for k in ks.tolist():
                self.broadcast(k, self.telemetry.heartbeat(k))
            try:
                await asyncio.wait_for(self._stop.wait(), HEARTBEAT_POLL_S)
            except asyncio.TimeoutError:
                pass

    async def _sim_task(self) -> None:
        """Take ticks; the decision to step and the step itself have no await between them."""
        tc = self.cfg.time
        wall0, sim0 = self.wall_clock(), self.sim_s
        while not self._stop.is_set():
            if tc.lockstep and self.any_offboard():
                if self.lockstep_waiting():
                    self._sp_event.clear()
                    try:
                        await asyncio.wait_for(self._sp_event.wait(), 0.05)
                    except asyncio.TimeoutError:
                        pass
                    continue
                wall0, sim0 = self.wall_clock(), self.sim_s + self.tick_s
            else:
                delay = wall0 + (self.sim_s + self.tick_s - sim0) / tc.speed - self.wall_clock()
                if delay > 0:
                    await asyncio.sleep(delay)
                    continue  # re-evaluate: commands may have arrived meanwhile
                if delay < -0.5:  # overloaded: drop the debt instead of bursting
                    wall0, sim0 = self.wall_clock(), self.sim_s
            self.step_once()
            self.emit_streams()
            self._sp_fresh[:] = False
            await asyncio.sleep(0)  # let the endpoints send and receive

    async def run(self, on_ready: Callable[["SitlServer"], None] | None = None,
                  handle_signals: bool = False) -> None:
        await self.start()
        if handle_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(sig, self._stop.set)
        if on_ready is not None:
            on_ready(self)
        try:
            await asyncio.gather(self._sim_task(), self._heartbeat_task())
        finally:
            for ep in self.endpoints + ([self.gcs] if self.gcs else []):
                await ep.close()
            if self.tlog is not None:
                self.tlog.close()


class BackgroundSitl:
    """Run a SitlServer on its own thread and event loop (tests, embedding)."""

    def __init__(self, cfg: SitlConfig, **kwargs):
        self.server = SitlServer(cfg, **kwargs)
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="sitl", daemon=True)

    def _main(self) -> None:
        try:
            asyncio.run(self.server.run(on_ready=lambda s: self._ready.set()))
        except BaseException as exc:  # surfaced by start()/stop()
            self._error = exc
            self._ready.set()

    def start(self, timeout_s: float = 30.0) -> SitlServer:
        self._thread.start()
        if not self._ready.wait(timeout_s) or self._error is not None:
            raise RuntimeError(f"SITL did not start: {self._error!r}")
        return self.server

    def stop(self, timeout_s: float = 10.0) -> None:
        self.server.request_stop()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise RuntimeError("SITL thread did not stop")

    def __enter__(self) -> SitlServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
