"""A scenario's `commands:` schedule in the SITL (issue 19; docs/swarm.md, "Swarm commands";
docs/sitl.md, "Swarm commands"): the fleet's `swarmdrop run` flies the schedule the headless
run flies (sim_bridge.runs.commands), through real agents.

The SITL has the scenario, so it is the command source: a `companion.commands.CommandSource`
(the console's, with the scenario's separation) issues each entry at its mission time on the
SITL's clock (simulation time; the agents' mission time too, the fleet's epoch being a whole
hour), and the plan's frames (`plan_messages`) go into the swarm radio as a ground station
(sysid 255, MAV_COMP_ID_MISSIONPLANNER), signed when the SITL signs, on the radio's faults
(sim_bridge.sitl.medium: the RadioModel of the states, the plan stream's hash), repeated
REPEATS times REPEAT_S apart as the console repeats (a newer plan stops the older one's
repeats). The source learns the agreed transit start from the vehicles' states, as the
console does. Everything runs on simulation time: a lockstep run repeats exactly.

What happened to each command is recorded per vehicle from what the radio sees
(`PlanListener`): `held_s`, when the radio had delivered every frame of the plan (or of a
newer one) to the vehicle; `applied_s`, the stamp of its first SWARMDROP_STATE whose plan_seq
is the command's or newer. The recorder judges each vehicle against the source's reference
(`reference_ned_m`: what a vehicle that heard every plan on time flies).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from companion.commands import CommandError, CommandSource, plan_messages
from companion.link.enums import MavComponent
from companion.link.wire import Codec
from companion.mission import Mission
from sim_bridge.reports.record import CommandRecord
from sim_bridge.scenario import ScenarioConfig
from sim_bridge.sitl.medium import Medium

log = logging.getLogger("swarmdrop.sitl")

REPEATS = 3
REPEAT_S = 0.3
"""The source sends every plan REPEATS times, REPEAT_S (simulated) apart: the console's
repeats (swarmdrop.console.commands)."""
SOURCE_SYSID = 255
SOURCE_COMPID = int(MavComponent.MAV_COMP_ID_MISSIONPLANNER)
SOURCE_LINK_ID = 201
"""The signing link id of the SITL's command source (the radio's marker is 200)."""


class SitlCommands:
    """The scenario's schedule, issued into the SITL's radio and recorded (module docstring).

    Args:
        scenario: the scenario (its `commands`, `safety.separation_m`).
        mission: its Mission.
        medium: the swarm radio (this object becomes its plan listener).
        epoch_unix_s: Unix time of simulation time 0 (the plan's effective time on the wire).
        codec: the swarmdrop codec (encodes the frames).
        sign: signs one encoded frame (None: unsigned).
    """

    def __init__(self, scenario: ScenarioConfig, mission: Mission, medium: Medium, epoch_unix_s: float,
                 codec: Codec, sign: Callable[[bytes], bytes] | None = None):
        self.n = n = mission.n
        self.source = CommandSource(mission, separation_m=scenario.safety.separation_m)
        self.medium = medium
        medium.plan_listener = self
        self.epoch_unix_s = epoch_unix_s
        self.codec = codec
        self.sign = sign
        self.todo = sorted(scenario.commands, key=lambda e: e.t_s)
        self.records: list[CommandRecord] = []
        """Every command of the schedule, in the order issued (refused ones with seq 0)."""
        self._by_seq: dict[int, CommandRecord] = {}
        self._t_go_known = False
        self._repeats: list[float] = []
        """Simulated times of the newest plan's repeats still to send."""
        self._messages: list = []
        self._seq = 0
        """The newest plan's seq (what the repeats send)."""
        self._frame_seq = 0
        self._parts = medium.plan_parts
        self._got: dict[int, np.ndarray] = {}
        """seq -> (n, parts) bool: the frames the radio has delivered to each vehicle."""
        self._held_seq = np.zeros(n, np.int64)
        """The newest of the source's plans each vehicle has had whole."""

    # ------------------------------------------------------------------ the schedule
    def step(self, sim_s: float) -> None:
        """At a SITL tick, before the radio schedules: learn the transit start, issue the
        entries due, send the repeats due."""
        if not self._t_go_known:
            go = np.fmin.reduce(self.medium.t_go_s)
            if go == go:
                self.source.set_t_go(float(go))
                self._t_go_known = True
        while self.todo and self.todo[0].t_s <= sim_s + 1e-9:
            self._issue(sim_s, self.todo.pop(0))
        while self._repeats and self._repeats[0] <= sim_s + 1e-9:
            self._repeats.pop(0)
            self._send()

    def _issue(self, sim_s: float, entry) -> None:
        try:
            plan = self.source.apply(entry)
        except CommandError as err:
            log.warning("command %s at t=%.1f s refused by the source: %s", entry.kind, entry.t_s, err)
            self.records.append(CommandRecord(0, entry.kind, entry.t_s, math.nan, str(err), np.full(self.n, np.nan),
                                              np.full(self.n, np.nan)))
            return
        rec = CommandRecord(plan.seq, entry.kind, entry.t_s, plan.effective_s, "", np.full(self.n, np.nan),
                            np.full(self.n, np.nan))
        self.records.append(rec)
        self._by_seq[plan.seq] = rec
        self._got[plan.seq] = np.zeros((self.n, self._parts), bool)
        print(f"swarm command {entry.kind} at t={sim_s:.2f} s: plan {plan.seq}, effective at "
              f"t={plan.effective_s:.2f} s", flush=True)
        self._messages = plan_messages(plan, self.epoch_unix_s, self.codec)
        self._seq = plan.seq
        self._repeats = [sim_s + k * REPEAT_S for k in range(1, REPEATS)]
        self._send()

    def _send(self) -> None:
        frames = []
        for msgid, values in self._messages:
            frame = self.codec.encode_fields(msgid, values, SOURCE_SYSID, SOURCE_COMPID, self._frame_seq)
            self._frame_seq = (self._frame_seq + 1) & 0xFF
            frames.append(self.sign(frame) if self.sign is not None else frame)
        self.medium.send_plan(frames, self._seq)

    # ------------------------------------------------------------------ what the radio saw
    def plan_delivered(self, seq: int, part: int, receivers: np.ndarray, sim_s: float) -> None:
        """(PlanListener) A frame of plan seq reached these vehicles: a vehicle holds the plan
        once it has every frame (from any mix of senders), and with it every older plan."""
        got = self._got.get(seq)
        if got is None:
            return  # (not one of this source's plans)
        got[receivers, part] = True
        whole = receivers[got[receivers].all(axis=1) & (self._held_seq[receivers] < seq)]
        if not len(whole):
            return
        self._held_seq[whole] = seq
        for s, rec in self._by_seq.items():
            if s <= seq:
                fresh = whole[np.isnan(rec.held_s[whole])]
                rec.held_s[fresh] = sim_s

    def state_plan_seq(self, k: int, stamp_s: float, plan_seq: int) -> None:
        """(PlanListener) Vehicle k's states now carry plan_seq: it applied every plan up to it."""
        for s, rec in self._by_seq.items():
            if s <= plan_seq and math.isnan(rec.applied_s[k]):
                rec.applied_s[k] = stamp_s

    # ------------------------------------------------------------------ for the recorder
    def settled(self, counted: np.ndarray | None = None) -> bool:
        """Nothing left to issue, and every counted vehicle (None: every vehicle) has applied
        every plan issued: a run with a schedule does not end before it has."""
        if self.todo:
            return False
        c = slice(None) if counted is None else np.asarray(counted, bool)
        return all(not np.isnan(rec.applied_s[c]).any() for rec in self._by_seq.values())

    def reference_ned_m(self, t_s: float) -> np.ndarray:
        """(n, 3) where the source's current plan puts every vehicle at t_s (what a vehicle
        that heard every plan on time flies; NaN: a vehicle with no reference)."""
        return self.source.reference(t_s)[0]
