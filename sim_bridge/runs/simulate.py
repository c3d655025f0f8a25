"""`swarmdrop simulate`: run a scenario headless and write its run directory."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from sim_bridge.reports.figures import write_figures
from sim_bridge.reports.figures_studies import fig_launch_cdf
from sim_bridge.reports.launch_so3 import run_so3_study
from sim_bridge.reports.launch_study import run_launch_study
from sim_bridge.reports.metrics import compute_metrics
from sim_bridge.reports.record import save_log
from sim_bridge.reports.results import RunMetrics
from sim_bridge.reports.summary import write_csv
from sim_bridge.runs.headless import run_scenario
from sim_bridge.scenario import ScenarioConfig


def simulate(cfg: ScenarioConfig, out_dir: Path, progress: bool = True, figures: bool | None = None) -> RunMetrics:
    """Fly the launch study and the scenario, write the run directory, return metrics.

    The run directory holds metrics.json, telemetry.npz (every state of every
    vehicle at the log rate), config.json (the resolved config) and the figures. They are
    written only once the run has flown, metrics.json last (sim_bridge.runs.rundir.interrupted_note
    tells a finished directory from one an interrupt cut short).
    """
    ls = cfg.launch_study
    study, traces = run_launch_study(cfg) if ls.enabled else (None, None)
    so3 = run_so3_study(cfg) if ls.enabled and ls.so3_draws > 0 else None
    result = run_scenario(cfg, progress=progress)
    metrics = compute_metrics(result, study, so3)
    # Nothing is written before the run has flown (an interrupt until here leaves the directory
    # as it was), and metrics.json comes last: a directory without it holds no finished run.
    out_dir.mkdir(parents=True, exist_ok=True)  # (the CLI prepared it: sim_bridge.runs.rundir)
    (out_dir / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2))
    save_log(result, out_dir)
    if so3 is not None:
        write_csv(out_dir / "launch_so3.csv", so3.rows())
    if cfg.output.figures if figures is None else figures:
        write_figures(result, traces, out_dir)
        if so3 is not None:
            fig_launch_cdf(so3, out_dir)
    (out_dir / "metrics.json").write_text(json.dumps(metrics.to_json(), indent=2))
    return metrics


