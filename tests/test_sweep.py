"""`swarmdrop sweep`: runs reproducible from their seed, failures kept, Dask and in-process agree."""
import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from sim_bridge.runs.sweep import SweepRun, markdown, run_one, run_sweep, summary, write_results

ROOT = Path(__file__).resolve().parents[1]
SMALL = str(ROOT / "configs" / "small_6.yaml")


def _figures(r: SweepRun) -> dict:
    d = dataclasses.asdict(r)
    d.pop("wall_s")
    return d


@pytest.fixture(scope="module")
def in_process():
    return run_sweep(SMALL, [3, 4], workers=1, progress=False)


def test_every_run_is_reproducible_from_its_seed(in_process):
    a, b = in_process
    assert a.ok and b.ok and a.passed and b.passed, (a, b)
    assert _figures(run_one(SMALL, 4)) == _figures(b)
    assert a.min_separation_m != b.min_separation_m  # the seed does change the run


def test_dask_local_cluster_gives_the_in_process_results(in_process):
    pytest.importorskip("distributed")
    on_dask = run_sweep(SMALL, [3, 4], workers=2, progress=False)
    assert [_figures(r) for r in on_dask] == [_figures(r) for r in in_process]


def test_a_run_that_raises_is_kept_with_seed_reason_and_trace(tmp_path, in_process):
    bad = run_one(str(ROOT / "configs" / "ground_4.yaml"), 11)  # the headless runner refuses ground launches
    assert not bad.ok and bad.seed == 11 and "ConfigError" in bad.reason and "Traceback" in bad.trace
    runs = [*in_process, bad]
    s = write_results(runs, tmp_path, "test", 1.0, figures=True)
    assert s["runs"] == 3 and s["crashed"] == 1 and s["passed_every_check"] == 2
    assert "seed 11" in (tmp_path / "failures" / "11.txt").read_text()
    md = (tmp_path / "summary.md").read_text()
    assert "| 11 | ConfigError" in md and "--rerun SEED" in md
    rows = (tmp_path / "runs.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("seed,ok,")
    assert (tmp_path / "fig_sweep.png").stat().st_size > 10_000


def test_summary_counts_separation_violations():
    runs = [SweepRun(1, True, 1.0, passed=True, min_separation_m=2.0, pairs_below_safety_distance=0),
            SweepRun(2, True, 1.0, passed=False, min_separation_m=0.7, pairs_below_safety_distance=3,
                     failed_checks="min_separation_ok")]
    s = summary(runs, 1.0)
    assert s["runs_below_safety_distance"] == 1 and s["min_separation_m"]["min"] == 0.7
    assert "| 2 | failed: min_separation_ok |" in markdown(runs, s, "t")


def test_the_target_counts_healthy_completion_without_collision_and_failures_are_summarised():
    runs = [SweepRun(1, True, 1.0, mission_completed=True, collisions=0, rotor_failures=1, failures_detected=1,
                     max_detection_latency_s=0.8, min_failed_distance_m=5.0),
            SweepRun(2, True, 1.0, mission_completed=True, collisions=1, rotor_failures=1, failures_detected=1,
                     max_detection_latency_s=0.9, min_failed_distance_m=3.0),
            SweepRun(3, True, 1.0, mission_completed=False, collisions=0, rotor_failures=1, failures_detected=0),
            SweepRun(4, False, 1.0, reason="boom")]
    assert [r.target_met for r in runs] == [True, False, False, False]
    s = summary(runs, 1.0)
    assert s["target_met"] == 1 and s["healthy_collisions"] == 1
    assert s["rotor_failures"] == 3 and s["rotor_failures_detected"] == 2
    assert s["detection_latency_s"]["max"] == 0.9 and s["min_failed_distance_m"] == 3.0
    md = markdown(runs, s, "t")
    assert "no collision | 1 (25.0 %)" in md and "rotor failures / declared by the vehicle's agent | 3 / 2" in md


def test_one_worker_needs_no_dask_and_a_bad_config_fails_once(tmp_path):
    code = ("import sys; from sim_bridge.runs.sweep import run_sweep;"
            f"run_sweep({SMALL!r}, [5], workers=1, progress=False);"
            "assert 'distributed' not in sys.modules and 'dask' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=300)
    bad = tmp_path / "bad.yaml"
    bad.write_text("mission:\n  n_vehicles: -3\n")
    r = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "sweep", str(bad), "--seeds", "2", "--workers", "1"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "n_vehicles" in r.stderr
