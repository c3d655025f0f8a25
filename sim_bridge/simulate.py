"""`swarmdrop simulate`: run a scenario headless and write its run directory."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from companion.config import load_yaml
from sim_bridge.figures import write_figures
from sim_bridge.figures_studies import fig_launch_cdf
from sim_bridge.headless import run_scenario
from sim_bridge.launch_so3 import run_so3_study
from sim_bridge.launch_study import run_launch_study
from sim_bridge.metrics import compute_metrics
from sim_bridge.record import save_log
from sim_bridge.results import RunMetrics
from sim_bridge.scenario import ScenarioConfig


def load_scenario(path: str | Path, seed: int | None = None) -> ScenarioConfig:
    """Load and validate a scenario YAML; seed overrides the file's seed.

    Raises:
        ConfigError: unknown keys or bad values, naming their dotted path.
    """
    cfg = load_yaml(ScenarioConfig, path)
    return cfg if seed is None else dataclasses.replace(cfg, seed=seed)


def simulate(cfg: ScenarioConfig, out_dir: Path, progress: bool = True, figures: bool | None = None) -> RunMetrics:
    """Fly the launch study and the scenario, write the run directory, return metrics.

    The run directory holds metrics.json, telemetry.npz (every state of every
    vehicle at the log rate), config.json (the resolved config) and the figures.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    ls = cfg.launch_study
    study, traces = run_launch_study(cfg) if ls.enabled else (None, None)
    so3 = run_so3_study(cfg) if ls.enabled and ls.so3_draws > 0 else None
    result = run_scenario(cfg, progress=progress)
    metrics = compute_metrics(result, study, so3)
    (out_dir / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2))
    save_log(result, out_dir)
    (out_dir / "metrics.json").write_text(json.dumps(metrics.to_json(), indent=2))
    if so3 is not None:
        write_csv(out_dir / "launch_so3.csv", so3.rows())
    if cfg.output.figures if figures is None else figures:
        write_figures(result, traces, out_dir)
        if so3 is not None:
            fig_launch_cdf(so3, out_dir)
    return metrics


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
        f"  mission complete at:   {fmt(metrics.mission.completion_time_s, ' s', 1)}",
        f"  final max deviation:   {fmt(f.final_max_m, ' m', 4)}",
        f"  min separation:        {fmt(sep.min_pair_distance_m, ' m')} (UAVs {sep.min_pair_vehicles},"
        f" t = {fmt(sep.min_pair_time_s, ' s', 1)}); pairs < {sep.safety_distance_m} m: {sep.pairs_below_safety_distance}",
        f"  min obstacle clearance:{fmt(metrics.obstacles.min_clearance_m, ' m')}",
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
