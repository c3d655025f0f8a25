"""What a run prints and tabulates: the console summary of a run, and CSV tables."""
from __future__ import annotations

from pathlib import Path

from sim_bridge.reports.results import RunMetrics


def write_csv(path: Path, rows: list[dict]) -> Path:
    """rows (dicts with the same keys) as CSV with a header; floats as written by repr."""
    import csv

    with path.open("w", newline="") as fh:
        if rows:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return path


def _steps(per_s: float | None) -> str:
    if not per_s:
        return "n/a"
    return f"{per_s / 1e6:.2f}M" if per_s >= 1e5 else f"{per_s / 1e3:.1f}k"


def summary_lines(metrics: RunMetrics, out_dir: Path) -> list[str]:
    """The console summary of a run."""
    s, f, sep, perf = metrics.stabilisation, metrics.formation_deviation, metrics.separation, metrics.performance
    fmt = lambda x, u="", p=3: "n/a" if x is None else f"{x:.{p}f}{u}"  # noqa: E731
    lines = [
        f"run directory: {out_dir}",
        f"  vehicles stabilised:   {sum(r.stabilised for r in s.per_vehicle)}/{metrics.n_vehicles}"
        f" (max settle {fmt(s.max_settle_time_s, ' s', 2)}, max drift {fmt(s.max_drift_m, ' m', 2)})",
        f"  all assembled at:      {fmt(metrics.assembly.all_assembled_s, ' s', 1)};"
        f" transit start {fmt(metrics.assembly.transit_start_s, ' s', 1)}",
        f"  mission complete at:   {fmt(metrics.mission.completion_time_s, ' s', 1)}"
        + (f" (every vehicle landed and disarmed at {metrics.mission.landed_early_s:.1f} s, before the mission "
           "completed (landed by swarm commands, e.g. an operator's LAND); the run ended there)"
           if metrics.mission.landed_early_s is not None else ""),
        f"  final max deviation:   {fmt(f.final_max_m, ' m', 4)}"
        + (" (at the end of the hover, before landing)" if metrics.landing is not None else ""),
        f"  min separation:        {fmt(sep.min_pair_distance_m, ' m')} (UAVs {sep.min_pair_vehicles},"
        f" t = {fmt(sep.min_pair_time_s, ' s', 1)}); pairs < {sep.safety_distance_m} m: {sep.pairs_below_safety_distance}",
        f"  min obstacle clearance: {fmt(metrics.obstacles.min_clearance_m, ' m')}",
        *([f"  landing:               {metrics.landing.vehicles_down}/{metrics.landing.vehicles_judged} down"
           f" (all at {fmt(metrics.landing.all_down_s, ' s', 1)}), began {fmt(metrics.landing.land_start_s, ' s', 1)};"
           f" min separation descending {fmt(metrics.landing.min_pair_distance_descending_m, ' m')}"]
          if metrics.landing is not None else []),
        f"  speed:                 {fmt(perf.real_time_factor, 'x real time', 1)},"
        f" {_steps(perf.vehicle_steps_per_s)} vehicle-steps/s",
    ]
    for c in metrics.launch_study or []:
        g, p, r = c.geometric, c.pid, c.pid_over_geometric
        lines.append(
            f"  launch roll {c.roll_deg:g} deg: geometric settles {fmt(g.settling_time_s, ' s', 2)},"
            f" drift {fmt(g.drift_m, ' m', 2)}, lost {fmt(g.altitude_loss_m, ' m', 2)};"
            f" PID {fmt(p.settling_time_s, ' s', 2)}, drift {fmt(p.drift_m, ' m', 2)},"
            f" lost {fmt(p.altitude_loss_m, ' m', 2)} (PID/geometric: settle {fmt(r.get('settling_time_s'), 'x', 2)},"
            f" drift {fmt(r.get('drift_m'), 'x', 2)}, lost {fmt(r.get('altitude_loss_m'), 'x', 2)})"
        )
    if metrics.launch_so3 is not None:
        so3 = metrics.launch_so3.summary()
        g, p = so3["geometric"], so3["pid"]
        lines.append(
            f"  {so3['draws']} random-attitude launches: recovered {100 * (g['recovered_fraction'] or 0):.1f} %"
            f" geometric / {100 * (p['recovered_fraction'] or 0):.1f} % PID; settle p50/p95"
            f" {fmt(g['settle_time_s_p50'], '', 2)}/{fmt(g['settle_time_s_p95'], ' s', 2)} vs"
            f" {fmt(p['settle_time_s_p50'], '', 2)}/{fmt(p['settle_time_s_p95'], ' s', 2)}; height lost p50/p95"
            f" {fmt(g['altitude_loss_m_p50'], '', 2)}/{fmt(g['altitude_loss_m_p95'], ' m', 2)} vs"
            f" {fmt(p['altitude_loss_m_p50'], '', 2)}/{fmt(p['altitude_loss_m_p95'], ' m', 2)}")
    for name, ok in metrics.checks.items():
        lines.append(f"  [{'PASS' if ok else 'FAIL'}] {name}")
    return lines
