"""The `swarmdrop` console script: one command, subcommands from both packages.

`swarmdrop agent ...` is dispatched before anything else is imported, so that an
onboard companion process loads only `companion` (no numba, scipy or matplotlib:
they cost a small computer about 0.5 s and 100 MB per process). The simulator
subcommands import their packages only when they run.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def _cmd_simulate(args: argparse.Namespace) -> int:
    from companion.config import ConfigError
    from sim_bridge.simulate import load_scenario, simulate, summary_lines

    try:
        cfg = load_scenario(args.config, args.seed)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    try:
        metrics = simulate(cfg, out, progress=not args.quiet, figures=False if args.no_figures else None)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print("\n".join(summary_lines(metrics, out)))
    if args.check and not metrics.passed:
        return 1
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from companion.config import ConfigError
    from sim_bridge.fleet import FleetOptions, parse_kill, run_fleet
    from sim_bridge.fleet_report import summary_lines

    out = Path(args.out) if args.out else Path("runs") / (Path(args.config).stem + "_fleet")
    try:
        opts = FleetOptions(out_dir=out, dialect=args.dialect, lockstep=args.lockstep, output=args.output,
                            base_port=args.base_port, rate_hz=args.rate, kill=parse_kill(args.kill_agent),
                            fix_delay_max_s=args.fix_delay_max, progress=not args.quiet,
                            figures=not args.no_figures, agent_nice=args.agent_nice, signing=args.signing)
        report, code = run_fleet(args.config, opts)
    except (ConfigError, ValueError, OSError, RuntimeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print("\n".join(summary_lines(report, out)))
    if code:
        return code
    if args.check and not report.passed:
        return 1
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from companion.config import ConfigError
    from sim_bridge.simulate import load_scenario, simulate, summary_lines
    from sim_bridge.sweep import SweepError, run_sweep, write_results

    stem = Path(args.config).stem
    try:
        cfg = load_scenario(args.config)
        if args.rerun is not None:  # one run, in-process, with its full run directory and figures
            out = Path(args.out) if args.out else Path("runs") / f"{stem}_sweep" / f"rerun_{args.rerun}"
            metrics = simulate(load_scenario(args.config, args.rerun), out, progress=not args.quiet)
            print("\n".join(summary_lines(metrics, out)))
            return 0 if metrics.passed else 1
        if args.seeds < 1 or args.workers < 1:
            raise ValueError("--seeds and --workers must be at least 1")
        first = cfg.seed if args.first_seed is None else args.first_seed
        seeds = list(range(first, first + args.seeds))
        out = Path(args.out) if args.out else Path("runs") / f"{stem}_sweep"
        runs = run_sweep(args.config, seeds, workers=args.workers, address=args.address, progress=not args.quiet,
                         warn=lambda m: print(f"warning: {m}", file=sys.stderr), max_batch=args.batch)
    except (ConfigError, SweepError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    s = write_results(runs, out, f"{stem}, seeds {seeds[0]}..{seeds[-1]}", cfg.safety.separation_m,
                      figures=not args.no_figures)
    print((out / "summary.md").read_text())
    print(f"results: {out}/runs.csv, summary.md, summary.json" + ("" if args.no_figures else ", fig_sweep.png"))
    if args.check:
        return 0 if s["target_met"] == s["runs"] else 1
    return 0 if s["crashed"] == 0 else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="swarmdrop", description="Carrier-launched UAV swarm flight stack")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="fly a scenario headless and write a run directory")
    s.add_argument("config", help="scenario YAML, e.g. configs/paper_40.yaml")
    s.add_argument("--out", help="run directory (default runs/<config name>)")
    s.add_argument("--seed", type=int, help="override the config's random seed")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    s.add_argument("--check", action="store_true", help="exit 1 if any acceptance check fails")
    s.set_defaults(func=_cmd_simulate)
    r = sub.add_parser("run", help="fly a scenario with the MAVLink SITL and one agent process per vehicle")
    r.add_argument("config", help="scenario YAML, e.g. configs/paper_40.yaml")
    r.add_argument("--out", help="run directory (default runs/<config name>_fleet)")
    r.add_argument("--dialect", choices=("px4", "ardupilot"), default="px4", help="autopilots of the fleet")
    r.add_argument("--lockstep", action="store_true", help="deterministic: simulation time waits for every agent")
    r.add_argument("--signing", action="store_true",
                   help="MAVLink 2 signing (required) on every link, with a fresh key in the run directory")
    r.add_argument("--output", choices=("acceleration", "attitude"), default="acceleration")
    r.add_argument("--rate", type=float, default=50.0, help="agents' setpoint rate, Hz")
    r.add_argument("--base-port", type=int, default=None, help="first of 3N+1 UDP ports (default: free ones)")
    r.add_argument("--kill-agent", action="append", default=[], metavar="ID@T",
                   help="kill agent ID at simulation time T s (fault injection; repeatable)")
    r.add_argument("--fix-delay-max", type=float, default=0.0,
                   help="vehicles get their first GNSS fix (EKF origin) at random times up to this, s")
    r.add_argument("--agent-nice", type=int, default=5, help="niceness added to agents (the SITL keeps priority)")
    r.add_argument("--quiet", action="store_true")
    r.add_argument("--no-figures", action="store_true")
    r.add_argument("--check", action="store_true", help="exit 1 if any acceptance check fails")
    r.set_defaults(func=_cmd_run)
    from sim_bridge.sweep import MAX_BATCH  # (the module imports nothing heavy at load)

    w = sub.add_parser("sweep", help="Monte Carlo over seeds, headless, on Dask (or in-process with --workers 1)")
    w.add_argument("config", help="scenario YAML, e.g. configs/paper_40.yaml")
    w.add_argument("--seeds", type=int, default=10, help="number of seeds (from the config's seed, or --first-seed)")
    w.add_argument("--first-seed", type=int, default=None)
    w.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="local Dask worker processes (default: one per core; 1 = in-process, no Dask needed)")
    w.add_argument("--address", default=None, help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786")
    w.add_argument("--batch", type=int, default=MAX_BATCH, metavar="B",
                   help=f"at most B seeds flown side by side per task (default {MAX_BATCH}; the same results, "
                        "less time per run; 1 = one run per task)")
    w.add_argument("--rerun", type=int, default=None, metavar="SEED",
                   help="replay one seed in-process, writing its full run directory and figures")
    w.add_argument("--out", help="results directory (default runs/<config name>_sweep)")
    w.add_argument("--check", action="store_true",
                   help="exit 1 unless every run met the target (healthy vehicles finish, no collision); "
                        "without it, exit 1 only if a run crashed")
    w.add_argument("--quiet", action="store_true")
    w.add_argument("--no-figures", action="store_true")
    w.set_defaults(func=_cmd_sweep)
    from companion.node import cli as agent_cli
    from sim_bridge.sitl import cli as sitl_cli

    sitl_cli.add_parser(sub)
    agent_cli.add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "agent":  # onboard: import nothing of the simulators
        from companion.node.cli import main as agent_main

        return agent_main(argv[1:])
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
