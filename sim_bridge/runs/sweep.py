"""`swarmdrop sweep`: Monte Carlo over seeds, headless, on Dask (or in-process).

Every run is the headless scenario with one seed: the seed draws the release
attitudes, the gusts, the link's losses and everything else random in the scenario,
so `--rerun SEED` replays exactly one run. Runs go to a Dask cluster: a local one
(`--workers W`, one single-threaded worker process per core) or an existing one
(`--address tcp://host:8786`). With one worker and no address nothing of Dask is
imported, so a plain install (without the `sweep` extra) still sweeps.

A run that raises is kept, with its seed, its reason and its traceback.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

TRIM_VAR = "MALLOC_TRIM_THRESHOLD_"


class SweepError(Exception):
    """The sweep cannot start (no Dask for several workers, a cluster that does not answer)."""


@dataclass(frozen=True)
class SweepRun:
    """One seed's outcome (SI units). ok False: the run raised (reason and trace say why),
    and the figures are None."""

    seed: int
    ok: bool
    wall_s: float
    reason: str | None = None
    trace: str | None = None
    passed: bool = False
    """Every acceptance check of the run passed."""
    mission_completed: bool = False
    all_stabilised: bool = False
    completion_time_s: float | None = None
    min_separation_m: float | None = None
    pairs_below_safety_distance: int | None = None
    min_obstacle_clearance_m: float | None = None
    max_settle_time_s: float | None = None
    mean_settle_time_s: float | None = None
    final_max_deviation_m: float | None = None
    sim_s: float | None = None
    failed_checks: str = ""
    """Names of the checks that failed, separated by spaces."""
    collisions: int | None = None
    """Pairs of healthy vehicles that came within the collision distance."""
    rotor_failures: int = 0
    failures_detected: int = 0
    """Failed vehicles whose own agent declared loss of control."""
    max_detection_latency_s: float | None = None
    min_failed_distance_m: float | None = None
    """Closest approach of a vehicle with a failed rotor to a healthy one."""

    @property
    def target_met(self) -> bool:
        """The issue's sweep target for a run: the healthy vehicles reached formation and
        finished the mission, and no two healthy vehicles collided."""
        return self.ok and self.mission_completed and self.collisions == 0


MAX_SEEDS = 100_000
"""Most seeds one sweep takes (`swarmdrop sweep --seeds`): their results are held and written
together (about 1 kB a seed), and 100,000 paper_40 runs are already days of 2 cores' time."""

MAX_BATCH = 5
"""Most seeds flown side by side in one process (headless.run_batch). The per-tick
Python cost is shared (a paper_40 run: 3.7 s alone, 2.6 s in a batch of 5 or 10) and
the logs of a batch fit easily in memory (about 60 MB a run of paper_40)."""


def _sweep_cfg(config_path: str, seed: int):
    """The scenario with this seed, without the launch study (a sweep scores the mission)."""
    from sim_bridge.scenario import load_scenario

    cfg = load_scenario(config_path, seed)
    return dataclasses.replace(cfg, launch_study=dataclasses.replace(cfg.launch_study, enabled=False))


def _crashed(seed: int, wall_s: float, err: BaseException) -> SweepRun:
    # (the reason on one line: it is a cell of runs.csv and of summary.md's table; the trace keeps the rest)
    return SweepRun(seed, False, wall_s, reason=" ".join(f"{type(err).__name__}: {err}".split()),
                    trace="".join(traceback.format_exception(err)))


def _scored(seed: int, wall_s: float, m) -> SweepRun:
    """A SweepRun from one run's metrics (sim_bridge.reports.results.Metrics)."""
    st = m.stabilisation
    lat = [f.detection_latency_s for f in m.rotor_failures if f.detection_latency_s is not None]
    return SweepRun(
        seed, True, wall_s, passed=m.passed, mission_completed=m.mission.completed,
        all_stabilised=st.all_stabilised, completion_time_s=m.mission.completion_time_s,
        min_separation_m=m.separation.min_pair_distance_m,
        pairs_below_safety_distance=m.separation.pairs_below_safety_distance,
        min_obstacle_clearance_m=m.obstacles.min_clearance_m, max_settle_time_s=st.max_settle_time_s,
        mean_settle_time_s=st.mean_settle_time_s, final_max_deviation_m=m.formation_deviation.final_max_m,
        sim_s=m.performance.sim_s, failed_checks=" ".join(k for k, ok in m.checks.items() if not ok),
        collisions=m.separation.collisions, rotor_failures=len(m.rotor_failures),
        failures_detected=sum(f.detection_latency_s is not None for f in m.rotor_failures),
        max_detection_latency_s=max(lat, default=None), min_failed_distance_m=m.separation.min_failed_distance_m,
    )


def run_one(config_path: str, seed: int) -> SweepRun:
    """Fly the scenario headless with this seed (no launch study, no figures). Never raises:
    an exception becomes a failed SweepRun with its traceback."""
    t0 = time.perf_counter()
    try:
        from sim_bridge.reports.metrics import compute_metrics
        from sim_bridge.runs.headless import run_scenario

        m = compute_metrics(run_scenario(_sweep_cfg(config_path, seed), progress=False), None)
    except Exception as err:  # kept, not lost: the sweep reports it with the seed
        return _crashed(seed, time.perf_counter() - t0, err)
    return _scored(seed, time.perf_counter() - t0, m)


def run_seeds(config_path: str, seeds: list[int]) -> list[SweepRun]:
    """Fly these seeds side by side in this process (headless.run_batch: each run's result
    is the one `run_one` gives, to the last bit) and score each. Each run's wall_s is the
    batch's wall time divided by its size. Never raises: if the batch raises, every seed
    is flown alone, so that the run that raised keeps its own reason and trace and the
    others are not lost."""
    t0 = time.perf_counter()
    try:
        from sim_bridge.reports.metrics import compute_metrics
        from sim_bridge.runs.headless import run_batch

        results = run_batch([_sweep_cfg(config_path, s) for s in seeds], progress=False)
    except Exception:
        return [run_one(config_path, s) for s in seeds]
    scored: list[tuple[int, object]] = []
    for seed, res in zip(seeds, results):
        try:
            scored.append((seed, compute_metrics(res, None)))
        except Exception as err:  # kept with its seed
            scored.append((seed, err))
    wall = (time.perf_counter() - t0) / len(seeds)
    return [_crashed(seed, wall, m) if isinstance(m, BaseException) else _scored(seed, wall, m) for seed, m in scored]


def plan_batches(seeds: list[int], workers: int, max_batch: int = MAX_BATCH) -> list[list[int]]:
    """Split seeds into batches of at most max_batch, their count a multiple of workers
    (so that every worker gets as many), sizes differing by at most one.

    Raises:
        ValueError: workers or max_batch below 1.
    """
    if workers < 1 or max_batch < 1:
        raise ValueError("workers and max_batch must be at least 1")
    if not seeds:
        return []
    n_batches = workers * math.ceil(len(seeds) / (workers * max_batch))
    n_batches = min(n_batches, len(seeds))
    size, extra = divmod(len(seeds), n_batches)
    out, i = [], 0
    for b in range(n_batches):
        k = size + (1 if b < extra else 0)
        out.append(seeds[i:i + k])
        i += k
    return out


def _in_process(config_path: str, seeds: list[int], max_batch: int) -> Iterator[list[SweepRun]]:
    for batch in plan_batches(seeds, 1, max_batch):
        yield run_seeds(config_path, batch)


def _pin_to(cpu: int) -> None:
    """Run this whole process (every thread) on one CPU (Linux)."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), {cpu})
        except OSError:  # a thread that has just ended
            pass


def _pin_workers(client) -> None:
    """One CPU per local worker, when there are enough: the runs are CPU-bound, and two
    workers left to the scheduler lose 5-15 % here to migrations between the cores.
    Does nothing where affinity is not available (not Linux)."""
    if not hasattr(os, "sched_getaffinity") or not os.path.isdir("/proc/self/task"):
        return
    cpus = sorted(os.sched_getaffinity(0))
    workers = sorted(client.scheduler_info().get("workers", {}))
    if len(workers) > len(cpus):
        return
    for address, cpu in zip(workers, cpus):
        client.run(_pin_to, cpu, workers=[address])


def _on_dask(config_path: str, seeds: list[int], workers: int, address: str | None,
             warn: Callable[[str], None], max_batch: int) -> Iterator[list[SweepRun]]:
    try:
        import dask
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise SweepError("several workers or a cluster address need Dask: pip install 'swarmdrop[sweep]' "
                         "(or run with --workers 1)") from None
    cluster = None
    if address is None:
        # Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in its workers, which made this
        # numpy-heavy work about 1.9x slower here: unset it (None removes the variable).
        with dask.config.set({f"distributed.nanny.pre-spawn-environ.{TRIM_VAR}": None}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, host="127.0.0.1")
        client = Client(cluster)
        _pin_workers(client)
    else:
        try:
            client = Client(address, timeout="10s")
        except OSError as err:
            raise SweepError(f"--address {address}: no Dask scheduler answers ({err})") from None
        trimmed = {w: v for w, v in client.run(os.environ.get, TRIM_VAR).items() if v is not None}
        if trimmed:
            warn(f"{len(trimmed)} worker(s) of {address} run with {TRIM_VAR}={next(iter(trimmed.values()))}, "
                 f"which slows this work; start them with `env -u {TRIM_VAR}`")
    try:
        n_workers = len(client.scheduler_info().get("workers", {})) or workers
        batches = plan_batches(seeds, n_workers, max_batch)
        futures = client.map(run_seeds, [config_path] * len(batches), batches, pure=False)
        for fut in as_completed(futures):
            yield fut.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_sweep(config_path: str | Path, seeds: list[int], workers: int = 1, address: str | None = None,
              progress: bool = True, warn: Callable[[str], None] = print,
              max_batch: int = MAX_BATCH) -> list[SweepRun]:
    """Fly every seed, up to max_batch side by side per task (plan_batches); returns the
    runs in seed order.

    Raises:
        SweepError: Dask missing for workers > 1 or an address, or the cluster does not answer.
        ConfigError: the scenario does not load (checked once here, before anything is sent out).
    """
    from tqdm import tqdm

    from sim_bridge.scenario import load_scenario

    path = str(Path(config_path).resolve())
    load_scenario(path)  # a bad config fails once, here, with its path and reason
    if max_batch < 1:
        raise ValueError("--batch must be at least 1")
    it = _in_process(path, seeds, max_batch) if workers <= 1 and address is None \
        else _on_dask(path, seeds, workers, address, warn, max_batch)
    runs: list[SweepRun] = []
    with tqdm(total=len(seeds), unit="run", disable=not progress, desc="sweep") as bar:
        for batch in it:
            runs += batch
            bar.update(len(batch))
            bad = sum(not x.ok or not x.passed for x in runs)
            bar.set_postfix_str(f"failed {bad}" if bad else "all passed", refresh=False)
    return sorted(runs, key=lambda r: r.seed)


def _pct(xs: list[float], p: float) -> float | None:
    import numpy as np

    return float(np.percentile(xs, p)) if xs else None


def summary(runs: list[SweepRun], safety_distance_m: float) -> dict:
    """The sweep's headline figures (JSON-ready)."""
    ok = [r for r in runs if r.ok]
    sep = [r.min_separation_m for r in ok if r.min_separation_m is not None]
    settle = [r.max_settle_time_s for r in ok if r.max_settle_time_s is not None]
    comp = [r.completion_time_s for r in ok if r.completion_time_s is not None]
    lat = [r.max_detection_latency_s for r in ok if r.max_detection_latency_s is not None]
    fd = [r.min_failed_distance_m for r in ok if r.min_failed_distance_m is not None]
    n = len(runs)
    return {
        "runs": n, "crashed": n - len(ok), "passed_every_check": sum(r.passed for r in ok),
        "mission_completed": sum(r.mission_completed for r in ok),
        "target_met": sum(r.target_met for r in ok),
        "healthy_collisions": sum(r.collisions or 0 for r in ok),
        "rotor_failures": sum(r.rotor_failures for r in ok),
        "rotor_failures_detected": sum(r.failures_detected for r in ok),
        "detection_latency_s": {"median": _pct(lat, 50), "max": max(lat) if lat else None},
        "min_failed_distance_m": min(fd) if fd else None,
        "runs_below_safety_distance": sum((r.pairs_below_safety_distance or 0) > 0 for r in ok),
        "safety_distance_m": safety_distance_m,
        "min_separation_m": {"min": min(sep) if sep else None, "p5": _pct(sep, 5), "median": _pct(sep, 50)},
        "max_settle_time_s": {"median": _pct(settle, 50), "p95": _pct(settle, 95), "max": max(settle) if settle else None},
        "completion_time_s": {"median": _pct(comp, 50), "p95": _pct(comp, 95)},
        "wall_s_per_run": {"mean": sum(r.wall_s for r in runs) / n if n else None},
    }


def _fmt(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def markdown(runs: list[SweepRun], s: dict, title: str) -> str:
    """A Markdown summary: headline table, then every run that crashed or failed a check."""
    n = max(s["runs"], 1)
    lines = [f"# Sweep: {title}", "",
             "| figure | value |", "|---|---|",
             f"| runs | {s['runs']} ({s['crashed']} crashed) |",
             f"| healthy vehicles reached formation and finished, no collision | {s['target_met']} "
             f"({100 * s['target_met'] / n:.1f} %) |",
             f"| collisions between healthy vehicles (all runs) | {s['healthy_collisions']} |",
             f"| passed every check | {s['passed_every_check']} ({100 * s['passed_every_check'] / n:.1f} %) |",
             f"| mission completed | {s['mission_completed']} ({100 * s['mission_completed'] / n:.1f} %) |",
             f"| runs with a pair closer than {s['safety_distance_m']:g} m | {s['runs_below_safety_distance']} |",
             f"| minimum separation: min / p5 / median | {_fmt(s['min_separation_m']['min'])} / "
             f"{_fmt(s['min_separation_m']['p5'])} / {_fmt(s['min_separation_m']['median'])} m |",
             f"| worst recovery (settle) time per run: median / p95 / max | {_fmt(s['max_settle_time_s']['median'])} / "
             f"{_fmt(s['max_settle_time_s']['p95'])} / {_fmt(s['max_settle_time_s']['max'])} s |",
             f"| mission completion time: median / p95 | {_fmt(s['completion_time_s']['median'], 1)} / "
             f"{_fmt(s['completion_time_s']['p95'], 1)} s |"]
    if s["rotor_failures"]:
        lines += [f"| rotor failures / declared by the vehicle's agent | {s['rotor_failures']} / "
                  f"{s['rotor_failures_detected']} |",
                  f"| detection latency: median / max | {_fmt(s['detection_latency_s']['median'])} / "
                  f"{_fmt(s['detection_latency_s']['max'])} s |",
                  f"| closest approach of a failed vehicle to a healthy one | {_fmt(s['min_failed_distance_m'])} m |"]
    lines.append("")
    bad = [r for r in runs if not r.ok or not r.passed]
    if bad:
        lines += ["## Runs that crashed or failed a check (replay with `swarmdrop sweep CONFIG --rerun SEED`)", "",
                  "| seed | outcome |", "|---|---|"]
        lines += [f"| {r.seed} | {r.reason if not r.ok else 'failed: ' + r.failed_checks} |" for r in bad]
    return "\n".join(lines) + "\n"


def write_results(runs: list[SweepRun], out_dir: Path, title: str, safety_distance_m: float,
                  figures: bool = True) -> dict:
    """runs.csv, summary.md, summary.json, failures/SEED.txt (tracebacks) and figures."""
    from sim_bridge.reports.summary import write_csv

    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(out_dir / "runs.csv", [{**{k: v for k, v in dataclasses.asdict(r).items() if k != "trace"},
                                      "target_met": r.target_met} for r in runs])
    for r in runs:
        if r.trace:
            (out_dir / "failures").mkdir(exist_ok=True)
            (out_dir / "failures" / f"{r.seed}.txt").write_text(f"seed {r.seed}: {r.reason}\n\n{r.trace}")
    s = summary(runs, safety_distance_m)
    (out_dir / "summary.json").write_text(json.dumps(s, indent=2))
    (out_dir / "summary.md").write_text(markdown(runs, s, title))
    if figures and any(r.ok for r in runs):
        from sim_bridge.reports.figures_studies import fig_sweep

        fig_sweep(runs, safety_distance_m, out_dir)
    return s
