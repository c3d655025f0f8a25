"""`swarmdrop sitl --vehicles N [--config FILE] [--speed X] [--lockstep] [--tlog FILE] ...`."""
from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (the CLI imports the SITL's heavy modules only when it runs)
    from sim_bridge.sitl.config import SitlConfig


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The SITL's options. Unset options keep the --config file's value (or the --scenario's),
    whose own defaults are the ones shown."""
    p.add_argument("--vehicles", "-n", type=int, default=None, metavar="N",
                   help="number of vehicles, 1-250 (default 1; --scenario: mission.n_vehicles)")
    p.add_argument("--config", default=None, metavar="FILE", help="YAML SitlConfig file (docs/sitl.md; default none)")
    from companion.link.dialects import DIALECTS

    p.add_argument("--dialect", choices=sorted(DIALECTS), default=None,
                   help="behave like PX4 or ArduCopter: HEARTBEAT, modes, parameters, setpoint rules (default px4)")
    p.add_argument("--speed", type=float, default=None, metavar="X",
                   help="simulation seconds per wall second, up to 1000 (default 1)")
    p.add_argument("--lockstep", action="store_true",
                   help="simulation time waits for the companions (default: free-running)")
    p.add_argument("--tlog", default=None, metavar="FILE",
                   help="write every frame sent and received to this .tlog (default: none)")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="random seed, >= 0: launch attitudes, GNSS fix times, wind, faults "
                        "(default 0; --scenario: its seed)")
    p.add_argument("--signing", choices=("off", "optional", "require"), default=None,
                   help="MAVLink 2 signing on every endpoint (default off; docs/signing.md)")
    p.add_argument("--signing-key", default=None, metavar="FILE",
                   help="the 32-byte signing key (64 hex digits), a file only its owner can read; needs "
                        "--signing optional|require (or signing.mode in --config) (default none)")
    p.add_argument("--remote-base-port", type=int, default=None, metavar="P",
                   help="vehicle k sends to this + k, stepping over the GCS port (default 14540)")
    p.add_argument("--local-base-port", type=int, default=None, metavar="P",
                   help="vehicle k listens on this + k; 0 = ephemeral ports (default 18570)")
    p.add_argument("--gcs", action="store_true", help="enable the shared GCS endpoint (default off)")
    p.add_argument("--gcs-port", type=int, default=None, metavar="P", help="shared GCS remote port (default 14550)")
    p.add_argument("--launch", choices=("ground", "carrier"), default=None,
                   help="vehicles start on the ground or docked on the carrier "
                        "(default ground; --scenario: mission.launch)")
    p.add_argument("--scenario", default=None, metavar="CONFIG",
                   help="scenario YAML (swarmdrop simulate): take vehicle count, airframe, gains, carrier path, "
                        "seed, home (mission.origin), launch (mission.launch) and the swarm link from it, and "
                        "record the mission (--record) (default none)")
    p.add_argument("--strict", action="store_true",
                   help="with --scenario: refuse a mission with feasibility warnings too (docs/scenario.md)")
    p.add_argument("--medium-port", type=int, default=None, metavar="P",
                   help="run the simulated swarm radio on this UDP port, 0 = ephemeral (default: no radio)")
    p.add_argument("--medium-monitor", action="append", default=None, metavar="HOST:PORT",
                   help="the radio copies every state it takes to this monitor (an operator's console: swarmdrop "
                        "console --swarm-bind HOST:PORT) and forwards its SWARMDROP_PLAN/SLOTS to every vehicle; "
                        "needs --medium-port (repeatable; default none)")
    p.add_argument("--agent-base-port", type=int, default=None, metavar="P",
                   help="the radio sends vehicle k's copies to 127.0.0.1:this+k (default: where k sends from)")
    p.add_argument("--epoch", type=float, default=None, metavar="UNIX_S",
                   help="Unix time of simulation time 0 (SYSTEM_TIME; default: the wall clock at start)")
    p.add_argument("--start-when-attached", type=int, default=None, metavar="N",
                   help="hold the clock at 0 until this many vehicles have heard from a companion (default 0)")
    p.add_argument("--fix-delay-max", type=float, default=None, metavar="S",
                   help="first GNSS fix (and EKF origin) of each vehicle at a random time up to this, s (default 0)")
    p.add_argument("--record", default=None, metavar="DIR", help="with --scenario: write the recorded run "
                   "(run.json, telemetry.npz) to this directory when the SITL stops (default: no recording)")
    p.add_argument("--status", action="store_true", help="print a STATUS json line every second (default off)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop at this simulation time, s, above 0 (default: run until stopped)")
    p.add_argument("--stop-when-done", action="store_true",
                   help="with --scenario: stop once the mission is complete (completion_hold_s after; default off)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("sitl", help="multi-vehicle PX4/ArduPilot-like MAVLink SITL",
                              description="One process simulating N PX4- or ArduPilot-like quadrotors over "
                                          "MAVLink 2 (docs/sitl.md).")
    add_arguments(p)
    p.set_defaults(func=run)
    return p


def _pick(value, default):
    return default if value is None else value


def _looks_like_scenario(path: str) -> bool:
    """The file is YAML with a top-level `mission:` (a scenario given to --config)."""
    from companion.config import ConfigError, read_yaml

    try:
        data = read_yaml(path)
    except ConfigError:
        return False
    return isinstance(data, dict) and "mission" in data


def config_from_args(args) -> SitlConfig:
    """The SitlConfig from the command line: the --config file (or the defaults), its
    scenario section replaced by --scenario's, then the options given.

    Raises:
        ConfigError: bad config or scenario file, a scenario the SITL cannot fly, an option
            out of range (named with the reason: a --duration that is not above 0, ports past
            65535), or --signing-key with signing off.
    """
    import math

    from companion.config import ConfigError, replace
    from sim_bridge.scenario import load_scenario
    from sim_bridge.sitl.config import load_config

    duration = getattr(args, "duration", None)
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise ConfigError(f"--duration {duration:g}: must be a finite number of seconds above 0")
    try:
        cfg = load_config(args.config)
    except ConfigError as err:
        if args.config and _looks_like_scenario(args.config):
            raise ConfigError(f"{err}\n{args.config} is a scenario (it has a mission: section), not a SITL config "
                              f"(docs/sitl.md): pass it as --scenario {args.config}") from None
        raise
    sc = cfg.scenario
    if getattr(args, "scenario", None):
        sc = load_scenario(args.scenario, args.seed, runner="sitl", strict=getattr(args, "strict", False),
                           warn=lambda m: print(f"swarmdrop sitl: warning: {m}", file=sys.stderr))
    m = sc.mission
    sc = replace(sc, seed=_pick(args.seed, sc.seed), mission=replace(
        m, n_vehicles=_pick(args.vehicles, m.n_vehicles), launch=_pick(args.launch, m.launch)))
    t = cfg.time
    time_cfg = replace(t, speed=_pick(args.speed, t.speed), lockstep=args.lockstep or t.lockstep,
                       epoch_unix_s=_pick(args.epoch, t.epoch_unix_s),
                       start_when_attached=_pick(args.start_when_attached, t.start_when_attached))
    ep = cfg.endpoints
    ep = replace(
        ep, remote_base_port=_pick(args.remote_base_port, ep.remote_base_port),
        local_base_port=_pick(args.local_base_port, ep.local_base_port), gcs_enabled=args.gcs or ep.gcs_enabled,
        gcs_remote_port=_pick(args.gcs_port, ep.gcs_remote_port))
    spawn = replace(cfg.spawn, gps_fix_delay_max_s=_pick(args.fix_delay_max, cfg.spawn.gps_fix_delay_max_s))
    medium = cfg.medium
    if args.medium_port is not None:
        medium = replace(medium, enabled=True, port=args.medium_port)
    medium = replace(medium, agent_base_port=_pick(args.agent_base_port, medium.agent_base_port))
    monitors = getattr(args, "medium_monitor", None)
    if monitors:
        if not medium.enabled:
            raise ConfigError("--medium-monitor needs the radio (--medium-port P, or medium.enabled in --config)")
        medium = replace(medium, monitors=tuple(medium.monitors) + tuple(monitors))
    signing = replace(cfg.signing, mode=_pick(getattr(args, "signing", None), cfg.signing.mode),
                      key_file=_pick(getattr(args, "signing_key", None), cfg.signing.key_file))
    if getattr(args, "signing_key", None) is not None and signing.mode == "off":
        raise ConfigError(f"--signing-key {args.signing_key} needs --signing optional|require: with signing off "
                          "the key is not used and nothing is signed")
    return replace(
        cfg, scenario=sc, dialect=_pick(args.dialect, cfg.dialect), time=time_cfg, endpoints=ep, spawn=spawn,
        medium=medium, tlog_path=_pick(args.tlog, cfg.tlog_path), signing=signing)


def run(args) -> int:
    from companion.config import ConfigError
    from sim_bridge.sitl.server import SitlServer  # heavy (numba) import only when running

    for flag, given in (("--record", args.record), ("--stop-when-done", args.stop_when_done)):
        if given and not args.scenario:  # (refused before any port is bound)
            print(f"swarmdrop sitl: {flag} needs --scenario (a mission to record or to be done with)", file=sys.stderr)
            return 2
    try:
        cfg = config_from_args(args)
        server = SitlServer(cfg, record=bool(args.record))
    except (ConfigError, ValueError, OSError) as exc:
        print(f"swarmdrop sitl: bad configuration: {exc}", file=sys.stderr)
        return 2

    def ready(s: SitlServer) -> None:
        if s.medium is not None:  # (the server makes the radio; its monitors are set before the clock runs)
            s.medium.set_monitors(cfg.medium.monitor_addrs)
        mode = "lockstep" if cfg.time.lockstep else f"speed x{cfg.time.speed:g}"
        print(f"swarmdrop sitl: {cfg.vehicles} {cfg.dialect} vehicles, {mode}, tick {cfg.time.tick_s * 1000:g} ms",
              flush=True)
        for line in s.describe_endpoints():
            print(line, flush=True)
        for host, port in cfg.medium.monitor_addrs:
            print(f"swarm radio monitor: udp {host}:{port}", flush=True)
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
        from sim_bridge.reports.record import save_run

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
