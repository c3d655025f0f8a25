"""A scenario's `commands:` schedule in a simulated run (issue 19; docs/swarm.md, "Swarm
commands"): the command source issues each entry at its mission time through a
`companion.commands.CommandSource` (the one the console uses), the plans travel on the
simulated radio (sim_bridge.world.plan_radio: loss, delay, relays), and each vehicle's
agent takes them into its plan book (companion.agent.Agent.plans). What happened to each
command is recorded per vehicle: when it held the whole plan, when its agent applied it.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from companion.commands import CommandError, CommandSource, PlanBook, SwarmPlan
from companion.mission import Mission
from sim_bridge.reports.record import CommandRecord
from sim_bridge.scenario import ScenarioConfig
from sim_bridge.world.plan_radio import PlanRadio

log = logging.getLogger("swarmdrop.simulate")


@dataclass
class _Issued:
    plan: SwarmPlan
    record: CommandRecord


class ScheduledCommands:
    """The schedule of one run (headless): issue, carry, apply, record.

    Args:
        cfg: the run's scenario (its `commands`, `link` and seed).
        mission: its Mission.
        rows: the run's rows of the agent's plan book (a slice of n rows).
    """

    def __init__(self, cfg: ScenarioConfig, mission: Mission, rows: slice):
        n = mission.n
        self.rows, self.n = rows, n
        self.source = CommandSource(mission, separation_m=cfg.safety.separation_m)
        self.radio = PlanRadio(cfg.link, n, cfg.seed)
        self.todo = sorted(cfg.commands, key=lambda e: e.t_s)
        self.issued: list[_Issued] = []
        self.by_seq: dict[int, SwarmPlan] = {}
        self.records: list[CommandRecord] = []
        self._t_go_known = False
        self._open: list[_Issued] = []
        """Commands some vehicle has not applied yet (checked each step)."""

    @property
    def done(self) -> bool:
        """Nothing left to issue, carry or wait for."""
        return not self.todo and not self._open

    def step(self, t_s: float, book: PlanBook, positions_ned_m: np.ndarray, t_go_s: np.ndarray) -> None:
        """Before the agent's step at t_s: issue the entries due, deliver the plan frames that
        arrived (whole plans into the book), and note which vehicles applied which plan at the
        previous step.

        Args:
            book: the agent's plan book (its rows `self.rows` are this run's vehicles).
            positions_ned_m: (n, 3) the vehicles' true positions (radio range).
            t_go_s: (n,) the transit starts the vehicles hold (the source learns the agreed one,
                as the console does from their states).
        """
        r0 = self.rows.start
        if not self._t_go_known:
            go = np.fmin.reduce(np.asarray(t_go_s, float))
            if go == go:
                self.source.set_t_go(float(go))
                self._t_go_known = True
        while self.todo and self.todo[0].t_s <= t_s + 1e-9:
            entry = self.todo.pop(0)
            try:
                plan = self.source.apply(entry)
            except CommandError as err:
                log.warning("command %s at t=%.1f s refused by the source: %s", entry.kind, entry.t_s, err)
                self.records.append(CommandRecord(0, entry.kind, entry.t_s, math.nan, str(err),
                                                  np.full(self.n, np.nan), np.full(self.n, np.nan)))
                continue
            rec = CommandRecord(plan.seq, entry.kind, entry.t_s, plan.effective_s, "", np.full(self.n, np.nan),
                                np.full(self.n, np.nan))
            item = _Issued(plan, rec)
            self.issued.append(item)
            self._open.append(item)
            self.records.append(rec)
            self.by_seq[plan.seq] = plan
            self.radio.issue(t_s, plan.seq)
        newest = book.newest_seq[self.rows]
        for rows, seq in self.radio.step(t_s, positions_ned_m, newest):
            book.receive(rows + r0, self.by_seq[seq])
        if self._open:
            held = book.plan_seq[self.rows]
            newest = book.newest_seq[self.rows]
            still = []
            for item in self._open:
                rec, seq = item.record, item.plan.seq
                fresh = np.isnan(rec.held_s) & (newest >= seq)
                rec.held_s[fresh] = t_s
                fresh = np.isnan(rec.applied_s) & (held >= seq)
                rec.applied_s[fresh] = t_s
                if np.isnan(rec.applied_s).any():
                    still.append(item)
            self._open = still

    def reference_ned_m(self, t_s: float) -> np.ndarray:
        """(n, 3) where the source's current plan puts every vehicle at t_s (what a vehicle that
        heard every plan flies; NaN: a vehicle with no reference)."""
        return self.source.reference(t_s)[0]
