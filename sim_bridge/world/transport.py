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

import dataclasses
import math
from dataclasses import dataclass as std_dataclass
from dataclasses import field
from typing import overload

import numpy as np
from numba import njit
from pydantic import Field
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.swarm import SwarmStates, SwarmView


@std_dataclass(frozen=True)
class AgeSummary:
    """Ages of neighbour states when delivered, s (None when nothing was delivered)."""

    count: int = 0
    mean: float | None = None
    p50: float | None = None
    p90: float | None = None
    p99: float | None = None
    max: float | None = None


@std_dataclass(frozen=True)
class MeanMax:
    """Mean and maximum of a per-vehicle figure (units those of the field that holds it);
    None when nothing was measured."""

    mean: float | None = None
    max: float | None = None


@std_dataclass(frozen=True)
class LinkStats:
    """Neighbour transport of one run: the headless transport or the SITL's radio medium.

    Fields a transport does not measure are None (the headless transport has no bytes,
    the radio medium no configured-but-unused kind).
    """

    copies_sent: int = 0
    """Copies of published states addressed to receivers (one per sender-receiver pair)."""
    copies_delivered: int = 0
    delivered_fraction: float | None = None
    age_at_delivery_s: AgeSummary = field(default_factory=AgeSummary)
    kind: str | None = None
    loss: float | None = None
    delay_s: float | None = None
    jitter_s: float | None = None
    bytes_per_s_per_vehicle: MeanMax | None = None
    states_received: int | None = None
    copies_lost: int | None = None
    bad_frames: int | None = None
    foreign_frames: int | None = None

    @classmethod
    def from_json(cls, d: dict | None) -> "LinkStats":
        """Read the dict run.json stores (older runs may lack fields)."""
        d = dict(d or {})
        d["age_at_delivery_s"] = AgeSummary(**d.get("age_at_delivery_s", {}))
        if d.get("bytes_per_s_per_vehicle") is not None:
            d["bytes_per_s_per_vehicle"] = MeanMax(**d["bytes_per_s_per_vehicle"])
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


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


@overload
def _splitmix(x: np.uint64) -> np.uint64: ...
@overload
def _splitmix(x: np.ndarray) -> np.ndarray: ...
def _splitmix(x: np.ndarray | np.uint64) -> np.ndarray | np.uint64:
    """SplitMix64's finaliser, elementwise on uint64 (a scalar key or an array)."""
    x = (x + np.uint64(0x9E3779B97F4A7C15)) & _MASK64
    x = ((x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & _MASK64
    x = ((x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & _MASK64
    return x ^ (x >> np.uint64(31))


def hashed_uniform(seed: int, sender: np.ndarray, stamp_us: np.ndarray, receiver: np.ndarray,
                   stream: int) -> np.ndarray:
    """Uniform [0, 1) draws keyed by (seed, sender, stamp, receiver, stream); broadcasting."""
    x: np.ndarray | np.uint64  # (the scalar key, then the broadcast array)
    with np.errstate(over="ignore"):
        x = _splitmix(np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ np.uint64(stream * 0x632BE59BD9B4E019 & 0xFFFFFFFFFFFFFFFF))
        x = _splitmix(x ^ np.asarray(sender, dtype=np.uint64))
        x = _splitmix(x ^ np.asarray(stamp_us, dtype=np.int64).astype(np.uint64))
        x = _splitmix(x ^ np.asarray(receiver, dtype=np.uint64))
    return (x >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


@njit(cache=True)
def _splitmix_nb(x):
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit(cache=True)
def _fates(seed_lo, stream_keys, sender, stamp_us, n, loss, delay_s, jitter_s, send_s, dist_ok):
    """The loop of RadioModel.deliveries (compiled: it runs for every published state):
    hashed_uniform's draws, bit for bit, for every (message, receiver) pair."""
    k = sender.shape[0]
    msg = np.empty(k * n, np.int64)
    rcv = np.empty(k * n, np.int64)
    when = np.empty(k * n)
    m = 0
    b_loss = _splitmix_nb(seed_lo ^ stream_keys[0])
    b_jit = _splitmix_nb(seed_lo ^ stream_keys[1])
    for i in range(k):
        st = np.uint64(stamp_us[i])
        xs_l = _splitmix_nb(_splitmix_nb(b_loss ^ np.uint64(sender[i])) ^ st)
        xs_j = _splitmix_nb(_splitmix_nb(b_jit ^ np.uint64(sender[i])) ^ st)
        for r in range(n):
            if r == sender[i] or not dist_ok[i, r]:
                continue
            if loss > 0.0:
                u = np.float64(_splitmix_nb(xs_l ^ np.uint64(r)) >> np.uint64(11)) * 2.0 ** -53
                if u < loss:
                    continue
            w = send_s + delay_s
            if jitter_s > 0.0:
                w += jitter_s * (np.float64(_splitmix_nb(xs_j ^ np.uint64(r)) >> np.uint64(11)) * 2.0 ** -53)
            msg[m], rcv[m], when[m] = i, r, w
            m += 1
    return msg[:m], rcv[:m], when[:m]


class RadioModel:
    """Fate of each copy of a published state: lost, or delivered at a time.

    Args:
        cfg: the link.
        seed: run seed (the same seed gives the same losses in every simulator).
    """

    def __init__(self, cfg: LinkConfig, seed: int):
        self.cfg = cfg
        self.seed = int(seed)
        # hashed_uniform's key material for streams 1 (loss) and 2 (jitter), precomputed
        self._seed_lo = np.uint64(self.seed & 0xFFFFFFFFFFFFFFFF)
        self._stream_keys = np.array([s * 0x632BE59BD9B4E019 & 0xFFFFFFFFFFFFFFFF for s in (1, 2)], np.uint64)
        self._all_ok = np.ones((0, 0), np.bool_)

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
        sender = np.asarray(sender, np.int64)
        if c.range_m is not None:
            d = np.linalg.norm(np.asarray(sender_pos)[:, None, :] - np.asarray(receiver_pos)[None], axis=2)
            dist_ok = d <= c.range_m
        else:
            dist_ok = self._everyone(k, n)
        stamp_us = np.round(np.asarray(stamp_s, float) * 1e6).astype(np.int64)
        return _fates(self._seed_lo, self._stream_keys, sender, stamp_us, n, c.loss if lossy else 0.0,
                      c.delay_s if lossy else 0.0, c.jitter_s if lossy else 0.0, float(send_s), dist_ok)

    def _everyone(self, k: int, n: int) -> np.ndarray:
        if self._all_ok.shape != (k, n):
            self._all_ok = np.ones((k, n), np.bool_)
        return self._all_ok


class AgeHistogram:
    """Distribution of ages in 1 ms bins up to 10 s (bounded memory for long runs)."""

    BIN_S = 1e-3
    BINS = 10000

    def __init__(self):
        self.counts = np.zeros(self.BINS + 1, dtype=np.int64)  # last bin: >= 10 s
        self.total_s = 0.0

    def add(self, ages_s: np.ndarray, weight: int = 1) -> None:
        a = np.asarray(ages_s, float)
        if len(a) <= 64:  # the usual handful per tick: plain Python beats numpy's per-call cost
            counts, top = self.counts, self.BINS
            for x in a.tolist():
                b = math.floor(x / self.BIN_S + 1e-6) if x < top * self.BIN_S else top
                counts[b if b > 0 else 0] += weight
        else:
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
    """Copies are lost, delayed and jittered as RadioModel decides (seeded).

    Copies wait in chunks, one per publish call, each with its earliest and latest
    delivery time: with a fixed delay a chunk is delivered whole, without selecting
    rows (the common case costs one view.receive per chunk, not a copy per field).
    """

    def __init__(self, n: int, cfg: LinkConfig, seed: int):
        super().__init__(n)
        self.radio = RadioModel(cfg, seed)
        self._chunks: list[tuple[float, float, np.ndarray, np.ndarray, SwarmStates]] = []
        """(earliest, latest delivery time, delivery times, receiver rows, states) per publish call."""

    def publish(self, t_s, states, positions_ned_m) -> None:
        if not len(states):
            return
        pos = np.asarray(positions_ned_m, float)
        ids = np.asarray(states.vehicle_id)
        msg, rcv, when = self.radio.deliveries(ids, np.asarray(states.stamp_s), t_s, pos[ids], pos)
        self.sent += len(states) * (self.n - 1)
        if len(msg):
            self._chunks.append((float(when.min()), float(when.max()), when, rcv, states.select(msg)))

    def deliver(self, t_s, view) -> None:
        t = t_s + 1e-9
        kept = []
        for chunk in self._chunks:
            first, last, when, rows, st = chunk
            if first > t:
                kept.append(chunk)
                continue
            if last > t:  # partly due (jitter): split it
                due = when <= t
                keep = ~due
                kept.append((float(when[keep].min()), last, when[keep], rows[keep], st.select(keep)))
                rows, st = rows[due], st.select(due)
            view.receive(rows, st)
            self.delivered += len(rows)
            self._ages.add(t_s - np.asarray(st.stamp_s))
        self._chunks = kept


def make_transport(cfg: LinkConfig, n: int, seed: int) -> NeighbourTransport:
    """The transport the config asks for; seed is the run's seed."""
    if cfg.kind == "perfect":
        return PerfectTransport(n)
    return LossyTransport(n, cfg, seed)


