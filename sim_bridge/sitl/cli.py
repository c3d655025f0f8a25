"""`swarmdrop sitl --vehicles N [--config FILE] [--speed X] [--lockstep] [--tlog FILE]`."""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import sys

from sim_bridge.sitl.config import SitlConfig, load_config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicles", "-n", type=int, default=None, help="number of vehicles (default 1)")
    p.add_argument("--config", default=None, help="YAML SitlConfig file")
    p.add_argument("--speed", type=float, default=None, help="simulation speed factor (default 1)")
    p.add_argument("--lockstep", action="store_true", help="advance only when offboard setpoints arrived")
    p.add_argument("--tlog", default=None, help="write every frame sent and received to this .tlog")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--remote-base-port", type=int, default=None, help="vehicle k sends to this + k")
    p.add_argument("--local-base-port", type=int, default=None, help="vehicle k listens on this + k")
    p.add_argument("--gcs", action="store_true", help="enable the shared GCS endpoint")
    p.add_argument("--gcs-port", type=int, default=None, help="shared GCS remote port (default 14550)")
    p.add_argument("--launch", choices=("ground", "carrier"), default=None)
    p.add_argument("--scenario", default=None,
                   help="scenario YAML (swarmdrop simulate): take vehicle count, airframe, gains, carrier path "
                        "and seed from it and launch from the carrier")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("sitl", help="multi-vehicle PX4-like MAVLink SITL")
    add_arguments(p)
    p.set_defaults(func=run)
    return p


def from_scenario(cfg: SitlConfig, path: str) -> SitlConfig:
    """The scenario's fleet, airframe, inner loop, carrier path and seed, launched from the carrier."""
    from sim_bridge.simulate import load_scenario

    sc = load_scenario(path)
    ground = sc.physics.ground_z_m if sc.physics.ground_z_m is not None else cfg.ground_z_m
    return dataclasses.replace(cfg, vehicles=sc.mission.n_vehicles, seed=sc.seed, vehicle=sc.vehicle,
                               inner_loop=sc.inner_loop, carrier=sc.carrier, ground_z_m=ground,
                               spawn=dataclasses.replace(cfg.spawn, launch="carrier"))


def config_from_args(args) -> SitlConfig:
    cfg = load_config(args.config)
    if getattr(args, "scenario", None):
        cfg = from_scenario(cfg, args.scenario)
    time_cfg = dataclasses.replace(cfg.time, speed=args.speed if args.speed is not None else cfg.time.speed,
                                   lockstep=args.lockstep or cfg.time.lockstep)
    ep = cfg.endpoints
    ep = dataclasses.replace(
        ep,
        remote_base_port=args.remote_base_port if args.remote_base_port is not None else ep.remote_base_port,
        local_base_port=args.local_base_port if args.local_base_port is not None else ep.local_base_port,
        gcs_enabled=args.gcs or ep.gcs_enabled,
        gcs_remote_port=args.gcs_port if args.gcs_port is not None else ep.gcs_remote_port)
    spawn = cfg.spawn if args.launch is None else dataclasses.replace(cfg.spawn, launch=args.launch)
    return dataclasses.replace(
        cfg, vehicles=args.vehicles if args.vehicles is not None else cfg.vehicles,
        seed=args.seed if args.seed is not None else cfg.seed, time=time_cfg, endpoints=ep, spawn=spawn,
        tlog_path=args.tlog if args.tlog is not None else cfg.tlog_path)


def run(args) -> int:
    from sim_bridge.sitl.server import SitlServer  # heavy (numba) import only when running

    try:
        cfg = config_from_args(args)
    except (ValueError, OSError) as exc:
        print(f"swarmdrop sitl: bad configuration: {exc}", file=sys.stderr)
        return 2
    server = SitlServer(cfg)

    def ready(s: SitlServer) -> None:
        mode = "lockstep" if cfg.time.lockstep else f"speed x{cfg.time.speed:g}"
        print(f"swarmdrop sitl: {cfg.vehicles} vehicles, {mode}, tick {cfg.time.tick_s * 1000:g} ms", flush=True)
        for line in s.describe_endpoints():
            print(line, flush=True)
        if cfg.tlog_path:
            print(f"tlog: {cfg.tlog_path}", flush=True)
        print("SITL READY", flush=True)

    try:
        asyncio.run(server.run(on_ready=ready, handle_signals=True))
    except OSError as exc:
        print(f"swarmdrop sitl: {exc}", file=sys.stderr)
        return 1
    print("swarmdrop sitl: stopped", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="swarmdrop sitl")
    add_arguments(p)
    return run(p.parse_args(argv))
