"""`swarmdrop sitl --vehicles N [--config FILE] [--speed X] [--lockstep] [--tlog FILE] ...`."""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicles", "-n", type=int, default=None, help="number of vehicles (default 1)")
    p.add_argument("--config", default=None, help="YAML SitlConfig file")
    p.add_argument("--dialect", choices=("px4", "ardupilot"), default=None,
                   help="behave like PX4 (default) or ArduCopter: HEARTBEAT, modes, parameters, setpoint rules")
    p.add_argument("--speed", type=float, default=None, help="simulation speed factor (default 1)")
    p.add_argument("--lockstep", action="store_true", help="simulation time waits for the companions")
    p.add_argument("--tlog", default=None, help="write every frame sent and received to this .tlog")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--signing", choices=("off", "optional", "require"), default=None,
                   help="MAVLink 2 signing on every endpoint (default off; docs/signing.md)")
    p.add_argument("--signing-key", default=None, metavar="FILE",
                   help="the 32-byte signing key (64 hex digits), a file only its owner can read")
    p.add_argument("--remote-base-port", type=int, default=None, help="vehicle k sends to this + k")
    p.add_argument("--local-base-port", type=int, default=None, help="vehicle k listens on this + k")
    p.add_argument("--gcs", action="store_true", help="enable the shared GCS endpoint")
    p.add_argument("--gcs-port", type=int, default=None, help="shared GCS remote port (default 14550)")
    p.add_argument("--launch", choices=("ground", "carrier"), default=None)
    p.add_argument("--scenario", default=None,
                   help="scenario YAML (swarmdrop simulate): take vehicle count, airframe, gains, carrier path, "
                        "seed, home (mission.origin), launch (mission.launch) and the swarm link from it, and "
                        "record the mission (--record)")
    p.add_argument("--medium-port", type=int, default=None,
                   help="run the simulated swarm radio on this UDP port (0 = ephemeral)")
    p.add_argument("--agent-base-port", type=int, default=None,
                   help="the radio sends vehicle k's copies to 127.0.0.1:this+k (default: where k sends from)")
    p.add_argument("--epoch", type=float, default=None, help="Unix time of simulation time 0 (SYSTEM_TIME)")
    p.add_argument("--start-when-attached", type=int, default=None,
                   help="hold the clock at 0 until this many vehicles have heard from a companion")
    p.add_argument("--fix-delay-max", type=float, default=None,
                   help="first GNSS fix (and EKF origin) of each vehicle at a random time up to this, s")
    p.add_argument("--record", default=None, help="with --scenario: write the recorded run (run.json, "
                   "telemetry.npz) to this directory when the SITL stops")
    p.add_argument("--status", action="store_true", help="print a STATUS json line every second")
    p.add_argument("--duration", type=float, default=None, help="stop at this simulation time, s")
    p.add_argument("--stop-when-done", action="store_true",
                   help="with --scenario: stop once the mission is complete (completion_hold_s after)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("sitl", help="multi-vehicle PX4/ArduPilot-like MAVLink SITL")
    add_arguments(p)
    p.set_defaults(func=run)
    return p


def from_scenario(cfg, sc):
    """The scenario's fleet, airframe, inner loop, carrier path, seed, home, swarm link and the
    disturbed world (wind, estimator errors, rotor failures)."""
    from sim_bridge.sitl.config import HomeConfig

    ground = sc.physics.ground_z_m if sc.physics.ground_z_m is not None else cfg.ground_z_m
    o = sc.mission.origin
    home = cfg.home if o is None else HomeConfig(lat_deg=o.lat_deg, lon_deg=o.lon_deg, alt_amsl_m=o.alt_amsl_m)
    medium = dataclasses.replace(cfg.medium, link=sc.link, swarm_rate_hz=sc.mission.swarm.rate_hz)
    return dataclasses.replace(cfg, vehicles=sc.mission.n_vehicles, seed=sc.seed, vehicle=sc.vehicle,
                               inner_loop=sc.inner_loop, carrier=sc.carrier, ground_z_m=ground, home=home,
                               wind=sc.physics.wind, estimator=sc.estimator, faults=sc.faults,
                               medium=medium, spawn=dataclasses.replace(cfg.spawn, launch=sc.mission.launch))


def _pick(value, default):
    return default if value is None else value


def config_from_args(args):
    """SitlConfig (and the scenario, or None) from the command line.

    Raises:
        ConfigError: bad config or scenario file.
    """
    from sim_bridge.simulate import load_scenario
    from sim_bridge.sitl.config import load_config

    cfg = load_config(args.config)
    scenario = None
    if getattr(args, "scenario", None):
        scenario = load_scenario(args.scenario, args.seed)
        cfg = from_scenario(cfg, scenario)
    t = cfg.time
    time_cfg = dataclasses.replace(t, speed=_pick(args.speed, t.speed), lockstep=args.lockstep or t.lockstep,
                                   epoch_unix_s=_pick(args.epoch, t.epoch_unix_s),
                                   start_when_attached=_pick(args.start_when_attached, t.start_when_attached))
    ep = cfg.endpoints
    ep = dataclasses.replace(
        ep, remote_base_port=_pick(args.remote_base_port, ep.remote_base_port),
        local_base_port=_pick(args.local_base_port, ep.local_base_port), gcs_enabled=args.gcs or ep.gcs_enabled,
        gcs_remote_port=_pick(args.gcs_port, ep.gcs_remote_port))
    spawn = cfg.spawn if args.launch is None else dataclasses.replace(cfg.spawn, launch=args.launch)
    spawn = dataclasses.replace(spawn, gps_fix_delay_max_s=_pick(args.fix_delay_max, spawn.gps_fix_delay_max_s))
    medium = cfg.medium
    if args.medium_port is not None:
        medium = dataclasses.replace(medium, enabled=True, port=args.medium_port)
    medium = dataclasses.replace(medium, agent_base_port=_pick(args.agent_base_port, medium.agent_base_port))
    cfg = dataclasses.replace(
        cfg, vehicles=_pick(args.vehicles, cfg.vehicles), dialect=_pick(args.dialect, cfg.dialect),
        seed=_pick(args.seed, cfg.seed), time=time_cfg, endpoints=ep, spawn=spawn, medium=medium,
        tlog_path=_pick(args.tlog, cfg.tlog_path),
        signing=dataclasses.replace(cfg.signing, mode=_pick(getattr(args, "signing", None), cfg.signing.mode),
                                    key_file=_pick(getattr(args, "signing_key", None), cfg.signing.key_file)))
    return cfg, scenario


def run(args) -> int:
    from companion.config import ConfigError
    from sim_bridge.sitl.server import SitlServer  # heavy (numba) import only when running

    try:
        cfg, scenario = config_from_args(args)
        server = SitlServer(cfg, scenario=scenario)
    except (ConfigError, ValueError, OSError) as exc:
        print(f"swarmdrop sitl: bad configuration: {exc}", file=sys.stderr)
        return 2
    if args.record and scenario is None:
        print("swarmdrop sitl: --record needs --scenario", file=sys.stderr)
        return 2

    def ready(s: SitlServer) -> None:
        mode = "lockstep" if cfg.time.lockstep else f"speed x{cfg.time.speed:g}"
        print(f"swarmdrop sitl: {cfg.vehicles} {cfg.dialect} vehicles, {mode}, tick {cfg.time.tick_s * 1000:g} ms",
              flush=True)
        for line in s.describe_endpoints():
            print(line, flush=True)
        if cfg.tlog_path:
            print(f"tlog: {cfg.tlog_path}", flush=True)
        print("SITL READY", flush=True)

    try:
        asyncio.run(server.run(on_ready=ready, handle_signals=True, status_out=sys.stdout if args.status else None,
                               stop_when_done=args.stop_when_done, stop_at_s=args.duration))
    except OSError as exc:
        print(f"swarmdrop sitl: {exc}", file=sys.stderr)
        return 1
    if args.record:
        from sim_bridge.record import save_run

        result = server.run_result()
        if result is None:  # Ctrl-C before the mission started: nothing to score, and no traceback
            print("swarmdrop sitl: stopped before the first recorded sample: no recording", flush=True)
        else:
            out = Path(args.record)
            out.mkdir(parents=True, exist_ok=True)
            save_run(result, out)
            print(f"recorded: {out}", flush=True)
    print("swarmdrop sitl: stopped", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="swarmdrop sitl")
    add_arguments(p)
    return run(p.parse_args(argv))
