"""Typed report of a fleet run: the paper metrics plus what the processes did.

`FleetReport.to_json()` is the run's metrics.json: the headless document
(`RunMetrics`) with a "fleet" section, or, for a run interrupted before the SITL
recorded anything, only `{"recorded": false, "fleet": ...}`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.link.signing import SigningCounters
from companion.node.stats import AgentStats, histogram_percentiles
from sim_bridge.reports.results import RunMetrics
from sim_bridge.sitl.status import SitlStatus
from sim_bridge.world.transport import MeanMax


@dataclass(frozen=True)
class CpuShare:
    """The agents' CPU use, as a fraction of one core (None: not measured)."""

    mean: float | None
    """Fraction of one core, averaged over the agents."""
    max: float | None
    measured_from_sim_s: float
    """The CPU window starts here (start-up and compilation are left out)."""


@dataclass(frozen=True)
class Latency:
    """Agent tick latency (state received -> setpoint sent), ms."""

    pooled: dict[str, float]
    """Percentile name ("p50", "p99", "p99.9") -> ms, over every agent's ticks together."""
    p50_median: float | None
    p99_max: float | None
    p99_median: float | None


@dataclass(frozen=True)
class DeadlineMisses:
    """Setpoint intervals longer than the agents' tick deadline, summed over the agents:
    misses out of intervals measured, and their fraction (None: none measured)."""

    count: int
    intervals: int
    fraction: float | None


@dataclass(frozen=True)
class FleetSection:
    """The processes of a fleet run (metrics.json "fleet")."""

    dialect: str
    lockstep: bool
    output: str
    agents: int
    setpoint_rate_hz: float
    wall_s: float
    interrupted: bool
    sitl_status: SitlStatus
    dead_agents: dict[str, int]
    """Vehicle id -> exit code of agents that died unasked."""
    killed_agents: list[int]
    events: list[str]
    agent_cpu_fraction_of_core: CpuShare
    agent_latency_ms: Latency
    setpoint_deadline_misses: DeadlineMisses
    agent_startup_s: MeanMax
    agent_pss_mb: MeanMax
    sitl_cpu_fraction_of_core: float | None
    swarm_link_bytes_per_s_per_vehicle: float | None
    signing: dict[str, SigningCounters] | None = None
    """Per link kind ("autopilot", "swarm"): what the agents' signing layers dropped, summed (None unsigned)."""
    aborted: str = ""
    """Why the harness stopped the run itself (no agent left that could fly it), or ""."""


@dataclass(frozen=True)
class FleetReport:
    """metrics (None when the SITL recorded nothing) and the fleet section."""

    fleet: FleetSection
    metrics: RunMetrics | None = None

    @property
    def recorded(self) -> bool:
        return self.metrics is not None

    @property
    def passed(self) -> bool:
        return self.metrics is not None and self.metrics.passed

    def to_json(self) -> dict[str, Any]:
        fleet = dataclasses.asdict(self.fleet)
        if self.metrics is None:
            return {"recorded": False, "fleet": fleet}
        return {**self.metrics.to_json(), "fleet": fleet}


def pooled_percentiles(hists: list, percents) -> dict[str, float]:
    """Percentiles (ms) of every agent's latencies together, from their histograms."""
    hists = [h for h in hists if h and h.get("counts")]
    if not hists:
        return {}
    counts = np.sum([np.asarray(h["counts"]) for h in hists], axis=0)
    values = histogram_percentiles(counts, hists[0]["bin_us"], percents)
    return {f"p{p:g}": v for p, v in zip(percents, values)}


def _stat(xs: list[float], fn) -> float | None:
    return float(fn(xs)) if xs else None


def agent_figures(stats: list[AgentStats], cpu: list[float], pss: list[float], cpu_from_sim_s: float) -> dict:
    """The per-agent figures of the fleet section, from the agents' stats files."""
    p50 = [s.latency_ms.p50 for s in stats if s.latency_ms is not None]
    p99 = [s.latency_ms.p99 for s in stats if s.latency_ms is not None]
    misses = sum(s.deadline_misses for s in stats)
    intervals = sum(s.setpoint_intervals for s in stats)
    startup = [s.startup_s for s in stats if s.startup_s is not None]
    hists = [s.latency_hist.to_json() if s.latency_hist is not None else None for s in stats]
    return dict(
        agent_cpu_fraction_of_core=CpuShare(_stat(cpu, np.mean), _stat(cpu, np.max), cpu_from_sim_s),
        agent_latency_ms=Latency(pooled_percentiles(hists, (50, 99, 99.9)),
                                 _stat(p50, np.median), _stat(p99, np.max), _stat(p99, np.median)),
        setpoint_deadline_misses=DeadlineMisses(misses, intervals, misses / intervals if intervals else None),
        agent_startup_s=MeanMax(mean=_stat(startup, np.mean), max=_stat(startup, np.max)),
        agent_pss_mb=MeanMax(mean=_stat(pss, np.mean), max=_stat(pss, np.max)),
    )


def signing_totals(stats: list[AgentStats]) -> dict[str, SigningCounters]:
    """What the agents' signing layers dropped, summed per link."""
    out: dict[str, SigningCounters] = {}
    for s in stats:
        for link, counters in s.signing.links():
            tot = out.get(link, SigningCounters())
            out[link] = SigningCounters(**{f.name: getattr(tot, f.name) + getattr(counters, f.name)
                                           for f in dataclasses.fields(SigningCounters)})
    return out


def summary_lines(report: FleetReport, out_dir: Path) -> list[str]:
    """The console summary of a fleet run (the headless summary plus the fleet figures)."""
    from sim_bridge.reports.summary import summary_lines as headless_lines

    fl = report.fleet
    fmt = lambda x, p=2: "n/a" if x is None else f"{x:.{p}f}"  # noqa: E731
    pct = lambda x, p: fmt(None if x is None else 100 * x, p)  # noqa: E731  (a share, in %; n/a: not measured)
    how = "INTERRUPTED" if fl.interrupted else ("ABORTED (" + fl.aborted + ")" if fl.aborted else "")
    if report.metrics is None:
        lines = [f"run directory: {out_dir}", f"  {how or 'STOPPED'} before the SITL recorded its first sample: "
                 "nothing to score"]
    else:
        lines = headless_lines(report.metrics, out_dir)
        if how:
            lines.insert(1, f"  {how} at t = {fl.sitl_status.sim_s:.1f} s: the mission did not complete; the checks "
                         "below see a partial run")
    dm, lat = fl.setpoint_deadline_misses, fl.agent_latency_ms.pooled
    lines += [
        f"  fleet: {fl.agents} agent processes ({fl.dialect}, {fl.output}, "
        f"{'lockstep' if fl.lockstep else 'real time'}), dead: {fl.dead_agents or 'none'}",
        f"  agent CPU: mean {pct(fl.agent_cpu_fraction_of_core.mean, 2)} % of a core,"
        f" latency (all agents) p50 {fmt(lat.get('p50'))} ms,"
        f" p99 {fmt(lat.get('p99'))} ms, deadline misses {pct(dm.fraction, 3)} %",
        f"  agent start {fmt(fl.agent_startup_s.max)} s (max), PSS {fmt(fl.agent_pss_mb.mean, 1)} MB;"
        f" SITL CPU {pct(fl.sitl_cpu_fraction_of_core, 1)} % of a core",
    ]
    return lines
