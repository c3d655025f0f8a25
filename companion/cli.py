"""The `swarmdrop` console script."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from companion.config import ConfigError


def _cmd_simulate(args: argparse.Namespace) -> int:
    from sim_bridge.simulate import load_scenario, simulate, summary_lines

    try:
        cfg = load_scenario(args.config, args.seed)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path("runs") / Path(args.config).stem
    metrics = simulate(cfg, out, progress=not args.quiet, figures=False if args.no_figures else None)
    print("\n".join(summary_lines(metrics, out)))
    if args.check and not all(metrics["checks"].values()):
        return 1
    return 0


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
    try:
        from sim_bridge.sitl import cli as sitl_cli
    except ImportError:  # the SITL is optional at import time (issue 3)
        sitl_cli = None
    if sitl_cli is not None and hasattr(sitl_cli, "add_parser"):
        sitl_cli.add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
