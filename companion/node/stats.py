"""The statistics `swarmdrop agent --stats` writes: latency, planner time, deadline misses,
CPU, link and signing counters, and identity (docs/companion.md).

`AgentStats` is a frozen snapshot, a tree of dataclasses that mirrors the JSON file key for
key (`to_json`). The fleet harness reads the files back with `from_json`/`load`, which take
whatever an agent managed to write: a missing file, a missing section or a field that does
not parse gives that section's empty value (None, 0 or NaN), never an error, because an
agent that crashed early must not break the fleet's report.

`TickCounters` is what the tick path counts as it goes (mutable, cheap to update); `collect`
turns it and the node's link counters into an AgentStats.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from companion.link.signing import SigningCounters

if TYPE_CHECKING:
    from companion.node.runner import AgentNode
    from companion.node.streams import UnreadStreams

LAT_BIN_US, LAT_BINS = 50, 1000
"""Latency histogram in the statistics: 50 µs bins up to 50 ms (a fleet pools them)."""
FINE_BIN_US, FINE_BINS = 10, 5000
"""What the agent counts durations in: 10 µs bins up to 50 ms, the last one also holding
everything beyond (the file's histogram sums them five by five)."""
SIGNED_LINKS = ("autopilot", "swarm")
"""The links whose signing counters the statistics carry, in file order."""

T = TypeVar("T")


def histogram_percentiles(counts, bin_us: float, percents, max_ms: float | None = None) -> list[float]:
    """Percentiles of durations counted in a histogram, ms: the upper edge of the bin that
    holds each (conservative: at most one bin above the exact value). The agent's own figures
    and the fleet's pooled ones (sim_bridge/runs/fleet_report.py) both come from here.

    Args:
        counts: (B,) counts per bin, bin b covering [b, b + 1) * bin_us µs, the last one also
            everything beyond. percents: in [0, 100].
        max_ms: the exact largest duration, if known: no percentile exceeds it, and one in
            the last bin (past its lower edge, unbounded) is it.
    Returns:
        One value per percent, ms ([] if counts is empty or all zero).
    """
    cum = np.cumsum(np.asarray(counts, dtype=np.int64))
    if not len(cum) or cum[-1] == 0:
        return []
    idx = np.minimum(np.searchsorted(cum, np.asarray(percents, dtype=float) / 100.0 * cum[-1]), len(cum) - 1)
    out = (idx + 1) * (bin_us / 1000.0)
    if max_ms is not None:
        out = np.where(idx == len(cum) - 1, max_ms, np.minimum(out, max_ms))
    return out.tolist()


class DurationHistogram:
    """Durations counted as they come, in FINE_BIN_US bins, and their maximum: O(1) to add
    (one tick's cost is an index and an increment) and O(bins) to summarise, however long the
    flight, so writing the statistics every few seconds costs the same after hours as after
    seconds. Percentiles cover the whole flight."""

    __slots__ = ("counts", "max_s", "n")

    def __init__(self) -> None:
        self.counts = [0] * FINE_BINS
        self.max_s = 0.0
        self.n = 0

    def add(self, dt_s: float) -> None:
        """Count one duration, s (negative counts as 0, beyond the last bin in the last)."""
        b = int(dt_s * (1e6 / FINE_BIN_US))
        if b >= FINE_BINS:
            b = FINE_BINS - 1
        elif b < 0:
            b = 0
        self.counts[b] += 1
        if dt_s > self.max_s:
            self.max_s = dt_s
        self.n += 1

    def percentiles_ms(self, percents) -> list[float]:
        """histogram_percentiles of what was counted, ms, none above the largest ([] if
        nothing was)."""
        return histogram_percentiles(self.counts, FINE_BIN_US, percents, self.max_s * 1e3)

    def coarse(self, bin_us: int, bins: int) -> tuple[int, ...]:
        """The counts in bins of bin_us (a multiple of FINE_BIN_US), `bins` of them, the last
        also holding everything beyond.

        Raises:
            ValueError: bin_us not a multiple of FINE_BIN_US, or the bins reach past the fine ones.
        """
        k = bin_us // FINE_BIN_US
        if k < 1 or bins < 1 or k * FINE_BIN_US != bin_us or k * bins > FINE_BINS:
            raise ValueError(f"{bins} bins of {bin_us} us from {FINE_BINS} of {FINE_BIN_US} us")
        c = np.asarray(self.counts, dtype=np.int64)
        out = c[:k * bins].reshape(bins, k).sum(axis=1)
        out[-1] += c[k * bins:].sum()
        return tuple(out.tolist())


class TickCounters:
    """What the tick path counts, updated on every tick (attributes and two histograms: no
    allocation)."""

    __slots__ = ("ticks", "setpoints_sent", "unsendable", "deadline_misses", "intervals", "last_send_wall",
                 "latency", "step")

    def __init__(self) -> None:
        self.ticks = 0
        """Control ticks run (one per new LOCAL_POSITION_NED while flying)."""
        self.setpoints_sent = 0
        self.unsendable = 0
        """Setpoints not sent because they could not be encoded (the autopilot's failsafe covers the gap)."""
        self.deadline_misses = 0
        """Intervals between consecutive setpoints longer than the tick path's late_s."""
        self.intervals = 0
        """Intervals between consecutive setpoints measured (a tick without one restarts the count)."""
        self.last_send_wall = math.nan
        """perf_counter() of the last setpoint sent, s; NaN after a tick that sent none."""
        self.latency = DurationHistogram()
        """Telemetry received -> setpoint sent, per tick that sent one."""
        self.step = DurationHistogram()
        """Wall time of each Agent.step."""


# ----------------------------------------------------------------------------- tolerant readers
def _is_num(value: Any) -> bool:
    """An int or a float (JSON numbers; bool is not one)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _section(data: Any, key: str) -> Mapping[str, Any]:
    """data[key] if it is a mapping, else {} (a section the agent never wrote)."""
    value = data.get(key) if isinstance(data, Mapping) else None
    return value if isinstance(value, Mapping) else {}


def _num(data: Mapping[str, Any], key: str, kind: Callable[[Any], T], default: T) -> T:
    """data[key] converted by kind (int or float), default when absent, not a number, or not
    convertible (int of NaN)."""
    value = data.get(key)
    if not _is_num(value):
        return default
    try:
        return kind(value)
    except (ValueError, OverflowError):  # int(NaN), int(inf)
        return default


def _opt_float(data: Mapping[str, Any], key: str) -> float | None:
    """None when absent or null (not measured), else the number (NaN if it is none)."""
    return None if data.get(key) is None else _num(data, key, float, math.nan)


def _str_list(data: Mapping[str, Any], key: str) -> list[str]:
    """A list of strings (anything else: empty)."""
    v = data.get(key)
    return [x for x in v if isinstance(x, str)] if isinstance(v, list) else []


def _opt_str(data: Mapping[str, Any], key: str) -> str | None:
    value = data.get(key)
    return value if isinstance(value, str) else None


def _all_floats(data: Mapping[str, Any], keys: tuple[str, ...]) -> dict[str, float] | None:
    """{key: float} for every key, or None if any is missing or not a number."""
    if not all(_is_num(data.get(k)) for k in keys):
        return None
    return {k: float(data[k]) for k in keys}


# ----------------------------------------------------------------------------- the tree
@dataclass(frozen=True)
class TickLatency:
    """Telemetry received -> setpoint sent on the ticks that sent one, ms, over the whole
    flight (percentiles: histogram_percentiles of FINE_BIN_US bins; max exact). File: "latency_ms"."""

    p50: float
    p90: float
    p99: float
    max: float

    def to_json(self) -> dict[str, float]:
        return {"p50": self.p50, "p90": self.p90, "p99": self.p99, "max": self.max}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> TickLatency | None:
        """None unless every percentile is there (an agent that sent no setpoint writes {})."""
        v = _all_floats(data, ("p50", "p90", "p99", "max"))
        return None if v is None else cls(**v)


@dataclass(frozen=True)
class LatencyHistogram:
    """The same latencies binned (a fleet pools them into fleet-wide percentiles). File: "latency_hist"."""

    bin_us: int
    """Bin width, µs."""
    counts: tuple[int, ...]
    """Ticks per bin; the last bin also holds everything beyond it."""

    def to_json(self) -> dict[str, Any]:
        return {"bin_us": self.bin_us, "counts": list(self.counts)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> LatencyHistogram | None:
        """None without a bin width and a list of integer counts."""
        counts = data.get("counts")
        bin_us = _num(data, "bin_us", int, 0)
        if bin_us <= 0 or not isinstance(counts, list) or not all(isinstance(c, int) for c in counts):
            return None
        return cls(bin_us, tuple(counts))


@dataclass(frozen=True)
class StepTime:
    """Wall time of Agent.step (the planner), ms, over the whole flight (histogram_percentiles
    of FINE_BIN_US bins). File: "agent_step_ms"."""

    p50: float
    p99: float

    def to_json(self) -> dict[str, float]:
        return {"p50": self.p50, "p99": self.p99}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> StepTime | None:
        v = _all_floats(data, ("p50", "p99"))
        return None if v is None else cls(**v)


@dataclass(frozen=True)
class AutopilotLinkStats:
    """The link to the agent's own autopilot. File: "autopilot"."""

    dialect: str | None = None
    """The autopilot's dialect ("px4", "ardupilot"), None if no HEARTBEAT of ours came."""
    bad_frames: int = 0
    """Frames that did not decode (CRC, truncated, bad flags)."""
    unknown_messages: int = 0
    """Well-formed frames of messages the dialect does not define."""
    foreign: int = 0
    """Messages from another system or component than our autopilot (ignored)."""
    dropped_nonfinite: int = 0
    """Messages of ours with values out of range or not finite (ignored)."""
    bytes_in: int = 0
    bytes_out: int = 0
    stranger_drops: int = 0
    """Frames claiming our autopilot's ids from another address while it talks (udpin,
    signing off: companion.link.endpoints, peer_ids): dropped."""
    streams_stopped: list[str] = dataclasses.field(default_factory=list)
    """Streams the autopilot stopped on this link at the agent's request (--stop-unread-streams)."""
    streams_not_stopped: list[str] = dataclasses.field(default_factory=list)
    """Unread messages whose stop it refused or did not answer (replies, or not streams)."""

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> AutopilotLinkStats:
        counts: dict[str, Any] = {f.name: _num(data, f.name, int, 0) for f in dataclasses.fields(cls)
                                  if f.type in ("int", int)}
        return cls(_opt_str(data, "dialect"), streams_stopped=_str_list(data, "streams_stopped"),
                   streams_not_stopped=_str_list(data, "streams_not_stopped"), **counts)


@dataclass(frozen=True)
class SwarmLinkStats:
    """The swarm link (SwarmLink). File: "swarm"."""

    states_in: int = 0
    """Neighbour states that passed the input rules (companion.node.swarmlink)."""
    rejected: int = 0
    """States dropped by them (wrong sender, slot, stamp, phase, or before the clock was known)."""
    future: int = 0
    """States (and radio tick markers) dropped for a stamp over 0.5 s ahead of the vehicle's clock
    (companion.swarm.FUTURE_TOLERANCE_S)."""
    bad_frames: int = 0
    stale_or_duplicate: int = 0
    """Accepted states older than, or as old as, the one already held."""
    published: int = 0
    """Own states sent (each to every peer)."""
    bytes_out: int = 0
    bytes_in: int = 0
    plan_frames_in: int = 0
    """SWARMDROP_PLAN / SWARMDROP_SLOTS frames taken (signed ones only under --signing require)."""
    plans_in: int = 0
    """Whole plans put together (each seq once)."""
    plan_frames_rejected: int = 0
    """Plan frames the assembler refused (malformed, stale, for another mission)."""
    plan_frames_out: int = 0
    """Plan frames relayed (each to every peer)."""

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SwarmLinkStats:
        return cls(*(_num(data, f.name, int, 0) for f in dataclasses.fields(cls)))


@dataclass(frozen=True)
class IdentityStats:
    """Who the node flies, who else was heard on its autopilot link, and who claimed its
    vehicle id on the swarm link (docs/companion.md, "Identity"). File: "identity"."""

    vehicle_id: int = -1
    sysid: int = 0
    """The mission's sysid of the vehicle (vehicle_id + 1); 0: unknown."""
    autopilot_sysid: int = 0
    """The sysid of the autopilot flown (sysid, or --target-sysid)."""
    override: bool = False
    """--target-sysid chose another autopilot than the mission assigns."""
    other_autopilots: dict[int, int] = field(default_factory=dict)
    """HEARTBEATs heard from autopilots of other sysids, by sysid (ignored)."""
    conflicts: int = 0
    """Swarm states that claimed this vehicle's id and were not its own."""
    conflict_sources: int = 0
    """Distinct senders (sysid, address) of those."""
    last_conflict: str | None = None
    """Who claimed it last ("sysid S at HOST:PORT")."""
    own_echoes: int = 0
    """Own states that came back (a peer or medium echoing them): ignored."""

    def to_json(self) -> dict[str, Any]:
        return {"vehicle_id": self.vehicle_id, "sysid": self.sysid, "autopilot_sysid": self.autopilot_sysid,
                "override": self.override,
                "other_autopilots": {str(k): n for k, n in sorted(self.other_autopilots.items())},
                "conflicts": self.conflicts, "conflict_sources": self.conflict_sources,
                "last_conflict": self.last_conflict, "own_echoes": self.own_echoes}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> IdentityStats:
        others = _section(data, "other_autopilots")
        return cls(vehicle_id=_num(data, "vehicle_id", int, -1), sysid=_num(data, "sysid", int, 0),
                   autopilot_sysid=_num(data, "autopilot_sysid", int, 0), override=data.get("override") is True,
                   other_autopilots={int(k): _num(others, k, int, 0) for k in others if k.isdigit()},
                   conflicts=_num(data, "conflicts", int, 0), conflict_sources=_num(data, "conflict_sources", int, 0),
                   last_conflict=_opt_str(data, "last_conflict"), own_echoes=_num(data, "own_echoes", int, 0))


@dataclass(frozen=True)
class SigningStats:
    """What each signed link's signing layer dropped (companion.link.signing); a link
    without signing has None. File: "signing", only the signed links."""

    autopilot: SigningCounters | None = None
    swarm: SigningCounters | None = None

    def links(self) -> list[tuple[str, SigningCounters]]:
        """(link name, counters) of the signed links, in SIGNED_LINKS order."""
        return [(name, c) for name in SIGNED_LINKS if (c := getattr(self, name)) is not None]

    def to_json(self) -> dict[str, Any]:
        return {name: dataclasses.asdict(c) for name, c in self.links()}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SigningStats:
        def counters(name: str) -> SigningCounters | None:
            c = data.get(name)
            if not isinstance(c, Mapping):
                return None
            return SigningCounters(**{f.name: _num(c, f.name, int, 0) for f in dataclasses.fields(SigningCounters)})

        return cls(*(counters(name) for name in SIGNED_LINKS))


@dataclass(frozen=True)
class AgentStats:
    """Everything one agent counts: the --stats file, as a tree of snapshots.

    Times: wall_s, cpu_s from node construction; setup_s from process start to the end of
    set-up (NaN: set-up did not finish); startup_s from process start to a constructed node
    (None where the OS does not say).
    """

    vehicle_id: int = -1
    """The vehicle's index in the mission; -1: unknown (a file without one)."""
    phase: str | None = None
    """The agent's phase (companion.agent.Phase name) when the snapshot was taken."""
    ticks: int = 0
    setpoints_sent: int = 0
    unsendable_setpoints: int = 0
    latency_ms: TickLatency | None = None
    """None: no setpoint was sent."""
    latency_hist: LatencyHistogram | None = None
    agent_step_ms: StepTime | None = None
    """None: the planner never ran."""
    deadline_misses: int = 0
    setpoint_intervals: int = 0
    cpu_s: float = math.nan
    wall_s: float = math.nan
    setup_s: float = math.nan
    startup_s: float | None = None
    event_loop: str | None = None
    """The event loop the agent flew on, name and version (--event-loop); None: not said."""
    left_offboard: int = 0
    """Times the autopilot left offboard/GUIDED after it was engaged (companion.node.offboard)."""
    autopilot: AutopilotLinkStats = field(default_factory=AutopilotLinkStats)
    swarm: SwarmLinkStats = field(default_factory=SwarmLinkStats)
    identity: IdentityStats = field(default_factory=IdentityStats)
    signing: SigningStats = field(default_factory=SigningStats)

    def to_json(self) -> dict[str, Any]:
        """The JSON document (the keys, their order and values as the file has always had them:
        an absent optional section is written as {})."""
        return {
            "vehicle_id": self.vehicle_id, "phase": self.phase, "ticks": self.ticks,
            "setpoints_sent": self.setpoints_sent, "unsendable_setpoints": self.unsendable_setpoints,
            "latency_ms": self.latency_ms.to_json() if self.latency_ms is not None else {},
            "latency_hist": self.latency_hist.to_json() if self.latency_hist is not None else {},
            "agent_step_ms": self.agent_step_ms.to_json() if self.agent_step_ms is not None else {},
            "deadline_misses": self.deadline_misses, "setpoint_intervals": self.setpoint_intervals,
            "cpu_s": self.cpu_s, "wall_s": self.wall_s, "setup_s": self.setup_s, "startup_s": self.startup_s,
            "event_loop": self.event_loop, "left_offboard": self.left_offboard,
            "autopilot": self.autopilot.to_json(),
            "swarm": self.swarm.to_json(),
            "identity": self.identity.to_json(),
            "signing": self.signing.to_json(),
        }

    @classmethod
    def from_json(cls, data: Any, vehicle_id: int | None = None) -> AgentStats:
        """An AgentStats from a parsed --stats file, tolerating a partial one.

        Args:
            data: the parsed JSON (anything: a non-object reads as an empty file).
            vehicle_id: the vehicle's id when the file does not say (the harness knows it).
        Returns:
            The snapshot; what is missing or unreadable takes the field's default.
        """
        d: Mapping[str, Any] = data if isinstance(data, Mapping) else {}
        vid = _num(d, "vehicle_id", int, -1 if vehicle_id is None else vehicle_id)
        return cls(
            vehicle_id=vid, phase=_opt_str(d, "phase"), ticks=_num(d, "ticks", int, 0),
            setpoints_sent=_num(d, "setpoints_sent", int, 0),
            unsendable_setpoints=_num(d, "unsendable_setpoints", int, 0),
            latency_ms=TickLatency.from_json(_section(d, "latency_ms")),
            latency_hist=LatencyHistogram.from_json(_section(d, "latency_hist")),
            agent_step_ms=StepTime.from_json(_section(d, "agent_step_ms")),
            deadline_misses=_num(d, "deadline_misses", int, 0), setpoint_intervals=_num(d, "setpoint_intervals", int, 0),
            cpu_s=_num(d, "cpu_s", float, math.nan), wall_s=_num(d, "wall_s", float, math.nan),
            setup_s=_num(d, "setup_s", float, math.nan), startup_s=_opt_float(d, "startup_s"),
            event_loop=_opt_str(d, "event_loop"), left_offboard=_num(d, "left_offboard", int, 0),
            autopilot=AutopilotLinkStats.from_json(_section(d, "autopilot")),
            swarm=SwarmLinkStats.from_json(_section(d, "swarm")),
            identity=IdentityStats.from_json(_section(d, "identity")),
            signing=SigningStats.from_json(_section(d, "signing")),
        )

    def save(self, path: Path) -> None:
        """Replace path with the JSON (written aside, then renamed: a reader never sees half)."""
        write_json(path, self.to_json())

    @classmethod
    def load(cls, path: Path, vehicle_id: int | None = None) -> AgentStats:
        """The stats file at path; an empty AgentStats of vehicle_id if it is missing or not JSON
        (an agent that died before its first write)."""
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            data = {}
        return cls.from_json(data, vehicle_id)


# ----------------------------------------------------------------------------- from a node
def _stream_stops(streams: UnreadStreams | None) -> dict[str, list[str]]:
    if streams is None:
        return {}
    from companion.node.streams import msg_name
    return {"streams_stopped": [msg_name(m) for m in streams.stopped],
            "streams_not_stopped": [msg_name(m) for m in streams.refused if m not in streams.stopped]}


def collect(node: AgentNode) -> AgentStats:
    """Snapshot everything a node counts (every STATS_PERIOD_S and at exit)."""
    c = node.tick.counters
    cfg, v, ap_ep, swarm = node.cfg, node.vehicle, node.ap_ep, node.swarm
    latency = hist = None
    if c.latency.n:
        p50, p90, p99 = c.latency.percentiles_ms((50, 90, 99))
        latency = TickLatency(p50, p90, p99, c.latency.max_s * 1e3)
        hist = LatencyHistogram(LAT_BIN_US, c.latency.coarse(LAT_BIN_US, LAT_BINS))
    step = None
    if c.step.n:
        step = StepTime(*c.step.percentiles_ms((50, 99)))
    return AgentStats(
        vehicle_id=cfg.vehicle_id, phase=node.tick.phase.name, ticks=c.ticks, setpoints_sent=c.setpoints_sent,
        unsendable_setpoints=c.unsendable, latency_ms=latency, latency_hist=hist, agent_step_ms=step,
        deadline_misses=c.deadline_misses, setpoint_intervals=c.intervals,
        cpu_s=time.process_time() - node.start_cpu, wall_s=time.monotonic() - node.start_wall,
        setup_s=node.setup.ready_wall_s, startup_s=node.startup_s, event_loop=node.event_loop,
        left_offboard=node.offboard.left,
        autopilot=AutopilotLinkStats(
            dialect=v.dialect.name if v.dialect else None, bad_frames=ap_ep.bad_frames,
            unknown_messages=ap_ep.unknown, foreign=v.foreign, dropped_nonfinite=v.dropped_nonfinite,
            bytes_in=ap_ep.link.bytes_in, bytes_out=ap_ep.link.bytes_out, stranger_drops=ap_ep.link.stranger_drops,
            **_stream_stops(node.setup.streams)),
        swarm=swarm.counters(),
        identity=IdentityStats(
            vehicle_id=cfg.vehicle_id, sysid=cfg.assigned_sysid, autopilot_sysid=cfg.autopilot_sysid,
            override=cfg.autopilot_sysid != cfg.assigned_sysid, other_autopilots=dict(v.other_autopilots),
            **swarm.identity()),
        signing=SigningStats(*(dataclasses.replace(ep.signing.counters) if ep.signing is not None else None
                               for ep in (ap_ep, node.sw_ep))),
    )


def check_writable(path: Path, option: str = "--stats") -> None:
    """Refuse a statistics path the agent could not write (checked at start, before anything
    flies): a directory, a missing or read-only directory. Writes the file's side file
    (write_json's PATH.tmp) and removes it; the file itself is left as it was.

    Raises:
        ConfigError: naming the option, the path and the reason.
    """
    from companion.config import ConfigError

    if path.is_dir():
        raise ConfigError(f"{option} {path}: is a directory, not a file")
    probe = path.with_suffix(".tmp")
    try:
        with probe.open("x" if not probe.exists() else "a"):
            pass
        probe.unlink()
    except OSError as err:
        raise ConfigError(f"{option} {path}: cannot write there: {err.strerror or err}") from None


def write_json(path: Path, data: dict) -> None:
    """Replace path with data as JSON (written aside, then renamed: a reader never sees half)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)
