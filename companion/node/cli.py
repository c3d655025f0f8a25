"""`swarmdrop agent`: the companion process of one vehicle (docs/companion.md)."""
from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path

from companion.config import ConfigError
from companion.link.endpoints import EndpointError, parse_url


def _hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT")
    return host, int(port)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle-id", type=int, required=True, help="this vehicle's index in the mission (0-based)")
    p.add_argument("--autopilot", required=True,
                   help="autopilot link: udpin://0.0.0.0:14540, udpout://HOST:PORT, tcp://HOST:PORT or "
                        "serial:///dev/ttyAMA0:921600")
    p.add_argument("--mission", required=True, help="mission (scenario) YAML, e.g. configs/paper_40.yaml")
    p.add_argument("--swarm-bind", type=_hostport, default=("0.0.0.0", 0), metavar="HOST:PORT",
                   help="local address of the swarm socket (default any interface, ephemeral port)")
    p.add_argument("--swarm-peer", type=_hostport, action="append", default=[], metavar="HOST:PORT",
                   help="send this vehicle's state here (the radio medium, or each peer; repeatable)")
    p.add_argument("--sysid", type=int, default=None, help="own MAVLink system id (default vehicle-id + 1)")
    p.add_argument("--target-sysid", type=int, default=None,
                   help="the autopilot's system id (default: the first autopilot heard)")
    p.add_argument("--output", choices=("acceleration", "attitude"), default="acceleration",
                   help="acceleration: SET_POSITION_TARGET_LOCAL_NED; attitude: the position law (eq. 14-16) "
                        "runs here and SET_ATTITUDE_TARGET carries attitude and thrust")
    p.add_argument("--rate", type=float, default=50.0, help="setpoint rate, Hz (default 50)")
    p.add_argument("--plan-every", type=int, default=5,
                   help="run the planner every N setpoint ticks (and on every swarm publication); in between "
                        "the last plan is advanced along its acceleration (default 5: at 50 Hz setpoints and "
                        "10 Hz neighbour states, the planner runs when new neighbour states can have come)")
    p.add_argument("--launch", choices=("carrier", "ground"), default=None,
                   help="carrier: the autopilot recovers the thrown vehicle; ground: arm and take off "
                        "(default: the mission's launch)")
    p.add_argument("--takeoff-alt", type=float, default=None, help="ground launch: climb above home, m")
    p.add_argument("--lockstep", action="store_true",
                   help="the SITL's lockstep: answer every control tick, wait for the radio's tick marker")
    p.add_argument("--setup-timeout", type=float, default=120.0,
                   help="give up (exit 3/4) if the autopilot, its clock or its EKF origin are not there, s")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.add_argument("--log-file", default=None, help="also log to this file")
    p.add_argument("--no-stderr-log", action="store_true", help="log only to --log-file")
    p.add_argument("--signing", choices=("off", "optional", "require"), default="off",
                   help="MAVLink 2 signing on the autopilot and swarm links (docs/signing.md)")
    p.add_argument("--signing-key", default=None, metavar="FILE",
                   help="the 32-byte signing key (64 hex digits) in a file only its owner can read")
    p.add_argument("--stats", default=None, help="write statistics (latency, CPU, link counters) to this JSON")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("agent", help="the companion process of one vehicle (MAVLink)")
    add_arguments(p)
    return p


def process_age_s() -> float | None:
    """Seconds since this process was started (Linux /proc), None elsewhere."""
    import os

    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _logging(args) -> None:
    handlers: list[logging.Handler] = []
    if not args.no_stderr_log:
        handlers.append(logging.StreamHandler(sys.stderr))
    if args.log_file:
        handlers.append(logging.FileHandler(args.log_file))
    fmt = logging.Formatter(f"%(asctime)s agent{args.vehicle_id} %(levelname)s %(name)s: %(message)s")
    for h in handlers:
        h.setFormatter(fmt)
    root = logging.getLogger()
    root.handlers[:] = handlers
    root.setLevel(args.log_level)


def run(args) -> int:
    from companion.link.signing import SigningError
    from companion.node.config import NodeConfig, check_node, load_mission_file
    from companion.node.runner import AgentNode, ExitCode

    _logging(args)
    log = logging.getLogger("swarmdrop.agent")
    try:
        parse_url(args.autopilot)
        mf = load_mission_file(args.mission)
        cfg = check_node(NodeConfig(
            vehicle_id=args.vehicle_id, autopilot_url=args.autopilot, mission=mf, swarm_bind=args.swarm_bind,
            swarm_peers=args.swarm_peer, sysid=args.sysid, target_sysid=args.target_sysid, output=args.output,
            rate_hz=args.rate, plan_every=args.plan_every, launch=args.launch or mf.mission.launch,
            takeoff_alt_m=args.takeoff_alt if args.takeoff_alt is not None else mf.mission.takeoff_alt_m,
            lockstep=args.lockstep, setup_timeout_s=args.setup_timeout,
            stats_path=Path(args.stats) if args.stats else None, signing=args.signing,
            signing_key_file=Path(args.signing_key) if args.signing_key else None))
        node = AgentNode(cfg)
        node.startup_s = process_age_s()
    except (ConfigError, EndpointError, SigningError) as err:
        log.error("%s", err)
        return int(ExitCode.CONFIG)
    except OSError as err:
        log.error("cannot open a link: %s", err)
        return int(ExitCode.CONFIG)
    if not cfg.swarm_peers:
        log.warning("no --swarm-peer: this vehicle hears the swarm but nobody hears it")
    return int(asyncio.run(node.run()))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="swarmdrop agent", description="the companion process of one vehicle")
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
