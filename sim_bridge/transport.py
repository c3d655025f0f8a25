"""Neighbour transports for the headless runner, and the radio model they share
with the SITL's radio medium.

A `NeighbourTransport` carries the states agents publish (companion.swarm) to
the other vehicles' views. `PerfectTransport` delivers every state at once to
everyone (the paper's assumption); `LossyTransport` drops, delays and jitters
each (sender, receiver) copy as `RadioModel` decides. RadioModel's draws are a
counter-based hash of (seed, sender, stamp, receiver), not a stream: the same
message gets the same fate whatever order messages are handled in, which keeps
lockstep SITL runs bit-identical (sim_bridge.sitl.medium) and makes a headless
run and a SITL run with one seed lose the same messages.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.swarm import SwarmStates, SwarmView
from sim_bridge.results import AgeSummary, LinkStats

_MASK64 = np.uint64(0xFFFFFFFFFFFFFFFF)


@dataclass(config=STRICT)
class LinkConfig:
    """The swarm radio: what happens to each copy of a state on its way to one receiver."""

    kind: str = Field(default="perfect", pattern="^(perfect|lossy)$")
    loss: float = Field(default=0.0, ge=0.0, le=1.0)
    """Probability that a copy is lost."""
    delay_s: float = Field(default=0.0, ge=0.0, le=10.0)
    """Fixed latency of every copy, s."""
    jitter_s: float = Field(default=0.0, ge=0.0, le=10.0)
    """Extra latency drawn uniformly in [0, jitter_s]; copies can overtake each other."""
    range_m: float | None = Field(default=None, gt=0)
    """Receivers further than this from the sender hear nothing (None: everyone)."""


def _splitmix(x: np.ndarray) -> np.ndarray:
    x = (x + np.uint64(0x9E3779B97F4A7C15)) & _MASK64
    x = ((x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & _MASK64
    x = ((x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & _MASK64
    return x ^ (x >> np.uint64(31))


def hashed_uniform(seed: int, sender: np.ndarray, stamp_us: np.ndarray, receiver: np.ndarray,
                   stream: int) -> np.ndarray:
    """Uniform [0, 1) draws keyed by (seed, sender, stamp, receiver, stream); broadcasting."""
    with np.errstate(over="ignore"):
        x = _splitmix(np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ np.uint64(stream * 0x632BE59BD9B4E019 & 0xFFFFFFFFFFFFFFFF))
        x = _splitmix(x ^ np.asarray(sender, dtype=np.uint64))
        x = _splitmix(x ^ np.asarray(stamp_us, dtype=np.int64).astype(np.uint64))
        x = _splitmix(x ^ np.asarray(receiver, dtype=np.uint64))
    return (x >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


class RadioModel:
    """Fate of each copy of a published state: lost, or delivered at a time.

    Args:
        cfg: the link.
        seed: run seed (the same seed gives the same losses in every simulator).
    """

    def __init__(self, cfg: LinkConfig, seed: int):
        self.cfg = cfg
        self.seed = int(seed)

    def deliveries(self, sender: np.ndarray, stamp_s: np.ndarray, send_s: float, sender_pos: np.ndarray,
                   receiver_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Who hears each of k states sent at send_s, and when.

        Args:
            sender: (k,) vehicle ids; stamp_s: (k,) their stamps (the hash key).
            sender_pos: (k, 3) where the senders are; receiver_pos: (N, 3) every vehicle
                (NaN rows: out of range of everyone).
        Returns:
            (message index (d,), receiver id (d,), delivery time (d,)) of the copies
            that arrive; a vehicle never receives its own state.
        """
        k, n = len(sender), len(receiver_pos)
        c = self.cfg
        lossy = c.kind == "lossy"
        msg, rcv = np.meshgrid(np.arange(k), np.arange(n), indexing="ij")
        keep = rcv != np.asarray(sender)[:, None]
        if c.range_m is not None:
            d = np.linalg.norm(np.asarray(sender_pos)[:, None, :] - np.asarray(receiver_pos)[None], axis=2)
            keep &= d <= c.range_m
        stamp_us = np.round(np.asarray(stamp_s, float) * 1e6)[:, None]
        if lossy and c.loss > 0:
            keep &= hashed_uniform(self.seed, np.asarray(sender)[:, None], stamp_us, rcv, 1) >= c.loss
        when = np.full((k, n), send_s + (c.delay_s if lossy else 0.0))
        if lossy and c.jitter_s > 0:
            when += c.jitter_s * hashed_uniform(self.seed, np.asarray(sender)[:, None], stamp_us, rcv, 2)
        return msg[keep], rcv[keep], when[keep]


class AgeHistogram:
    """Distribution of ages in 1 ms bins up to 10 s (bounded memory for long runs)."""

    BIN_S = 1e-3
    BINS = 10000

    def __init__(self):
        self.counts = np.zeros(self.BINS + 1, dtype=np.int64)  # last bin: >= 10 s
        self.total_s = 0.0

    def add(self, ages_s: np.ndarray, weight: int = 1) -> None:
        a = np.asarray(ages_s, float)
        idx = np.clip(np.floor(a / self.BIN_S + 1e-6), 0, self.BINS).astype(np.int64)
        np.add.at(self.counts, idx, weight)
        self.total_s += float(a.sum()) * weight

    def summary(self) -> AgeSummary:
        n = int(self.counts.sum())
        if n == 0:
            return AgeSummary()
        cum = np.cumsum(self.counts)
        pct = {f"p{p}": float(np.searchsorted(cum, p / 100.0 * n) * self.BIN_S) for p in (50, 90, 99)}
        return AgeSummary(count=n, mean=self.total_s / n, **pct,
                          max=float(np.flatnonzero(self.counts)[-1] * self.BIN_S))


class NeighbourTransport:
    """Carries published states into receivers' views. Subclasses decide the fate."""

    def __init__(self, n: int):
        self.n = n
        self.sent = 0
        self.delivered = 0
        self._ages = AgeHistogram()

    def publish(self, t_s: float, states: SwarmStates, positions_ned_m: np.ndarray) -> None:
        """States published at t_s; positions_ned_m (N, 3): where every vehicle is (for range)."""
        raise NotImplementedError

    def deliver(self, t_s: float, view: SwarmView) -> None:
        """Put every copy due by t_s into view (receiver row = vehicle id)."""
        raise NotImplementedError

    def stats(self) -> LinkStats:
        return LinkStats(copies_sent=self.sent, copies_delivered=self.delivered,
                         delivered_fraction=self.delivered / self.sent if self.sent else None,
                         age_at_delivery_s=self._ages.summary())


class PerfectTransport(NeighbourTransport):
    """Every state reaches every other vehicle at once (zero age)."""

    def __init__(self, n: int):
        super().__init__(n)
        self._pending: SwarmStates | None = None

    def publish(self, t_s, states, positions_ned_m) -> None:
        self._pending = states
        self.sent += len(states) * (self.n - 1)

    def deliver(self, t_s, view) -> None:
        st, self._pending = self._pending, None
        if st is None or not len(st):
            return
        view.receive_all(st)
        self.delivered += len(st) * (self.n - 1)
        self._ages.add(t_s - np.asarray(st.stamp_s), self.n - 1)


class LossyTransport(NeighbourTransport):
    """Copies are lost, delayed and jittered as RadioModel decides (seeded)."""

    def __init__(self, n: int, cfg: LinkConfig, seed: int):
        super().__init__(n)
        self.radio = RadioModel(cfg, seed)
        self._when = np.zeros(0)
        self._rows = np.zeros(0, dtype=np.int64)
        self._states: SwarmStates | None = None

    def publish(self, t_s, states, positions_ned_m) -> None:
        if not len(states):
            return
        pos = np.asarray(positions_ned_m, float)
        msg, rcv, when = self.radio.deliveries(np.asarray(states.vehicle_id), np.asarray(states.stamp_s), t_s,
                                               pos[np.asarray(states.vehicle_id)], pos)
        self.sent += len(states) * (self.n - 1)
        copies = states.select(msg)
        self._when = np.concatenate([self._when, when])
        self._rows = np.concatenate([self._rows, rcv])
        self._states = copies if self._states is None else SwarmStates(
            *(np.concatenate([getattr(self._states, f), getattr(copies, f)]) for f in SwarmStates.__dataclass_fields__))

    def deliver(self, t_s, view) -> None:
        if self._states is None or not len(self._when):
            return
        due = self._when <= t_s + 1e-9
        if not due.any():
            return
        st = self._states.select(due)
        view.receive(self._rows[due], st)
        self.delivered += int(due.sum())
        self._ages.add(t_s - np.asarray(st.stamp_s))
        keep = ~due
        self._when, self._rows, self._states = self._when[keep], self._rows[keep], self._states.select(keep)


def make_transport(cfg: LinkConfig, n: int, seed: int) -> NeighbourTransport:
    """The transport the config asks for; seed is the run's seed."""
    if cfg.kind == "perfect":
        return PerfectTransport(n)
    return LossyTransport(n, cfg, seed)


