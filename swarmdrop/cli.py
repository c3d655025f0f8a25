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

EXIT_INTERRUPTED = 130
EXTRAS: dict[str, tuple[str, ...]] = {
    "sim": ("scipy", "numba", "matplotlib", "tqdm", "pymavlink"),
    "console": ("aiohttp", "scipy"),
}
"""The packages of each pyproject extra a subcommand needs (`pip install swarmdrop` alone is the
onboard agent's install: docs/dependencies.md)."""
EXTRA_OF = {"simulate": "sim", "run": "sim", "sweep": "sim", "sitl": "sim", "console": "console"}


def missing_packages(extra: str) -> list[str]:
    """The packages of `extra` (EXTRAS) that cannot be imported here."""
    import importlib.util

    out = []
    for name in EXTRAS[extra]:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            out.append(name)
    return out


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from companion.config import ConfigError
    from sim_bridge.reports.summary import summary_lines
    from sim_bridge.runs.rundir import RunDirError, interrupted_note, prepare_run_dir
    from sim_bridge.runs.simulate import simulate
    from sim_bridge.scenario import load_scenario

    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    prepared: Path | None = None
    try:
        cfg = load_scenario(args.config, args.seed, strict=args.strict, warn=_warn)
        prepared = prepare_run_dir(out, args.overwrite)  # before anything flies: nothing is lost at the end
        if args.live is not None:  # a console watches the run at real-time pace (sim_bridge/runs/live.py)
            from sim_bridge.runs.live import LiveStream

            host, port = args.live
            print(f"streaming the run in real time to udp {host}:{port} (a console: swarmdrop console --mission "
                  f"{args.config} --swarm-bind {host}:{port})", flush=True)
            with LiveStream(args.live, cfg.mission.n_vehicles):
                metrics = simulate(cfg, prepared, progress=not args.quiet, figures=False if args.no_figures else None)
        else:
            metrics = simulate(cfg, prepared, progress=not args.quiet, figures=False if args.no_figures else None)
    except (ConfigError, RunDirError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        note = "interrupted before anything was written" if prepared is None else \
            interrupted_note(prepared, "metrics.json")
        print(f"\n{note}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print("\n".join(summary_lines(metrics, prepared)))
    if args.check and not metrics.passed:
        return 1
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from companion.config import ConfigError
    from sim_bridge.runs.fleet import FleetOptions, parse_kill, run_fleet
    from sim_bridge.runs.fleet_report import summary_lines
    from sim_bridge.runs.rundir import RunDirError

    out = Path(args.out) if args.out else Path("runs") / (Path(args.config).stem + "_fleet")
    try:
        opts = FleetOptions(out_dir=out, dialect=args.dialect, lockstep=args.lockstep, output=args.output,
                            base_port=args.base_port, rate_hz=args.rate, kill=parse_kill(args.kill_agent),
                            fix_delay_max_s=args.fix_delay_max, progress=not args.quiet,
                            figures=not args.no_figures, agent_nice=args.agent_nice, signing=args.signing,
                            overwrite=args.overwrite, strict=args.strict, console=not args.no_console,
                            console_port=args.console_port, agent_python=args.agent_python)
        report, code = run_fleet(args.config, opts, warn=_warn)
    except (ConfigError, RunDirError, ValueError, OSError, RuntimeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print("\n".join(summary_lines(report, out.expanduser().resolve())))  # absolute, as simulate prints it
    if code:
        return code
    if args.check and not report.passed:
        return 1
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from companion.config import ConfigError
    from sim_bridge.reports.summary import summary_lines
    from sim_bridge.runs.rundir import RunDirError, interrupted_note, prepare_run_dir
    from sim_bridge.runs.simulate import simulate
    from sim_bridge.runs.sweep import MAX_SEEDS, SweepError, run_sweep, write_results
    from sim_bridge.scenario import load_scenario

    stem = Path(args.config).stem
    out: Path | None = None
    try:
        cfg = load_scenario(args.config, strict=args.strict, warn=_warn)
        if args.rerun is not None:  # one run, in-process, with its full run directory and figures
            rerun = load_scenario(args.config, args.rerun, seed_option="--rerun")
            out = prepare_run_dir(Path(args.out) if args.out else Path("runs") / f"{stem}_sweep" / f"rerun_{args.rerun}",
                                  args.overwrite)
            metrics = simulate(rerun, out, progress=not args.quiet)
            print("\n".join(summary_lines(metrics, out)))
            return 0 if metrics.passed else 1
        if args.seeds < 1 or args.workers < 1:
            raise ValueError("--seeds and --workers must be at least 1")
        if args.seeds > MAX_SEEDS:
            raise ValueError(f"--seeds {args.seeds}: at most {MAX_SEEDS:,} in one sweep (split it with --first-seed)")
        if args.batch < 1:
            raise ValueError("--batch must be at least 1")
        first = cfg.seed if args.first_seed is None else args.first_seed
        seeds = list(range(first, first + args.seeds))
        for s in (seeds[0], seeds[-1]):  # every seed is valid if the first and last are (refused up front)
            load_scenario(args.config, s, runner=None,
                          seed_option="--first-seed" if s == seeds[0] else "--first-seed + --seeds - 1")
        out = prepare_run_dir(Path(args.out) if args.out else Path("runs") / f"{stem}_sweep", args.overwrite)
        runs = run_sweep(args.config, seeds, workers=args.workers, address=args.address, progress=not args.quiet,
                         warn=lambda m: print(f"warning: {m}", file=sys.stderr), max_batch=args.batch)
        s = write_results(runs, out, f"{stem}, seeds {seeds[0]}..{seeds[-1]}", cfg.safety.separation_m,
                          figures=not args.no_figures)
    except (ConfigError, SweepError, RunDirError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        note = "interrupted before anything was written" if out is None else \
            interrupted_note(out, "metrics.json" if args.rerun is not None else None)
        print(f"\n{note}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print((out / "summary.md").read_text())
    print(f"results: {out}/runs.csv, summary.md, summary.json" + ("" if args.no_figures else ", fig_sweep.png"))
    if args.check:
        return 0 if s["target_met"] == s["runs"] else 1
    return 0 if s["crashed"] == 0 else 1


def _live_address(text: str) -> tuple[str, int]:
    from companion.node.cli import _hostport  # the agent's HOST:PORT reader

    host, port = _hostport(text)
    if port == 0:
        raise argparse.ArgumentTypeError(f"{text!r}: a console's port is 1 to 65535")
    return host, port


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("swarmdrop")
    except PackageNotFoundError:  # (run from a source tree that was never installed)
        return "unknown (not installed)"


def _out_options(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument("--out", metavar="DIR", help=f"run directory (default {default}); must be empty or new")
    p.add_argument("--overwrite", action="store_true",
                   help="clear a non-empty --out of an earlier run's files first (a directory holding anything "
                        "else is refused; default: refuse any non-empty --out, so old results never sit beside "
                        "new ones)")
    p.add_argument("--strict", action="store_true",
                   help="refuse a mission with feasibility warnings too, not only errors (docs/scenario.md)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (default: a bar with an ETA to completion)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures (default: draw them)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="swarmdrop", description="Carrier-launched UAV swarm flight stack "
                                "(README.md; docs/ has the details)")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    s = sub.add_parser("simulate", help="fly a scenario headless and write a run directory",
                       description="Fly a scenario in-process, far faster than real time (the same agent logic "
                                   "as the MAVLink fleet), and write metrics, figures and telemetry.")
    s.add_argument("config", help="scenario YAML, e.g. configs/paper_40.yaml")
    _out_options(s, "runs/<config name>")
    s.add_argument("--seed", type=int, help="override the config's random seed (>= 0)")
    s.add_argument("--check", action="store_true", help="exit 1 if any acceptance check fails")
    s.add_argument("--live", nargs="?", const=("127.0.0.1", 14650), default=None, type=_live_address, metavar="HOST:PORT",
                   help="fly at real-time pace and stream every published state to a console's swarm port "
                        "(swarmdrop console --swarm-bind HOST:PORT; default 127.0.0.1:14650 when given without "
                        "an address) (default: off, as fast as it goes)")
    s.set_defaults(func=_cmd_simulate)
    r = sub.add_parser("run", help="fly a scenario with the MAVLink SITL and one agent process per vehicle",
                       description="Start the SITL and one `swarmdrop agent` process per vehicle on 127.0.0.1, fly "
                                   "the scenario in real time, and write metrics, figures, agent logs and a .tlog. "
                                   "Exit codes: 0 done, 1 a check failed (--check), 2 bad input, 3 no agent left "
                                   "that could fly, 130 interrupted.")
    r.add_argument("config", help="scenario YAML, e.g. configs/paper_40.yaml")
    _out_options(r, "runs/<config name>_fleet")
    from companion.link.dialects import DIALECTS

    r.add_argument("--dialect", choices=sorted(DIALECTS), default="px4",
                   help="autopilots of the fleet (default px4)")
    r.add_argument("--lockstep", action="store_true",
                   help="deterministic: simulation time waits for every agent (default: real time)")
    r.add_argument("--signing", action="store_true",
                   help="MAVLink 2 signing (required) on every link, with a fresh key in the run directory "
                        "(default off)")
    r.add_argument("--output", choices=("acceleration", "attitude"), default="acceleration",
                   help="what the agents send: acceleration (SET_POSITION_TARGET_LOCAL_NED) or attitude "
                        "(SET_ATTITUDE_TARGET: attitude and thrust) (default acceleration)")
    r.add_argument("--rate", type=float, default=50.0, metavar="HZ",
                   help="agents' setpoint rate, Hz, above 2 and up to 400 (default 50)")
    r.add_argument("--base-port", type=int, default=None, metavar="P",
                   help="first of 3N+1 consecutive UDP ports on 127.0.0.1, all within 65535 (default: free ones, "
                        "found)")
    r.add_argument("--kill-agent", action="append", default=[], metavar="ID@T",
                   help="kill agent ID (0-based) at simulation time T s, before the scenario's duration_s (fault "
                        "injection; repeatable; default none)")
    r.add_argument("--fix-delay-max", type=float, default=0.0, metavar="S",
                   help="vehicles get their first GNSS fix (EKF origin) at random times up to this, s, 0 or more "
                        "(default 0)")
    r.add_argument("--agent-nice", type=int, default=5, metavar="N",
                   help="niceness added to agents, 0 to 19, so the SITL keeps priority (default 5)")
    r.add_argument("--agent-python", default=None, metavar="PATH",
                   help="the Python the agents run on, e.g. PATH/bin/python of a venv with only the onboard install "
                        "(pip install swarmdrop) (default: this one)")
    r.add_argument("--check", action="store_true", help="exit 1 if any acceptance check fails")
    r.add_argument("--no-console", action="store_true",
                   help="do not start the operator's console (default: `swarmdrop console` for the run, its address "
                        "printed; it needs the console extra: pip install 'swarmdrop[console]')")
    r.add_argument("--console-port", type=int, default=0, metavar="P",
                   help="the console page's HTTP port on 127.0.0.1 (default 0: a free one, printed)")
    r.set_defaults(func=_cmd_run)
    from sim_bridge.runs.sweep import MAX_BATCH  # (the module imports nothing heavy at load)

    w = sub.add_parser("sweep", help="Monte Carlo over seeds, headless, on Dask (or in-process with --workers 1)",
                       description="Fly a scenario headless once per seed (the seed draws release attitudes, gusts, "
                                   "link losses, faults), on a local or remote Dask cluster or in-process, and write "
                                   "runs.csv, summary.md, summary.json, failures/SEED.txt and fig_sweep.png. "
                                   "--rerun SEED replays one seed with its full run directory. Exit codes: 0 done, "
                                   "1 a run crashed (or, with --check, missed the target), 2 bad input, "
                                   "130 interrupted.")
    w.add_argument("config", help="scenario YAML, e.g. configs/paper_40.yaml")
    w.add_argument("--seeds", type=int, default=10,
                   help="number of seeds (from the config's seed, or --first-seed) (default 10)")
    w.add_argument("--first-seed", type=int, default=None, metavar="S",
                   help="first seed (default: the config's seed)")
    w.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="local Dask worker processes (default: one per core; 1 = in-process, no Dask needed)")
    w.add_argument("--address", default=None,
                   help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local cluster, or none "
                        "with --workers 1)")
    w.add_argument("--batch", type=int, default=MAX_BATCH, metavar="B",
                   help=f"at most B seeds flown side by side per task (default {MAX_BATCH}; the same results, "
                        "less time per run; 1 = one run per task)")
    w.add_argument("--rerun", type=int, default=None, metavar="SEED",
                   help="replay one seed in-process, writing its full run directory and figures (default: sweep; "
                        "the directory defaults to runs/<config name>_sweep/rerun_SEED)")
    w.add_argument("--out", metavar="DIR", help="results directory (default runs/<config name>_sweep); must be "
                   "empty or new")
    w.add_argument("--overwrite", action="store_true",
                   help="clear a non-empty --out of an earlier run's files first (default: refuse it)")
    w.add_argument("--strict", action="store_true", help="refuse a mission with feasibility warnings too "
                   "(default: warnings are printed)")
    w.add_argument("--check", action="store_true",
                   help="exit 1 unless every run met the target (healthy vehicles finish, no collision); "
                        "without it (default), exit 1 only if a run crashed")
    w.add_argument("--quiet", action="store_true", help="no progress bar (default: a bar)")
    w.add_argument("--no-figures", action="store_true", help="skip fig_sweep.png (default: draw it)")
    w.set_defaults(func=_cmd_sweep)
    from companion.node import cli as agent_cli
    from sim_bridge.sitl import cli as sitl_cli
    from swarmdrop.console import cli as console_cli  # (argparse only: aiohttp is imported when it runs)

    sitl_cli.add_parser(sub)
    agent_cli.add_parser(sub)
    from companion.node import preflight

    preflight.add_parser(sub)
    console_cli.add_parser(sub)
    return p


def _options_taking_a_leading_dash(argv: list[str]) -> list[str]:
    """`--kill-agent -1@5` as `--kill-agent=-1@5`: argparse takes a token that starts with '-'
    (and is not a plain negative number) for an option, and would say "expected one
    argument"; joined, the value reaches parse_kill, which names what is wrong with it."""
    out: list[str] = []
    it = iter(range(len(argv)))
    for i in it:
        tok = argv[i]
        if tok == "--":
            out += argv[i:]
            break
        if tok == "--kill-agent" and i + 1 < len(argv) and argv[i + 1].startswith("-") and "@" in argv[i + 1]:
            out.append(f"--kill-agent={argv[i + 1]}")
            next(it, None)
            continue
        out.append(tok)
    return out


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; its exit code. Ctrl-C anywhere (also while the packages load)
    ends it with one line and EXIT_INTERRUPTED, never a traceback."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        if argv and argv[0] == "agent":  # onboard: import nothing of the simulators
            from companion.node.cli import main as agent_main

            return agent_main(argv[1:])
        if argv and argv[0] == "preflight":  # onboard too
            from companion.node.preflight import main as preflight_main

            return preflight_main(argv[1:])
        args = build_parser().parse_args(_options_taking_a_leading_dash(argv))
        extra = EXTRA_OF.get(argv[0]) if argv else None
        missing = missing_packages(extra) if extra is not None else []
        if missing:
            extras = "sim,sweep" if argv[0] == "sweep" else extra  # (Dask too, for a sweep on a cluster)
            print(f"swarmdrop {argv[0]}: needs the '{extra}' extra, not installed here (missing: "
                  f"{', '.join(missing)}); install it with: pip install 'swarmdrop[{extras}]' (from a clone of the "
                  f"repository: pip install '.[{extras}]'). `swarmdrop agent` needs none of it.", file=sys.stderr)
            return 2
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("\nswarmdrop: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
