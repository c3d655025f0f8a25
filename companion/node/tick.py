"""The per-tick path: telemetry received -> Agent.step on a plan tick -> setpoint sent.

A new LOCAL_POSITION_NED is a control tick: the tick sends this tick's setpoint (the
last plan advanced to now, in the vehicle's local frame), then runs the planner when
due, publishes the vehicle's state when due, and flushes; so a tick costs one wake-up,
and latency is telemetry-to-setpoint, not a timer period. In lockstep (the SITL's) a
tick waits until position, attitude and the radio's end-of-tick marker of one instant
are all in, and ends with a SWARMDROP_TICK, which lets simulation time advance.

This is the hot path (p99 latency target 2 ms on a small companion computer): the
state is plain floats and tuples, numpy only where the Agent wants arrays (on plan
ticks), message builders are resolved once here, and no reference cycles are made
(the garbage collector is off while flying: AgentNode._attach).
"""
from __future__ import annotations

import asyncio
import logging
import math
import time

import numpy as np

from companion.agent import FORMATION_PHASES, Agent, OwnState, Phase
from companion.control.geometric import pack_control_params
from companion.link.dialects import Mode
from companion.link.dialects.base import PositionLoop
from companion.link.enums import MavCmd, MavComponent, MavFrame, MavLandedState, MsgId
from companion.link.limits import SetpointLimits
from companion.link.setpoints import attitude_target_fields, position_target_fields
from companion.mission import Mission
from companion.node.config import NodeConfig
from companion.node.offboard import Offboard
from companion.node.stats import TickCounters
from companion.node.swarmlink import SwarmLink
from companion.node.vehicle import TICK_WAIT_S, VehicleLink
from companion.output import SEND_ATTITUDE, SEND_NOTHING, OutputStage, output_stage_for
from companion.swarm import SwarmView, swarm_due, tick_index

log = logging.getLogger("swarmdrop.agent")

ATTITUDE_MAX_AGE_MS = 500
"""An attitude older (or newer) than this against the tick's position is not used by the planner."""
NOT_RELEASED = (MavLandedState.MAV_LANDED_STATE_UNDEFINED, MavLandedState.MAV_LANDED_STATE_ON_GROUND)
"""Landed states of a vehicle still on the carrier or the ground (not released, even if armed)."""
RELAY_FAST_S = 1.0
"""A new plan is relayed on every publishing tick (the swarm rate) until this long after its
effective time, then every RELAY_SLOW_EVERY-th (docs/swarm.md, relays)."""
RELAY_SLOW_EVERY = 10
HOLD_RETRY_S = 1.0
"""After an ABORT, the switch to the autopilot's Hold is asked again this often until its
HEARTBEAT shows it (mission time, s)."""


class TickPath:
    """The control ticks of one node.

    Args:
        cfg: the node's configuration (rate, output, lockstep, plan_every, vehicle id).
        mission: the mission (geofence, swarm rate). agent: the sans-IO Agent that plans.
        vehicle: the autopilot link. swarm: the swarm link, whose view the agent reads.
        offboard: the offboard engagement, asked for on formation ticks.

    Ticks run once `attach` has been called (after set-up, at launch).
    """

    def __init__(self, cfg: NodeConfig, mission: Mission, agent: Agent, vehicle: VehicleLink, swarm: SwarmLink,
                 offboard: Offboard):
        self.cfg = cfg
        self.mission = mission
        self.agent = agent
        self.vehicle = vehicle
        self.ap_ep = vehicle.ep
        self.swarm = swarm
        self.sw_ep = swarm.ep
        self.view: SwarmView = swarm.view
        self.offboard = offboard
        self.counters = TickCounters()
        self.period_us = int(round(1e6 / cfg.rate_hz))
        """The setpoint period, µs."""
        self.swarm_rate_hz = mission.cfg.swarm.rate_hz
        self.late_s = 1.5 / cfg.rate_hz
        """A setpoint interval longer than this counts as a deadline miss, s."""
        self.limits = SetpointLimits()
        """PX4's default offboard limits: the agent's setpoints stay inside them on either autopilot."""
        self.output: OutputStage = output_stage_for(
            mission.cfg, 1, limits=self.limits, attitude=cfg.output == "attitude",
            ctrl_prm=pack_control_params(cfg.mission.vehicle, cfg.mission.inner_loop.geometric),
            thrust_field=lambda tw, h, c: vehicle.ap.thrust_field(tw, h, c))  # (the dialect: known after set-up)
        """The output stage (companion.output): the same lines as the headless runner's."""
        self._own_p, self._own_v, self._own_q = np.zeros((1, 3)), np.zeros((1, 3)), np.full((1, 4), np.nan)
        self.epoch_us = 0
        """Unix time of mission time 0, µs (set-up derives it from the autopilot's clock)."""
        self.flying = False
        self.last_tick_ms = -1
        """time_boot_ms of the last tick's LOCAL_POSITION_NED."""
        self.phase = Phase.LAUNCH
        self.plan_seq = 0
        """The swarm plan in force (logged when it changes)."""
        self.handed_over = False
        """An ABORT plan handed the vehicle to its autopilot's Hold."""
        self._hold_asked_s = -math.inf
        self._publishes = 0
        self.planned = False
        """Agent.step has run once (its setpoint is the output stage's plan)."""
        self._settling = False
        """Lockstep: a tick has just ended; the exchanges it woke have not run yet."""
        self._ended_us = -1
        """Lockstep: Unix µs of the last tick whose end was sent."""
        codec = self.ap_ep.codec  # named-field builders, resolved once: one plain call per message
        self._position_target = codec.builder(MsgId.SET_POSITION_TARGET_LOCAL_NED)
        self._attitude_target = codec.builder(MsgId.SET_ATTITUDE_TARGET)
        self._tick_marker = codec.builder(MsgId.SWARMDROP_TICK)

    def attach(self, epoch_us: int, hover_thrust: float, loop: PositionLoop | None = None) -> None:
        """Start ticking: in lockstep, declare this a lockstep companion (a SWARMDROP_TICK of
        time 0) before the SITL's clock may start, then send the first companion HEARTBEAT
        (a fleet SITL starts its clock once every vehicle's companion has sent one).

        Args:
            epoch_us: Unix time of mission time 0, µs. hover_thrust: the autopilot's (NaN: unknown).
            loop: its position loops (acceleration output; None: unknown): the slot hold drives them.
        """
        self.epoch_us = epoch_us
        self.agent.set_autopilot_loop([0], loop)
        self.output.set_loop([0], loop)
        if hover_thrust == hover_thrust:
            self.output.hover.set_param(0, hover_thrust)
        if self.cfg.lockstep:
            self.vehicle.send(MsgId.SWARMDROP_TICK, self._tick_marker(time_usec=0))
        self.vehicle.heartbeat()
        self.ap_ep.flush()
        # (VehicleLink.tick_aligned: from now on, sends go with ticks; the first may be long in
        # coming, as a fleet's clock starts once every agent is up)
        self.vehicle.tick_aligned = self.cfg.lockstep
        self.vehicle.tick_wait_s = max(TICK_WAIT_S, self.cfg.setup_timeout_s)
        self.flying = True

    # ------------------------------------------------------------------ I/O callbacks
    def on_autopilot(self) -> None:
        """The autopilot socket is readable: take everything, tick on a new position."""
        t_recv = time.perf_counter()
        v = self.vehicle
        raw, msgs = self.ap_ep.poll_split(v.RAW_IDS, 1)  # (one datagram: the loop calls again while more wait)
        for msg in msgs:
            v.handle(msg)
        for r in raw:
            v.handle_raw(*r)
        if v.new_control:
            self._maybe_tick(t_recv)
        if self.ap_ep.pending and not v.tick_aligned:
            self.ap_ep.flush()

    def on_swarm(self) -> None:
        """The swarm socket is readable (watched in lockstep only): the radio's marker may be
        the last input of a tick."""
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
            if self._settling:  # the last tick woke exchanges: they queue their next sends first
                asyncio.get_running_loop().call_soon(self._maybe_tick, t_recv)
                return
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
            unix_us = v.unix_us(ms)
            if self.cfg.lockstep and unix_us is not None and self._ended_us != unix_us:
                try:  # the tick is over all the same: the SITL's clock and the waiting exchanges go on
                    self._end_lockstep_tick(unix_us)
                except Exception:
                    log.exception("ending the failed tick failed")

    def _end_lockstep_tick(self, unix_us: int) -> None:
        """Lockstep: this tick is done, after its setpoint and published state. Its SWARMDROP_TICK
        to the SITL, then the answers and exchanges that waited for a tick's end
        (VehicleLink.tick_done); those queue what they send next before the next tick is read
        (_settling)."""
        v = self.vehicle
        v.send(MsgId.SWARMDROP_TICK, self._tick_marker(time_usec=unix_us))
        self.ap_ep.flush()
        self._ended_us = unix_us
        v.tick_done((unix_us - self.epoch_us) * 1e-6)
        self._settling = True
        asyncio.get_running_loop().call_soon(self._settled)

    def _settled(self) -> None:
        """The exchanges the last tick woke have run (they were scheduled before this)."""
        self._settling = False

    # ------------------------------------------------------------------ the control tick
    def _tick(self, t_recv: float) -> None:
        """One tick. t_recv: perf_counter() when its telemetry was read, s."""
        cfg, v, lpn = self.cfg, self.vehicle, self.vehicle.lpn
        if lpn is None:
            return
        ms = lpn.time_boot_ms
        unix_us = v.unix_us(ms)
        if unix_us is None:
            return  # ticks start after set-up, which waits for SYSTEM_TIME
        t = (unix_us - self.epoch_us) * 1e-6
        lp = lpn.values
        self.swarm.now_us = unix_us  # (the swarm link drops states stamped ahead of this)
        publish = swarm_due(unix_us, self.swarm_rate_hz, cfg.vehicle_id, self.period_us)
        k = tick_index(unix_us, self.period_us)
        # Plans on the ticks it publishes (vehicle-staggered, as swarm_due) and every plan_every-th,
        # after this tick's setpoint has left: the planner's output is a trajectory for the next
        # ticks, so planning adds nothing to the telemetry-to-setpoint latency.
        plan_now = publish or (k + cfg.vehicle_id) % cfg.plan_every == 0
        if not self.planned:
            self._plan(t, lp, ms, publish)
            plan_now = False
        sent = self._send(t, ms, lp)
        if sent and self.phase in FORMATION_PHASES:
            self.offboard.ensure()
        self.ap_ep.flush()
        now = time.perf_counter()
        c = self.counters
        c.ticks += 1
        if sent:
            c.setpoints_sent += 1
            c.latency.add(now - t_recv)
            if c.last_send_wall == c.last_send_wall:  # not NaN
                c.intervals += 1
                if now - c.last_send_wall > self.late_s:
                    c.deadline_misses += 1
            c.last_send_wall = now
        else:
            c.last_send_wall = math.nan
        if plan_now:
            self._plan(t, lp, ms, publish)
        if self.sw_ep.pending:
            self.sw_ep.flush()
        if cfg.lockstep:
            self._end_lockstep_tick(unix_us)

    def _plan(self, t: float, lp: tuple, ms: int, publish: bool) -> None:
        """Run the Agent (the planner) on this tick's inputs; its setpoint is the output stage's plan.
        The swarm socket is drained here, once per plan: only the planner reads the view.

        Args:
            t: mission time, s. lp: LOCAL_POSITION_NED (x, y, z, vx, vy, vz), local NED, m and m/s.
            ms: its time_boot_ms. publish: this tick publishes the vehicle's state.
        """
        v = self.vehicle
        self.swarm.poll()
        off = v.offset
        pos = np.array([lp[0] + off[0], lp[1] + off[1], lp[2] + off[2]])
        vel = np.array(lp[3:6], float)
        att = v.att
        q = np.array(att.values if att is not None and abs(att.time_boot_ms - ms) <= ATTITUDE_MAX_AGE_MS
                     else [np.nan] * 4)
        hb = v.hb
        released = hb is not None and hb.armed and hb.landed_state not in NOT_RELEASED
        own = OwnState(pos[None], vel[None], q[None], np.array([t]), np.array([released]),
                       np.array([v.launch_ready]))
        t_step = time.perf_counter()
        out = self.agent.step(t, own, self.view)
        self.counters.step.add(time.perf_counter() - t_step)
        if publish:
            self.swarm.publish(out.published)
            self._relay(t)
        seq = int(out.plan_seq[0])
        if seq != self.plan_seq:
            plan = self.agent.plans.plan(seq)
            log.info("swarm plan %d (%s) in force at t=%.2f s", seq, plan.kind if plan is not None else "?", t)
            self.plan_seq = seq
        if out.handed_over[0]:
            self._hand_over(t)
        if self.agent.go_decisions:
            for d in self.agent.go_decisions:
                if d.left_waiting:
                    log.warning("transit start proposed for t=%.1f s without vehicle(s) %s: heard but not assembled "
                                "%.0f s after this vehicle was (swarm.go_stall_s); they follow from where they are",
                                d.t_go_s, list(d.left_waiting), self.mission.cfg.swarm.go_stall_s)
                else:
                    log.info("transit start proposed for t=%.1f s: every vehicle heard is assembled", d.t_go_s)
            self.agent.go_decisions.clear()
        phase = Phase(int(out.phase[0]))
        if phase != self.phase:
            log.info("phase %s -> %s at t=%.2f s", self.phase.name, phase.name, t)
            self.phase = phase
        self.output.set_plan(t, out.setpoint, np.isfinite(q).all(keepdims=True), out.drive_ned_m,
                             out.acc_ff_max_mps2, out.acc_bias_ned_mps2)
        self.planned = True

    def _relay(self, t: float) -> None:
        """Pass the newest plan this vehicle holds on to its peers: on every publishing tick
        until RELAY_FAST_S after its effective time, then on every RELAY_SLOW_EVERY-th."""
        self._publishes += 1
        book = self.agent.plans
        newest = int(book.newest_seq[0])
        if newest == 0:
            return
        plan = book.plan(newest)
        if plan is None:
            return
        if t <= plan.effective_s + RELAY_FAST_S or self._publishes % RELAY_SLOW_EVERY == 0:
            self.swarm.relay(book.relay_messages(0, self.epoch_us * 1e-6, self.sw_ep.codec))

    def _hand_over(self, t: float) -> None:
        """ABORT: ask the autopilot for its own Hold (once a second until its HEARTBEAT shows it)."""
        v = self.vehicle
        if not self.handed_over:
            self.handed_over = True
            log.warning("ABORT at t=%.2f s: handing the vehicle to the autopilot's Hold; the agent commands "
                        "nothing more", t)
        hb = v.hb
        if hb is not None and v.ap.mode_of(hb.custom_mode) == Mode.HOLD:
            return
        if t - self._hold_asked_s >= HOLD_RETRY_S:
            self._hold_asked_s = t
            task = v.command_now(MavCmd.MAV_CMD_DO_SET_MODE, v.ap.set_mode_params(Mode.HOLD))
            task.add_done_callback(lambda tk: None if tk.cancelled() or tk.exception() is None else
                                   log.warning("switch to Hold after ABORT: %s (asking again)", tk.exception()))

    def _send(self, t: float, ms: int, lp: tuple) -> bool:
        """Queue this tick's setpoint: what the output stage makes of the plan now (advanced to
        t, bounded, limited, fenced; attitude output: the attitude law), in the vehicle's local
        frame.

        Args:
            t: mission time, s. ms: the tick's time_boot_ms.
            lp: LOCAL_POSITION_NED (x, y, z, vx, vy, vz), local NED.
        Returns:
            False if nothing to send or nothing sendable (never a malformed setpoint: the
            autopilot's failsafe covers a gap); the reason is logged at DEBUG and counted.
        """
        v = self.vehicle
        off = v.offset
        own_p, own_v, own_q = self._own_p, self._own_v, self._own_q
        own_p[0, 0], own_p[0, 1], own_p[0, 2] = lp[0] + off[0], lp[1] + off[1], lp[2] + off[2]
        own_v[0, 0], own_v[0, 1], own_v[0, 2] = lp[3], lp[4], lp[5]
        att = v.att
        if att is not None and abs(att.time_boot_ms - ms) <= ATTITUDE_MAX_AGE_MS:
            own_q[0] = att.values
        else:
            own_q[0] = math.nan
        o = self.output.step(t, own_p, own_v, own_q)
        send = o.send[0]
        if send == SEND_NOTHING:
            return False
        try:
            if send == SEND_ATTITUDE:
                mask, (q_d, roll_rate, pitch_rate, yaw_rate, thrust) = attitude_target_fields(
                    o.att_q_wxyz[0], float(o.thrust_field[0]))
                v.send(MsgId.SET_ATTITUDE_TARGET, self._attitude_target(
                    time_boot_ms=ms, target_system=v.target_sysid, target_component=MavComponent.MAV_COMP_ID_AUTOPILOT1,
                    type_mask=mask, q=q_d, body_roll_rate=roll_rate, body_pitch_rate=pitch_rate,
                    body_yaw_rate=yaw_rate, thrust=thrust))
            else:
                p = o.pos_ned_m[0]
                mask, (x, y, z, vx, vy, vz, afx, afy, afz, yaw, yaw_rate) = position_target_fields(
                    (p[0] - off[0], p[1] - off[1], p[2] - off[2]), o.vel_ned_mps[0], o.acc_ned_mps2[0],
                    float(o.yaw_rad[0]), float(o.yaw_rate_radps[0]))
                v.send(MsgId.SET_POSITION_TARGET_LOCAL_NED, self._position_target(
                    time_boot_ms=ms, target_system=v.target_sysid, target_component=MavComponent.MAV_COMP_ID_AUTOPILOT1,
                    coordinate_frame=MavFrame.MAV_FRAME_LOCAL_NED, type_mask=mask, x=x, y=y, z=z, vx=vx, vy=vy, vz=vz,
                    afx=afx, afy=afy, afz=afz, yaw=yaw, yaw_rate=yaw_rate))
        except ValueError as err:
            self.counters.unsendable += 1
            log.debug("setpoint not sent: %s", err)
            return False
        return True
