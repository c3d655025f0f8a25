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
import signal
import time
from typing import Callable, TextIO

import numpy as np

from companion.agent import Phase
from companion.frames import geodetic_to_ned
from companion.link.endpoints import MavEndpoint
from companion.link.framing import signature_of
from companion.link.signing import SigningCounters
from companion.mission import Mission
from companion.swarm import FLAG_ASSEMBLED, PHASE_COUNT, swarm_due
from sim_bridge.reports.record import MissionTracker, RunResult
from sim_bridge.reports.record import warm_up as warm_up_tracker
from sim_bridge.sitl.clock import LockstepGate
from sim_bridge.sitl.commands import SOURCE_LINK_ID, SitlCommands
from sim_bridge.sitl.config import SitlConfig
from sim_bridge.sitl.handler import MessageRouter
from sim_bridge.sitl.links import SitlLinks
from sim_bridge.sitl.medium import Medium, relay_frames_per_s
from sim_bridge.sitl.status import SitlStatus
from sim_bridge.sitl.telemetry import (
    GLOBAL_POSITION_INT,
    GPS_GLOBAL_ORIGIN,
    GPS_RAW_INT,
    HEARTBEAT,
    LOCAL_POSITION_NED,
    STREAMS,
    IntervalScheduler,
    Outgoing,
    TelemetryBuilder,
    default_interval_s,
)
from sim_bridge.sitl.vehicles import SimulatedFleet, hover_thrust_fraction, spawn_positions_ned_m  # noqa: F401
from sim_bridge.world.transport import LinkStats

RADIO_FLUSH_TICKS = 5
"""Vehicles without a control stream still get their radio copies this often (ticks)."""
SILENT_AGENT_S = 3.0
"""A vehicle whose agent has published nothing for this long (simulated) no longer counts
for the recorder's assembly and completion (a crashed companion must not stall the run)."""
HEARTBEAT_POLL_S = 0.02
STATUS_PERIOD_S = 0.25
"""A fleet harness acts on these (progress, fault injection at a simulated time)."""


class SitlServer:
    """One SITL process: the simulated vehicles (SimulatedFleet), their MAVLink endpoints
    (SitlLinks), telemetry streams, the swarm radio (Medium), the lockstep gate
    (LockstepGate) and the mission recorder, run by three asyncio tasks (simulation,
    wall-clock heartbeats, status). Implements the router's SitlContext and the
    fleet's FleetListener.

    Args:
        cfg: the SITL configuration.
        wall_clock: monotonic seconds (injected).
        rng: physics and launch randomness (default: seeded from cfg.seed).
        record: record the scenario's mission (MissionTracker) for metrics and figures.
    Raises:
        ValueError: a parameter override that is unknown or refused.
        SigningError: a signing mode without a usable key file.
    """

    def __init__(self, cfg: SitlConfig, wall_clock: Callable[[], float] = time.monotonic,
                 rng: np.random.Generator | None = None, record: bool = False):
        self.cfg = cfg
        self.n = n = cfg.vehicles
        self.wall_clock = wall_clock
        self.fleet = SimulatedFleet(cfg, self, rng)
        """The vehicles, their autopilots and physics."""
        fl = self.fleet
        # (aliases of the fleet's own objects: the router, tests and benches read them here)
        self.state, self.autopilots, self.params = fl.state, fl.autopilots, fl.params
        self.behaviour, self.dialect = fl.behaviour, fl.dialect
        self.home_ned_m, self.home_alt_amsl_m = fl.home_ned_m, fl.home_alt_amsl_m
        self.rotor_faults, self.tick_s = fl.rotor_faults, fl.tick_s
        self.links = SitlLinks(cfg, self._setup_signing_refused)
        """Endpoints, tlog and signing (bound by start())."""
        self.telemetry = TelemetryBuilder(fl.state, fl.autopilots, cfg.home, fl.home_ned_m, self.links.codec,
                                          cfg.time.epoch_unix_s, estimator=fl.estimator, origin_e7=fl.origin_e7,
                                          flight_time_s=fl.flight_time_s)
        # Stream intervals are per link, as PX4 (per MAVLink instance) and ArduPilot (per
        # channel) keep them: a companion's 50 Hz request on its vehicle's endpoint does not
        # flood the shared GCS endpoint, and a GCS's request does not change the companion's.
        stream_s = [default_interval_s(cfg.streams, m) for m in STREAMS]
        hb_s = [default_interval_s(cfg.streams, HEARTBEAT)]
        self.streams = IntervalScheduler(n, STREAMS, stream_s, 0.0)
        """The vehicles' own endpoints' streams (simulation time)."""
        self.heartbeats = IntervalScheduler(n, (HEARTBEAT,), hb_s, wall_clock())
        self.gcs_streams = IntervalScheduler(n, STREAMS, stream_s, 0.0)
        """The shared GCS endpoint's streams of each vehicle."""
        self.gcs_heartbeats = IntervalScheduler(n, (HEARTBEAT,), hb_s, wall_clock())
        self.gate = LockstepGate(n, cfg.time, wall_clock)
        """Who holds the lockstep clock."""
        self.attached = self.gate.attached
        self._pub_tick, self._pub = -1, np.zeros(n, bool)
        """_publish_ticks() of tick _pub_tick."""
        self.router = MessageRouter(self)
        self.medium: Medium | None = None
        self.commands: SitlCommands | None = None
        """The scenario's `commands:` schedule, issued into the radio (with a radio and a schedule)."""
        self.tracker: MissionTracker | None = None
        if record:
            scenario = cfg.scenario
            log_every = max(1, int(round(1.0 / (scenario.output.log_rate_hz * cfg.time.tick_s))))
            self.tracker = MissionTracker(scenario, Mission(scenario.mission), log_every)
        self.mission_done = False
        self._link_at_done: LinkStats | None = None
        """The radio's counters when the mission completed: states still in flight while the
        processes stop depend on the wall clock, and a lockstep run must report the same figures."""
        self._stop_when_done = False
        self._stop_at_s: float | None = None
        self._stop: asyncio.Event | None = None
        self._sp_event: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.wall_started: float | None = None
        self.sim_started_s = 0.0
        fl.start()

    # ---- the fleet's clock, read through ----------------------------------------------
    @property
    def sim_s(self) -> float:
        """Simulated time, s."""
        return self.fleet.sim_s

    @property
    def ticks(self) -> int:
        """Ticks taken."""
        return self.fleet.ticks

    @property
    def busy_wall_s(self) -> float:
        """Wall time spent inside ticks (physics, autopilots, telemetry building)."""
        return self.fleet.busy_wall_s

    @property
    def endpoints(self) -> list[MavEndpoint]:
        """Vehicle k's endpoint is endpoints[k] (empty until start())."""
        return self.links.endpoints

    @property
    def gcs(self) -> MavEndpoint | None:
        """The shared GCS endpoint (None if not enabled or not started)."""
        return self.links.gcs

    # ---- FleetListener ----------------------------------------------------------------
    def vehicle_changed(self, k: int) -> None:
        """Publish whatever vehicle k's autopilot changed: events, heartbeat; then its setpoint and gains."""
        self.after_change(k)

    def origin_set(self, k: int) -> None:
        """Vehicle k's first GNSS fix: GPS_GLOBAL_ORIGIN to its stations (once they are connected)."""
        if self.links.open:
            self._broadcast_origin(k)
            self.after_change(k)

    def _broadcast_origin(self, k: int) -> None:
        msg = self.telemetry.build(k, GPS_GLOBAL_ORIGIN, self.sim_s)
        if msg is not None:  # (None only before the vehicle has an origin)
            self.links.broadcast(k, msg)

    # ---- SitlContext -------------------------------------------------------------------
    def send(self, k: int, msg: Outgoing, endpoint: MavEndpoint, addr) -> None:
        """A reply of vehicle k to addr on one endpoint."""
        self.links.send(k, msg, endpoint, addr)

    def broadcast(self, k: int, msg: Outgoing) -> None:
        """Telemetry of vehicle k to its own endpoint and the shared GCS endpoint."""
        self.links.broadcast(k, msg)

    def _scheduler(self, msgid: int, endpoint: MavEndpoint | None) -> IntervalScheduler:
        """Whose interval of msgid a command on endpoint sets: the shared GCS endpoint's own,
        or the vehicle endpoint's."""
        on_gcs = endpoint is not None and endpoint is self.links.gcs
        if msgid == HEARTBEAT:
            return self.gcs_heartbeats if on_gcs else self.heartbeats
        return self.gcs_streams if on_gcs else self.streams

    def set_message_interval(self, k: int, msgid: int, interval_s: float | None,
                             endpoint: MavEndpoint | None = None) -> None:
        now = self.wall_clock() if msgid == HEARTBEAT else self.sim_s
        self._scheduler(msgid, endpoint).set_interval(k, msgid, interval_s, now)

    def message_interval_s(self, k: int, msgid: int, endpoint: MavEndpoint | None = None) -> float:
        return self._scheduler(msgid, endpoint).interval(k, msgid)

    def on_setpoint(self, k: int) -> None:
        self.gate.sp_fresh[k] = True
        self._wake_lockstep()

    def on_companion_tick(self, k: int, time_usec: int) -> None:
        """A lockstep companion has finished the control tick at time_usec (Unix µs)."""
        self.gate.note_companion_tick(k, time_usec)
        self._wake_lockstep()

    def set_origin_geodetic(self, k: int, lat_e7: int, lon_e7: int, alt_mm: int) -> None:
        h = self.cfg.home
        world = geodetic_to_ned(lat_e7 * 1e-7, lon_e7 * 1e-7, alt_mm * 1e-3, h.lat_deg, h.lon_deg, h.alt_amsl_m)
        if self.fleet.set_origin(k, world, (int(lat_e7), int(lon_e7), int(alt_mm))):
            self._broadcast_origin(k)

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
        self.fleet.sync(k)

    def _wake_lockstep(self) -> None:
        if self._sp_event is not None:
            self._sp_event.set()

    # ---- one tick ------------------------------------------------------------------
    def step_once(self) -> None:
        """Advance simulation time by one tick (physics, carrier, autopilots) and record it."""
        self.fleet.step()
        self._record()

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
        # (for a mission that lands; for one that holds station once every vehicle is landing, so
        # that a swarm LAND it was not written with ends the run: MissionTracker.update)
        down = np.fromiter((ap.landed and not ap.armed for ap in self.autopilots), bool, self.n) \
            if self.tracker.landing or (phase[slice(None) if counted is None else counted] == Phase.LAND).all() else None
        cmd = self.commands  # (with a schedule: judged against the plan's reference, and not done before it is)
        if self.tracker.update(self.sim_s, self.state, self.fleet.fleet_sp, released, phase, assembled, t_go,
                               counted, failed_at_s=self.rotor_faults.failed_at_s, down=down,
                               slot_ned_m=None if cmd is None else cmd.reference_ned_m(self.sim_s)) \
                and (cmd is None or cmd.settled(counted)):
            if not self.mission_done and md is not None:
                self._link_at_done = md.stats(self.sim_s)
            self.mission_done = True

    def run_result(self) -> RunResult | None:
        """What the recorder has (None without a scenario, or when stopped before its first sample)."""
        if self.tracker is None or not self.tracker.rec.t_s:
            return None
        wall = 0.0 if self.wall_started is None else self.wall_clock() - self.wall_started
        link = self._link_at_done or (self.medium.stats(self.sim_s) if self.medium is not None else LinkStats())
        fl = self.fleet
        rel_s = np.where(np.isnan(fl.released_at_s), np.inf, fl.released_at_s)
        return self.tracker.result(rel_s, fl.released_pos_ned_m, wall, self.sim_s, fl.vehicle_steps, link,
                                   None if self.commands is None else self.commands.records)

    def emit_streams(self) -> None:
        """Telemetry due now, each link's own (a LOCAL_POSITION_NED to a vehicle's endpoint is
        a control tick). A message due on both links is built once and sent on both."""
        t0 = time.perf_counter()
        due = [list(zip(*(a.tolist() for a in self.streams.due(self.sim_s))))]
        if self.links.gcs is not None:
            due.append(list(zip(*(a.tolist() for a in self.gcs_streams.due(self.sim_s)))))
        if any(due):
            self.telemetry.snapshot(self.sim_s)
            msgids = self.streams.msgids
            t_us = int(round(self.sim_s * 1e6))
            self.telemetry.prepare_geodetic(sorted({k for pairs in due for k, j in pairs
                                                    if msgids[j] in (GLOBAL_POSITION_INT, GPS_RAW_INT)}))
            built: dict[tuple[int, int], Outgoing | None] = {}
            for link, pairs in enumerate(due):
                for k, j in pairs:
                    if (k, j) not in built:
                        built[k, j] = self.telemetry.build(k, msgids[j], self.sim_s)
                    msg = built[k, j]
                    if msg is None:
                        continue
                    self.links.broadcast(k, msg, vehicle=link == 0, gcs=link == 1)
                    if link == 0 and msgids[j] == LOCAL_POSITION_NED:
                        self.gate.control_us[k] = t_us
        self.fleet.busy_wall_s += time.perf_counter() - t0

    def _unix_us(self, sim_s: float) -> int:
        return int(round((self.telemetry.epoch_unix_s + sim_s) * 1e6))

    def _publish_ticks(self) -> np.ndarray:
        """(N,) bool: vehicles at a control tick now that is also one of their swarm ticks
        (`companion.swarm.swarm_due`, with each vehicle's own control period): when their
        agent publishes, plans and reads the radio. Worked out once per tick (the radio
        and the lockstep gate both ask)."""
        if self._pub_tick == self.ticks:
            return self._pub
        t_us = int(round(self.sim_s * 1e6))
        at = self.gate.control_us == t_us
        if not at.any():
            self._pub_tick, self._pub = self.ticks, at
            return at
        unix_us = self._unix_us(self.sim_s)
        period_s = self.streams.interval_s[:, self.streams.col[LOCAL_POSITION_NED]]
        for k in np.flatnonzero(at).tolist():
            p = period_s[k]
            at[k] = bool(np.isfinite(p)) and bool(swarm_due(unix_us, self.cfg.swarm_rate_hz, k,
                                                            int(round(p * 1e6))))
        self._pub_tick, self._pub = self.ticks, at
        return at

    def _radio_tick(self, lockstep: bool) -> None:
        """Schedule what agents sent; deliver to each agent at its swarm ticks (one datagram,
        ending with the lockstep marker): an agent reads the radio when it plans, at the
        swarm rate, so copies in between would only cost wake-ups. Agents without a
        control stream get theirs every RADIO_FLUSH_TICKS ticks."""
        md = self.medium
        assert md is not None
        if self.commands is not None:
            self.commands.step(self.sim_s)
        md.schedule(self.sim_s, self.state.pos_ned_m)
        at_tick = self._publish_ticks()
        if self.ticks % RADIO_FLUSH_TICKS == 0:
            at_tick = at_tick | (self.gate.control_us < 0)
        md.deliver(self.sim_s, at_tick, tick_marker=lockstep)

    def lockstep_waiting(self) -> bool:
        """True while a companion that drives the clock has not answered the current tick."""
        return self.gate.waiting(int(round(self.sim_s * 1e6)), self._unix_us(self.sim_s), self.autopilots,
                                 self.medium, self._publish_ticks)

    def any_clock_driver(self) -> bool:
        """Someone drives a lockstep clock now."""
        return self.gate.any_driver(self.autopilots)

    # ---- status --------------------------------------------------------------------------
    def status(self) -> SitlStatus:
        """One line of progress for a fleet harness."""
        md = self.medium
        wall = 0.0 if self.wall_started is None else self.wall_clock() - self.wall_started
        return SitlStatus(
            sim_s=round(self.sim_s, 3), wall_s=round(wall, 3),
            rtf=round((self.sim_s - self.sim_started_s) / wall, 3) if wall > 0 else None,
            attached=int(self.attached.sum()), armed=int(sum(ap.armed for ap in self.autopilots)),
            complete=self.mission_done,
            phases=tuple(np.bincount(md.phase, minlength=PHASE_COUNT).tolist()) if md is not None else (),
            link_bytes_per_s_per_vehicle=round(float(md.bytes_in.sum()) / max(self.sim_s, 1e-9) / self.n, 1)
            if md is not None else None,
            t_go_s=_first_go(md.t_go_s) if md is not None else None,
            id_conflicts=md.id_conflicts if md is not None else 0)

    def signing_stats(self) -> dict[str, SigningCounters]:
        """Per endpoint (vehicle index, or "gcs"): what signing dropped (a copy)."""
        return self.links.signing_stats()

    def describe_endpoints(self) -> list[str]:
        """One line per endpoint and for the radio."""
        lines = self.links.describe()
        if self.medium is not None:
            lines.append(f"swarm radio: udp {self.cfg.endpoints.bind_host}:{self.medium.port}")
        return lines

    # ---- asyncio process -------------------------------------------------------------
    async def start(self) -> None:
        """Bind every socket and compile what a first tick would (before the clock runs).

        Raises:
            OSError: a port cannot be bound.
        """
        loop = self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._sp_event = asyncio.Event()
        self.fleet.warm_up()
        if self.tracker is not None:
            warm_up_tracker()
        self.links.start(loop, self._on_readable, lambda: self.telemetry.epoch_unix_s + self.sim_s)
        mc, ec = self.cfg.medium, self.cfg.endpoints
        if mc.enabled:
            ports = [mc.agent_base_port + k for k in range(self.n)] if mc.agent_base_port else None
            self.medium = Medium(self.n, self.cfg.link, self.cfg.seed, self.telemetry.epoch_unix_s,
                                 (ec.bind_host, mc.port), ports, ec.remote_host, signing=self.links.signing.radio(),
                                 relay_frames_per_s=relay_frames_per_s(self.n, self.cfg.swarm_rate_hz))
            loop.add_reader(self.medium.fileno(), self._on_medium)
            sc = self.cfg.scenario
            if sc.commands:
                signer = self.links.signing.link(SOURCE_LINK_ID)
                self.commands = SitlCommands(sc, Mission(sc.mission), self.medium, self.telemetry.epoch_unix_s,
                                             self.medium.codec, None if signer is None else signer.sign)

    def _setup_signing_refused(self, k: int, reason: str) -> None:
        """An endpoint's signing layer dropped a SETUP_SIGNING for vehicle k: count and answer it."""
        self.router.refuse_setup_signing(k, reason)
        self.after_change(k)

    def _on_readable(self, ep: MavEndpoint, k: int | None) -> None:
        sg = ep.signing
        for msg, addr in ep.poll():
            if k is not None and (sg is None or sg.claims_unsigned or signature_of(msg) is not None):
                self.attached[k] = True  # under require, an unsigned RADIO_STATUS attaches nobody
            try:
                self.router.handle(ep, msg, addr, k)
            except Exception:  # bad content must never take the SITL down
                ep.bad_frames += 1
        ep.flush()

    def _on_medium(self) -> None:
        assert self.medium is not None
        self.medium.receive()
        self._wake_lockstep()

    def request_stop(self) -> None:
        """Stop the tasks (from any thread)."""
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    async def _heartbeat_task(self) -> None:
        """Heartbeats and paced parameter listings, on the wall clock (they flow while a
        lockstep clock waits, as MAVSDK's timeouts are wall-clock)."""
        assert self._stop is not None
        last = self.wall_clock()
        while not self._stop.is_set():
            now = self.wall_clock()
            ks, _ = self.heartbeats.due(now)
            for k in ks.tolist():
                self.links.broadcast(k, self.telemetry.heartbeat(k), gcs=False)
            gks = self.gcs_heartbeats.due(now)[0] if self.links.gcs is not None else ks[:0]
            for k in gks.tolist():
                self.links.broadcast(k, self.telemetry.heartbeat(k), vehicle=False)
            listed = self.router.pump_params(now - last)
            last = now
            if len(ks) or len(gks):
                self.links.flush_all()
            else:
                for ep in listed:
                    ep.flush()
            try:
                await asyncio.wait_for(self._stop.wait(), HEARTBEAT_POLL_S)
            except asyncio.TimeoutError:
                pass

    async def _sim_task(self) -> None:
        """Take ticks; the decision to step and the step itself have no await between them."""
        assert self._stop is not None and self._sp_event is not None
        tc = self.cfg.time
        wall0, sim0 = self.wall_clock(), self.sim_s
        while not self._stop.is_set():
            if self.gate.held(self.ticks, self.fleet.fix_t):
                await asyncio.sleep(0.02)
                wall0, sim0 = self.wall_clock(), self.sim_s
                continue
            if self.wall_started is None:
                self.wall_started, self.sim_started_s = self.wall_clock(), self.sim_s
            if tc.lockstep and self.any_clock_driver():
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
            if self.medium is not None:
                self._radio_tick(tc.lockstep)
            self.links.flush_all()
            self.gate.sp_fresh[:] = False
            # Stop decided on simulation time, in this loop: a lockstep run ends on the same tick.
            if self._stop_when_done and self.mission_done:
                print("MISSION COMPLETE", flush=True)
                self._stop.set()
                break
            if self._stop_at_s is not None and self.sim_s >= self._stop_at_s - 1e-9:
                print("DURATION REACHED", flush=True)
                self._stop.set()
                break
            await asyncio.sleep(0)  # let the sockets be read

    async def _status_task(self, out: TextIO) -> None:
        assert self._stop is not None
        while not self._stop.is_set():
            try:
                await asyncio.wait_for(self._stop.wait(), STATUS_PERIOD_S)
            except asyncio.TimeoutError:
                pass
            print(self.status().to_line(), file=out, flush=True)

    async def run(self, on_ready: Callable[["SitlServer"], None] | None = None,
                  handle_signals: bool = False, status_out: TextIO | None = None, stop_when_done: bool = False,
                  stop_at_s: float | None = None) -> None:
        """Start, then run the tasks until stopped (request_stop, a signal, the mission done
        with stop_when_done, or simulated time stop_at_s).

        Raises:
            OSError: a port cannot be bound.
        """
        await self.start()
        loop, stop = self._loop, self._stop
        assert loop is not None and stop is not None
        if handle_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
        if on_ready is not None:
            on_ready(self)
        tasks = [self._sim_task(), self._heartbeat_task()]
        if status_out is not None:
            tasks.append(self._status_task(status_out))
        self._stop_when_done, self._stop_at_s = stop_when_done, stop_at_s
        try:
            await asyncio.gather(*tasks)
        finally:
            self.links.close(loop)
            if self.medium is not None:
                loop.remove_reader(self.medium.fileno())
                self.medium.close()


def _first_go(t_go_s: np.ndarray) -> float | None:
    """The earliest transit start published (None if none has been)."""
    go = t_go_s[np.isfinite(t_go_s)]
    return round(float(go.min()), 3) if len(go) else None
