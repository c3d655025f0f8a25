"""`swarmdrop agent`: one Agent, one autopilot, one swarm link, one asyncio loop.

The loop wakes when the autopilot's socket (or the swarm socket) is readable. A
new LOCAL_POSITION_NED is a control tick: the agent drains the swarm socket,
steps the sans-IO Agent at the autopilot's time, converts the setpoint to the
vehicle's local frame and sends it, publishes its own state when due, and
flushes; so a tick costs one wake-up and latency is telemetry-to-setpoint, not a
timer period. In lockstep (the SITL's) a tick waits until position, attitude and
the radio's end-of-tick marker of one instant are all in, and ends with a
SWARMDROP_TICK, which lets simulation time advance.

Setup and launch run beside it as commands with timeouts and retries. Exit codes:
see ExitCode (docs/companion.md).
"""
from __future__ import annotations

import asyncio
import collections
import dataclasses
import gc
import json
import logging
import math
import signal
import time
from enum import IntEnum

import numpy as np

from companion.agent import FORMATION_PHASES, Agent, OwnState, Phase
from companion.config import ConfigError
from companion.control.geometric import pack_control_params, position_law, quat_to_rot
from companion.frames import rot_to_quat_wxyz
from companion.link.dialects import Mode
from companion.link.endpoints import MavEndpoint, UdpLink, open_link
from companion.link.limits import SetpointLimits, clamp_tilt, clamp_velocity, fence_trajectory
from companion.link.msgdef import swarmdrop as md
from companion.link.setpoints import attitude_target_fields, position_target_fields
from companion.link.signing import Signing, SigningError, TimestampStore, load_key
from companion.link.wire import Codec
from companion.mission import Mission
from companion.node.config import NodeConfig
from companion.node.swarmlink import SwarmLink, view_for
from companion.node.vehicle import MAV_COMP_ID_ONBOARD_COMPUTER, CommandError, VehicleLink
from companion.params import GRAVITY_MPS2
from companion.swarm import swarm_due

log = logging.getLogger("swarmdrop.agent")

MSG_SYSTEM_TIME, MSG_LPN, MSG_ATT_Q, MSG_GPS_ORIGIN, MSG_HOME, MSG_EXT_STATE = 2, 32, 31, 49, 242, 245
MAV_FRAME_LOCAL_NED = 1
STATS_PERIOD_S = 5.0
LAT_BIN_US, LAT_BINS = 50, 1000
"""Latency histogram in the statistics: 50 µs bins up to 50 ms (a fleet pools them)."""
LAUNCH_RETRY_S = 1.0
LAUNCH_TIMEOUT_S = 60.0


class ExitCode(IntEnum):
    OK = 0
    """Stopped by SIGINT/SIGTERM (the normal end of a flight)."""
    ERROR = 1
    """An unexpected internal error (logged with its traceback)."""
    CONFIG = 2
    """Bad arguments or mission file."""
    NO_AUTOPILOT = 3
    """No autopilot HEARTBEAT within the timeout, or an autopilot of no known dialect."""
    SETUP = 4
    """Streams, clock, EKF origin or parameters could not be set up in time."""
    LAUNCH = 5
    """Arming, take-off or the switch to offboard/GUIDED was refused after retries."""
    LINK_LOST = 6
    """The autopilot fell silent in flight (its own failsafe flies the vehicle)."""


class NodeFailure(RuntimeError):
    def __init__(self, code: ExitCode, message: str):
        super().__init__(message)
        self.code = code


class Plan:
    """The planner's last setpoint as plain floats, and how to advance it between plans.

    kind: "state" (position and velocity given: advanced along the acceleration),
    "fixed" (something else commanded, e.g. a stop: sent as it is), "" (nothing to send).
    """

    __slots__ = ("t", "p", "v", "a", "yaw", "yaw_rate", "kind", "attitude_ok")
    t: float
    p: list[float]
    v: list[float]
    a: list[float]
    yaw: float
    yaw_rate: float
    kind: str
    attitude_ok: bool

    @classmethod
    def of(cls, t: float, sp, q) -> "Plan":
        self = cls()
        self.t = t
        self.p, self.v, self.a = sp.pos_ned_m[0].tolist(), sp.vel_ned_mps[0].tolist(), sp.acc_ned_mps2[0].tolist()
        self.yaw, self.yaw_rate = float(sp.yaw_rad[0]), float(sp.yaw_rate_radps[0])
        finite = [math.isfinite(x[0] + x[1] + x[2]) for x in (self.p, self.v, self.a)]
        self.kind = "state" if finite[0] and finite[1] else ("fixed" if any(finite) else "")
        if self.kind == "state" and not finite[2]:
            self.a = [0.0, 0.0, 0.0]
        self.attitude_ok = self.kind == "state" and bool(np.isfinite(q).all())
        return self

    def at(self, t: float) -> tuple:
        """(px, py, pz, vx, vy, vz, ax, ay, az) at t (NaN axes stay NaN: not commanded)."""
        p, v, a = self.p, self.v, self.a
        if self.kind != "state":
            return (*p, *v, *a)
        dt = t - self.t
        h = 0.5 * dt * dt
        return (p[0] + v[0] * dt + a[0] * h, p[1] + v[1] * dt + a[1] * h, p[2] + v[2] * dt + a[2] * h,
                v[0] + a[0] * dt, v[1] + a[1] * dt, v[2] + a[2] * dt, a[0], a[1], a[2])


class AgentNode:
    """One companion process. `await run()` returns an ExitCode."""

    def __init__(self, cfg: NodeConfig):
        self.cfg = cfg
        mf = cfg.mission
        mcfg = dataclasses.replace(mf.mission, setpoint=dataclasses.replace(mf.mission.setpoint,
                                                                            lead_s=1.0 / cfg.rate_hz))
        self.mission = Mission(mcfg)
        self.agent = Agent(self.mission, np.array([cfg.vehicle_id]))
        self.codec = Codec(md)
        self._sign_store: TimestampStore | None = None
        self._sign_key = b""
        sysid = cfg.own_sysid
        ap_sign, sw_sign = self._signing(0), self._signing(1)
        self.ap_ep = MavEndpoint(open_link(cfg.autopilot_url, self.codec.crc_extra), self.codec, sysid,
                                 MAV_COMP_ID_ONBOARD_COMPUTER, signing=ap_sign)
        self.sw_ep = MavEndpoint(UdpLink(bind=cfg.swarm_bind, remote=None, learn_remote=False), self.codec, sysid,
                                 MAV_COMP_ID_ONBOARD_COMPUTER, signing=sw_sign)
        if mcfg.origin is None:  # check_node refuses such a mission first; this keeps the type honest
            raise ConfigError("mission.origin is required by the agent")
        self.vehicle = VehicleLink(self.ap_ep, cfg.target_sysid, mcfg.origin)
        self.view = view_for(self.mission.n)
        self.swarm = SwarmLink(self.sw_ep, cfg.vehicle_id, cfg.swarm_peers, self.view)
        self.period_us = int(round(1e6 / cfg.rate_hz))
        self.ctrl_prm = pack_control_params(mf.vehicle, mf.inner_loop.geometric).tolist()  # read element-wise
        self.hover_thrust = math.nan
        self.epoch_us = 0
        self.flying = False
        self.last_tick_ms = -1
        self.phase = Phase.LAUNCH
        self.plan: Plan | None = None
        """The last Agent.step's setpoint."""
        self.swarm_rate_hz = self.mission.cfg.swarm.rate_hz
        self.late_s = 1.5 / cfg.rate_hz
        """A setpoint interval longer than this counts as a deadline miss."""
        self.offboard_task: asyncio.Task | None = None
        self.offboard_state = "idle"  # idle -> requesting -> engaged (-> lost: the autopilot left it)
        self.left_offboard = 0
        self._stop = asyncio.Event()
        self._failure: NodeFailure | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        # statistics
        self.ticks = 0
        self.setpoints_sent = 0
        self.latency_s: collections.deque = collections.deque(maxlen=100_000)
        self.step_s: collections.deque = collections.deque(maxlen=20000)
        self.last_send_wall = math.nan
        self.deadline_misses = 0
        self.intervals = 0
        self.unsendable = 0
        self.limits = SetpointLimits()
        """PX4's default offboard limits: the agent's setpoints stay inside them on either autopilot."""
        self.start_wall = time.monotonic()
        self.start_cpu = time.process_time()
        self.ready_wall_s = math.nan
        self.startup_s: float | None = None
        """From process start to a constructed node (imports, mission, sockets), s."""

    # ------------------------------------------------------------------ I/O callbacks
    def _on_autopilot(self) -> None:
        t_recv = time.perf_counter()
        v = self.vehicle
        raw, msgs = self.ap_ep.poll_split(v.RAW_IDS)
        for msg in msgs:
            v.handle(msg)
        for r in raw:
            v.handle_raw(*r)
        if v.new_control:
            self._maybe_tick(t_recv)
        if self.ap_ep.pending:
            self.ap_ep.flush()

    def _on_swarm(self) -> None:
        t_recv = time.perf_counter()
        self.swarm.poll()
        if self.cfg.lockstep and self.vehicle.new_control:
            self._maybe_tick(t_recv)

    def _maybe_tick(self, t_recv: float) -> None:
        v = self.vehicle
        if not self.flying or v.lpn is None:
            return
        ms = v.lpn.time_boot_ms
        if ms == self.last_tick_ms:
            v.new_control = False
            return
        if self.cfg.lockstep:
            # One instant's inputs, all of them: attitude, and on the ticks the radio delivers
            # (this vehicle's swarm ticks) its batch, ended by the marker.
            if v.att is None or v.att.time_boot_ms != ms:
                return
            unix_us = v.unix_us(ms)
            if unix_us is None:
                return
            if self.swarm.marker_us < unix_us and swarm_due(unix_us, self.swarm_rate_hz, self.cfg.vehicle_id,
                                                              self.period_us):
                return
        v.new_control = False
        self.last_tick_ms = ms
        try:
            self._tick(t_recv)
        except Exception:  # a bug must not kill a flying companion: the autopilot failsafes meanwhile
            log.exception("tick failed")

    # ------------------------------------------------------------------ the control tick
    def _tick(self, t_recv: float) -> None:
        cfg, v, lpn = self.cfg, self.vehicle, self.vehicle.lpn
        if lpn is None:
            return
        ms = lpn.time_boot_ms
        unix_us = v.unix_us(ms)
        if unix_us is None:
            return  # ticks start after set-up, which waits for SYSTEM_TIME
        t = (unix_us - self.epoch_us) * 1e-6
        lp = lpn.values
        publish = swarm_due(unix_us, self.swarm_rate_hz, cfg.vehicle_id, self.period_us)
        k = (unix_us + self.period_us // 2) // self.period_us
        # Plans on the ticks it publishes (vehicle-staggered, as swarm_due) and every plan_every-th,
        # after this tick's setpoint has left: the planner's output is a trajectory for the next
        # ticks, so planning adds nothing to the telemetry-to-setpoint latency.
        plan_now = publish or (k + cfg.vehicle_id) % cfg.plan_every == 0
        if self.plan is None:
            self._plan(t, lp, ms, publish)
            plan_now = False
        plan = self.plan
        assert plan is not None  # _plan always leaves one
        sent = bool(plan.kind) and self._send(plan, t, ms, lp)
        if sent and self.phase in FORMATION_PHASES:
            self._ensure_offboard()
        self.ap_ep.flush()
        now = time.perf_counter()
        self.ticks += 1
        if sent:
            self.setpoints_sent += 1
            self.latency_s.append(now - t_recv)
            if self.last_send_wall == self.last_send_wall:  # not NaN
                self.intervals += 1
                if now - self.last_send_wall > self.late_s:
                    self.deadline_misses += 1
            self.last_send_wall = now
        else:
            self.last_send_wall = math.nan
        if plan_now:
            self._plan(t, lp, ms, publish)
        if self.sw_ep.pending:
            self.sw_ep.flush()
        if cfg.lockstep:  # after the setpoint and the published state: this tick is done
            v.send(md.MAVLINK_MSG_ID_SWARMDROP_TICK, [unix_us])
            self.ap_ep.flush()

    def _plan(self, t: float, lp: tuple, ms: int, publish: bool) -> None:
        """Run the Agent (the planner) on this tick's inputs; keep its setpoint as a Plan.
        The swarm socket is drained here, once per plan: only the planner reads the view."""
        v = self.vehicle
        self.swarm.poll()
        off = v.offset
        pos = np.array([lp[0] + off[0], lp[1] + off[1], lp[2] + off[2]])
        vel = np.array(lp[3:6], float)
        q = np.array(v.att.values if v.att is not None and abs(v.att.time_boot_ms - ms) <= 500 else [np.nan] * 4)
        hb = v.hb
        released = hb is not None and hb.armed and hb.landed_state not in (0, 1)
        own = OwnState(pos[None], vel[None], q[None], np.array([t]), np.array([released]),
                       np.array([v.launch_ready]))
        t_step = time.perf_counter()
        out = self.agent.step(t, own, self.view)
        self.step_s.append(time.perf_counter() - t_step)
        if publish:
            self.swarm.publish(out.published)
        phase = Phase(int(out.phase[0]))
        if phase != self.phase:
            log.info("phase %s -> %s at t=%.2f s", self.phase.name, phase.name, t)
            self.phase = phase
        self.plan = Plan.of(t, out.setpoint, q)

    def _send(self, plan: "Plan", t: float, ms: int, lp: tuple) -> bool:
        """This tick's setpoint: the plan advanced to t, in the vehicle's local frame; False
        if nothing sendable (never a malformed setpoint: the autopilot's failsafe covers a gap)."""
        v = self.vehicle
        off = v.offset
        px, py, pz, vx, vy, vz, ax, ay, az = plan.at(t)
        # Setpoint hygiene (companion.link.limits): what PX4 would clamp, we never send.
        vx, vy, vz = clamp_velocity(vx, vy, vz, self.limits)
        fence = self.mission.cfg.geofence
        if fence is not None:
            own_pos = (lp[0] + off[0], lp[1] + off[1], lp[2] + off[2])
            (px, py, pz), (vx, vy, vz), (ax, ay, az) = fence_trajectory(
                (px, py, pz), (vx, vy, vz), (ax, ay, az), fence.min_ned_m, fence.max_ned_m, own_pos)
        try:
            if self.cfg.output == "attitude" and plan.attitude_ok and self.hover_thrust == self.hover_thrust \
                    and v.att is not None:
                own = (lp[0] + off[0], lp[1] + off[1], lp[2] + off[2]), lp[3:6]
                fields = self._attitude_fields((px, py, pz, vx, vy, vz, ax, ay, az, plan.yaw, plan.yaw_rate), own,
                                               v.att.values)
                v.send(md.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET, [ms, v.target_sysid, 1, fields[0], *fields[1]])
            else:
                mask, f = position_target_fields((px - off[0], py - off[1], pz - off[2]), (vx, vy, vz),
                                                 (ax, ay, az), plan.yaw, plan.yaw_rate)
                v.send(md.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED,
                       [ms, v.target_sysid, 1, MAV_FRAME_LOCAL_NED, mask, *f])
        except ValueError as err:
            self.unsendable += 1
            log.debug("setpoint not sent: %s", err)
            return False
        return True

    def _attitude_fields(self, target: tuple, own: tuple, q) -> tuple[int, tuple]:
        """eq. 14-16 on the companion: desired attitude and thrust from the state setpoint.

        Args:
            target: (px, py, pz, vx, vy, vz, ax, ay, az, yaw, yaw_rate), mission frame.
            own: (position, velocity) of the vehicle, mission frame. q: its attitude (w, x, y, z).
        """
        row = [*target] + [math.nan] * 8  # packed setpoint row (companion.control.geometric.SP_*): no attitude
        rot = quat_to_rot(*q)  # row-major 9-tuple, as position_law takes it
        rot_d, f, _ = position_law(tuple(own[0]), tuple(own[1]), rot, row, self.ctrl_prm)
        q_d = clamp_tilt(rot_to_quat_wxyz(np.array(rot_d).reshape(3, 3)), self.limits.tilt_max_rad)
        weight = self.cfg.mission.vehicle.mass_kg * GRAVITY_MPS2
        thrust = self.vehicle.ap.thrust_field(f / weight, self.hover_thrust, rot[8])  # rot[8]: cos(tilt)
        return attitude_target_fields(q_d, thrust)

    def _ensure_offboard(self) -> None:
        """Switch the autopilot to OFFBOARD (PX4) / GUIDED (ArduPilot) once the agent flies
        formation; if the autopilot later leaves it (its failsafe, a pilot), let it be."""
        v = self.vehicle
        in_offboard = v.hb is not None and v.ap.mode_of(v.hb.custom_mode) == Mode.OFFBOARD
        if in_offboard:
            self.offboard_state = "engaged"
            return
        if self.offboard_state == "idle":
            self.offboard_state = "requesting"
            task = v.command_now(176, v.ap.set_mode_params(Mode.OFFBOARD))
            task.add_done_callback(self._offboard_done)
            self.offboard_task = task
        elif self.offboard_state == "engaged":
            self.offboard_state = "lost"
            self.left_offboard += 1
            log.warning("autopilot left %s; not switching back (its failsafe or pilot decides)",
                        v.ap.mode_name(v.ap.custom_mode(Mode.OFFBOARD)))

    def _offboard_done(self, task: asyncio.Task) -> None:
        if task.cancelled() or self.offboard_state != "requesting":
            return
        err = task.exception()
        if err is not None:
            log.warning("switch to offboard: %s (asking again)", err)
            self.offboard_state = "idle"
        else:
            self.offboard_state = "engaged"
            log.info("autopilot in %s", self.vehicle.ap.mode_name(self.vehicle.ap.custom_mode(Mode.OFFBOARD)))

    # ------------------------------------------------------------------ setup and launch
    async def _wait(self, cond, timeout_s: float, what: str, code: ExitCode) -> None:
        deadline = self.loop.time() + timeout_s
        while not cond():
            if self.loop.time() > deadline:
                raise NodeFailure(code, f"{what}: nothing within {timeout_s:g} s")
            await asyncio.sleep(0.05)

    async def _setup(self) -> None:
        cfg, v = self.cfg, self.vehicle
        await self._wait(lambda: v.dialect is not None, cfg.setup_timeout_s, "autopilot HEARTBEAT",
                         ExitCode.NO_AUTOPILOT)
        d = v.ap
        try:
            for msgid, interval in ((MSG_LPN, 1.0 / cfg.rate_hz), (MSG_ATT_Q, 1.0 / cfg.rate_hz),
                                    (MSG_EXT_STATE, 0.2), (MSG_SYSTEM_TIME, 1.0)):
                await v.set_message_interval(msgid, interval)
            await v.request_message(MSG_SYSTEM_TIME)
        except CommandError as err:
            raise NodeFailure(ExitCode.SETUP, f"telemetry streams: {err}") from None
        deadline = self.loop.time() + cfg.setup_timeout_s
        while v.offset_ned_m is None:  # no origin before the autopilot's first GNSS fix
            try:
                await v.request_message(MSG_GPS_ORIGIN, timeout_s=1.0, retries=1)
            except CommandError:
                if self.loop.time() > deadline:
                    raise NodeFailure(ExitCode.SETUP, "no GPS_GLOBAL_ORIGIN: the autopilot has no EKF origin") \
                        from None
        await self._wait(lambda: v.unix_offset_us is not None, cfg.setup_timeout_s, "SYSTEM_TIME", ExitCode.SETUP)
        # Mission time is Unix time less a whole hour near the autopilot's boot: small floats;
        # every exchanged time is absolute (µs), so agents need not share this epoch.
        assert v.unix_offset_us is not None  # the wait above
        epoch_s = v.unix_offset_us // 1_000_000 // 3600 * 3600
        self.epoch_us = epoch_s * 1_000_000
        self.swarm.set_epoch(epoch_s)
        try:
            if cfg.output == "attitude":
                for name, bits in d.attitude_params().items():
                    current = int(await v.get_param(name))
                    if current & int(bits) != int(bits):
                        await v.set_param(name, current | int(bits))
                self.hover_thrust = await v.get_param(d.hover_thrust_param)
                log.info("%s = %.3f", d.hover_thrust_param, self.hover_thrust)
            if cfg.launch == "carrier":
                for name, value in d.carrier_params().items():
                    if await v.get_param(name) != value:
                        await v.set_param(name, value)
        except CommandError as err:
            raise NodeFailure(ExitCode.SETUP, f"parameters: {err}") from None
        self.ready_wall_s = time.monotonic() - self.start_wall
        log.info("set up in %.2f s: %s, %s output at %g Hz, %s launch%s", self.ready_wall_s, d.name, cfg.output,
                 cfg.rate_hz, cfg.launch, ", lockstep" if cfg.lockstep else "")

    def _attach(self) -> None:
        """Start flying: ticks run from now on, and the first companion HEARTBEAT (a fleet
        SITL starts its clock once every vehicle's companion has sent one).

        The garbage collector is taken off the tick path: what start-up built is frozen
        (never scanned again) and collection runs in the 1 Hz supervision loop instead of
        at whatever allocation a tick happens to make (a full pass costs milliseconds).
        Ticks allocate no reference cycles, so nothing accumulates meanwhile."""
        gc.collect()
        gc.freeze()
        gc.disable()
        if self.cfg.lockstep:  # declare ourselves a lockstep companion before the clock may start
            self.vehicle.send(md.MAVLINK_MSG_ID_SWARMDROP_TICK, [0])
        self.vehicle.heartbeat()
        self.ap_ep.flush()
        self.flying = True

    async def _launch(self) -> None:
        cfg, v = self.cfg, self.vehicle
        d = v.ap
        if cfg.launch == "carrier":
            await self._arm_for_throw()
            self._attach()
            return  # the carrier releases; the autopilot's throw recovery takes over
        self._attach()
        home = await v.request_message(MSG_HOME)
        deadline = self.loop.time() + LAUNCH_TIMEOUT_S
        while True:
            hb = v.hb
            assert hb is not None  # set-up waited for the HEARTBEAT
            try:
                if d.mode_of(hb.custom_mode) != d.takeoff_from_mode:
                    await v.command(176, d.set_mode_params(d.takeoff_from_mode))
                if not hb.armed:
                    await v.command(400, [1.0])
                await v.command(22, d.takeoff_params(cfg.takeoff_alt_m, home.altitude * 1e-3))
                log.info("taking off to %.1f m", cfg.takeoff_alt_m)
                return
            except CommandError as err:
                if self.loop.time() > deadline:
                    raise NodeFailure(ExitCode.LAUNCH, f"ground launch: {err}") from None
                log.info("ground launch: %s; retrying", err)
                await asyncio.sleep(LAUNCH_RETRY_S)

    async def _arm_for_throw(self) -> None:
        """On the carrier: select the autopilot's throw mode (ArduPilot THROW) and arm, so its
        throw launch recovers the vehicle. An autopilot that will not arm on the carrier
        (or is already flying) is left as it is: the carrier or the operator arms it."""
        v = self.vehicle
        d = v.ap
        if v.hb is None or v.hb.armed or v.hb.in_air:
            return
        try:
            if d.carrier_mode is not None and d.mode_of(v.hb.custom_mode) != d.carrier_mode:
                await v.command(176, d.set_mode_params(d.carrier_mode))
            await v.command(400, [1.0])
            log.info("armed on the carrier for the throw launch")
        except CommandError as err:
            log.info("not armed on the carrier (%s): the carrier arms it at release", err)

    async def _supervise(self) -> None:
        """Companion HEARTBEAT at 1 Hz, autopilot-loss watchdog, statistics file."""
        v = self.vehicle
        next_stats = self.loop.time() + STATS_PERIOD_S
        while not self._stop.is_set():
            v.heartbeat()
            self.ap_ep.flush()
            gc.collect(1)  # between ticks (see _attach)
            if self.loop.time() - v.hb_loop_time > self.cfg.heartbeat_timeout_s:
                raise NodeFailure(ExitCode.LINK_LOST, f"no autopilot HEARTBEAT for {self.cfg.heartbeat_timeout_s:g} s")
            if self.loop.time() >= next_stats:
                self.write_stats()
                next_stats += STATS_PERIOD_S
            try:
                await asyncio.wait_for(self._stop.wait(), 1.0)
            except asyncio.TimeoutError:
                pass

    async def _body(self) -> None:
        await self._setup()
        await self._launch()
        await self._supervise()

    async def run(self, handle_signals: bool = True) -> ExitCode:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._loop.add_reader(self.ap_ep.link.fileno(), self._on_autopilot)
        if self.cfg.lockstep:  # the radio's end-of-tick marker may be the last input of a tick
            self._loop.add_reader(self.sw_ep.link.fileno(), self._on_swarm)
        if handle_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(sig, self._stop.set)
        body = asyncio.ensure_future(self._body())
        stop = asyncio.ensure_future(self._stop.wait())
        code = ExitCode.OK
        try:
            await asyncio.wait({body, stop}, return_when=asyncio.FIRST_COMPLETED)
            if body.done() and body.exception() is not None:
                err = body.exception()
                if isinstance(err, NodeFailure):
                    log.error("%s", err)
                    code = err.code
                else:
                    log.error("internal error", exc_info=err)
                    code = ExitCode.ERROR
        finally:
            for task in (body, stop, self.offboard_task):
                if task is not None and not task.done():
                    task.cancel()
            self._loop.remove_reader(self.ap_ep.link.fileno())
            if self.cfg.lockstep:
                self._loop.remove_reader(self.sw_ep.link.fileno())
            self.write_stats()
            self.ap_ep.close()
            self.sw_ep.close()
        log.info("exit %d (%s)", int(code), code.name)
        return code

    def request_stop(self) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    # ------------------------------------------------------------------ statistics
    def _signing(self, link_id: int) -> Signing | None:
        """Signing of one of our links (0 autopilot, 1 swarm). Raises SigningError (a
        ConfigError for the CLI) on a missing or unsafe key file."""
        cfg = self.cfg
        if cfg.signing == "off":
            return None
        if cfg.signing_key_file is None:
            raise SigningError(f"signing {cfg.signing!r} needs --signing-key FILE")
        if self._sign_store is None:
            self._sign_key = load_key(cfg.signing_key_file)
            self._sign_store = TimestampStore(f"{cfg.signing_key_file}.timestamp-{cfg.own_sysid}")
        return Signing(cfg.signing, self._sign_key, link_id=link_id, store=self._sign_store,
                       crc_extra=self.codec.crc_extra)

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop run() runs on. Raises RuntimeError before run()."""
        if self._loop is None:
            raise RuntimeError("AgentNode.loop before run()")
        return self._loop

    def stats(self) -> dict:
        lat = np.array(self.latency_s) * 1e3 if self.latency_s else np.zeros(0)
        wall = time.monotonic() - self.start_wall
        v = self.vehicle
        return {
            "vehicle_id": self.cfg.vehicle_id, "phase": self.phase.name, "ticks": self.ticks,
            "setpoints_sent": self.setpoints_sent, "unsendable_setpoints": self.unsendable,
            "latency_ms": {f"p{p}": float(np.percentile(lat, p)) for p in (50, 90, 99)} | {
                "max": float(lat.max())} if len(lat) else {},
            "latency_hist": {"bin_us": LAT_BIN_US, "counts": np.bincount(
                np.minimum((np.array(self.latency_s) * 1e6 / LAT_BIN_US).astype(int), LAT_BINS - 1),
                minlength=LAT_BINS).tolist()} if self.latency_s else {},
            "agent_step_ms": {f"p{p}": float(np.percentile(np.array(self.step_s) * 1e3, p)) for p in (50, 99)}
            if self.step_s else {},
            "deadline_misses": self.deadline_misses, "setpoint_intervals": self.intervals,
            "cpu_s": time.process_time() - self.start_cpu, "wall_s": wall, "setup_s": self.ready_wall_s,
            "startup_s": self.startup_s,
            "left_offboard": self.left_offboard,
            "autopilot": {"dialect": v.dialect.name if v.dialect else None, "bad_frames": self.ap_ep.bad_frames,
                          "unknown_messages": self.ap_ep.unknown,
                          "foreign": v.foreign, "dropped_nonfinite": v.dropped_nonfinite,
                          "bytes_in": self.ap_ep.link.bytes_in, "bytes_out": self.ap_ep.link.bytes_out},
            "swarm": self.swarm.counters(),
            "signing": {name: dataclasses.asdict(ep.signing.counters) for name, ep in
                        (("autopilot", self.ap_ep), ("swarm", self.sw_ep)) if ep.signing is not None},
        }

    def write_stats(self) -> None:
        if self.cfg.stats_path is None:
            return
        tmp = self.cfg.stats_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.stats(), indent=1))
        tmp.replace(self.cfg.stats_path)
