"""`swarmdrop agent`: the companion process of one vehicle (docs/companion.md)."""
from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path
from typing import Callable

from companion.config import ConfigError
from companion.link.endpoints import EndpointError, parse_url


def _hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT")
    return host, int(port)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle-id", type=int, required=True,
                   help="this vehicle's index in the mission (0-based; required)")
    p.add_argument("--autopilot", required=True,
                   help="autopilot link: udpin://0.0.0.0:14540, udpout://HOST:PORT, tcp://HOST:PORT or "
                        "serial:///dev/ttyAMA0:921600 (required)")
    p.add_argument("--mission", required=True,
                   help="mission (scenario) YAML, e.g. configs/paper_40.yaml (required)")
    p.add_argument("--swarm-bind", type=_hostport, default=("0.0.0.0", 0), metavar="HOST:PORT",
                   help="local address of the swarm socket (default 0.0.0.0:0: any interface, an ephemeral port)")
    p.add_argument("--swarm-peer", type=_hostport, action="append", default=[], metavar="HOST:PORT",
                   help="send this vehicle's state here (the radio medium, or each peer; repeatable; default none: "
                        "nobody hears this vehicle)")
    p.add_argument("--sysid", type=int, default=None,
                   help="own MAVLink system id on both links (default: the mission's sysid of the vehicle, "
                        "vehicle-id + 1; peers expect that one)")
    p.add_argument("--target-sysid", type=int, default=None,
                   help="fly the autopilot with this system id although the mission assigns another to "
                        "--vehicle-id (an explicit override; default: the mission's, vehicle-id + 1, and the "
                        "agent refuses any other, exit 7)")
    p.add_argument("--output", choices=("acceleration", "attitude"), default="acceleration",
                   help="acceleration: SET_POSITION_TARGET_LOCAL_NED; attitude: the position law (eq. 14-16) "
                        "runs here and SET_ATTITUDE_TARGET carries attitude and thrust (default acceleration)")
    p.add_argument("--rate", type=float, default=50.0,
                   help="setpoint rate, Hz, above 2 and up to 400 (default 50)")
    p.add_argument("--plan-every", type=int, default=5,
                   help="run the planner every N setpoint ticks (and on every swarm publication); in between "
                        "the last plan is advanced along its acceleration (default 5: at 50 Hz setpoints and "
                        "10 Hz neighbour states, the planner runs when new neighbour states can have come)")
    p.add_argument("--launch", choices=("carrier", "ground"), default=None,
                   help="carrier: the autopilot recovers the thrown vehicle; ground: arm and take off "
                        "(default: the mission's mission.launch)")
    p.add_argument("--takeoff-alt", type=float, default=None,
                   help="ground launch: climb above home, m, above 0.5 and up to 500 (default: the mission's "
                        "mission.takeoff_alt_m)")
    p.add_argument("--lockstep", action="store_true",
                   help="the SITL's lockstep: answer every control tick, wait for the radio's tick marker "
                        "(default off)")
    p.add_argument("--setup-timeout", type=float, default=120.0,
                   help="give up (exit 3/4) if the autopilot (or its TCP server), its clock or its EKF origin "
                        "are not there within this, s, above 0 (default 120)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="log this level and above (default INFO)")
    p.add_argument("--log-file", default=None,
                   help="also log to this file (appended; its directory must exist; default none)")
    p.add_argument("--no-stderr-log", action="store_true", help="log only to --log-file (default: to stderr too)")
    p.add_argument("--signing", choices=("off", "optional", "require"), default="off",
                   help="MAVLink 2 signing on the autopilot and swarm links (docs/signing.md) (default off)")
    p.add_argument("--signing-key", default=None, metavar="FILE",
                   help="the 32-byte signing key (64 hex digits) in a file only its owner can read; needs "
                        "--signing optional|require (default none)")
    p.add_argument("--stats", default=None, metavar="FILE",
                   help="write statistics (latency, CPU, link counters) to this JSON every 10 s and at exit; its "
                        "directory must exist (default none)")
    p.add_argument("--set-loss-action", choices=("hold", "land"), default=None,
                   help="set what the autopilot does when this companion stops, before flight: hold (PX4 "
                        "COM_OBL_RC_ACT 5; ArduPilot GUIDED always holds) or land (PX4 COM_OBL_RC_ACT 4), and its "
                        "setpoint timeout (COM_OF_LOSS_T, GUID_TIMEOUT) down to the mission's swarm.loss.timeout_s "
                        "if longer; old values are logged (default: only read and verify them)")
    p.add_argument("--allow-drifting-loss", action="store_true",
                   help="fly although the autopilot's companion-loss parameters would leave the vehicle drifting, "
                        "returning home, falling, or beyond the mission's loss envelope (swarm.loss), where the "
                        "swarm's ghost does not cover it (a WARNING instead of refusing, exit 4) (default: refuse)")
    p.add_argument("--stop-unread-streams", action="store_true",
                   help="the autopilot link is this agent's alone: ask the autopilot to stop, on this link only, "
                        "every stream the agent does not read (ATTITUDE, GLOBAL_POSITION_INT, SYS_STATUS, ...), "
                        "which saves CPU; not behind a router that a ground station shares, whose view would "
                        "freeze (docs/companion.md, 'Streams') (default: leave the streams alone)")
    p.add_argument("--event-loop", choices=EVENT_LOOPS, default="auto",
                   help="the event loop to fly on: uvloop (libuv in C: less CPU on each of the 50+ wake-ups a "
                        "second), asyncio (the standard library's) or auto: uvloop where it is installed, else "
                        "asyncio (default auto)")
    p.add_argument("--strict", action="store_true",
                   help="refuse a mission with feasibility warnings too, not only errors (exit 2; "
                        "docs/scenario.md, 'Can it fly?') (default: warnings are logged)")


EVENT_LOOPS = ("auto", "uvloop", "asyncio")
"""--event-loop's choices."""


def event_loop_factory(choice: str) -> tuple[Callable[[], asyncio.AbstractEventLoop] | None, str]:
    """The event loop `swarmdrop agent` flies on (--event-loop).

    uvloop runs the loop's own work in C: the agent is woken 50-60 times a second (each
    control tick's telemetry, the supervisor, the streams), and the standard loop's Python
    turn on each wake-up was 7-16 % of a fleet agent's CPU (README, "Performance"). The
    agent's own code is the same on either: reader callbacks, call_later, tasks.

    Args:
        choice: "auto" (uvloop if it can be imported, else asyncio), "uvloop" or "asyncio".
    Returns:
        (a loop factory for asyncio.Runner, None for the standard one; the loop's name and version).
    Raises:
        ConfigError: "uvloop" was asked for and cannot be imported; an unknown choice.
    """
    if choice not in EVENT_LOOPS:
        raise ConfigError(f"--event-loop {choice!r}: expected one of {', '.join(EVENT_LOOPS)}")
    if choice != "asyncio":
        try:
            import uvloop
        except ImportError as err:
            if choice == "uvloop":
                raise ConfigError(f"--event-loop uvloop: uvloop cannot be imported ({err}); install it "
                                  "(pip install uvloop) or fly on --event-loop asyncio") from None
        else:
            return uvloop.new_event_loop, f"uvloop {uvloop.__version__}"
    return None, f"asyncio (Python {sys.version.split()[0]})"


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
    """Log to stderr (unless --no-stderr-log) and to --log-file.

    Raises:
        ConfigError: --log-file cannot be opened for appending (named, with the reason).
    """
    handlers: list[logging.Handler] = []
    if not args.no_stderr_log:
        handlers.append(logging.StreamHandler(sys.stderr))
    if args.log_file:
        try:
            handlers.append(logging.FileHandler(args.log_file))
        except OSError as err:
            raise ConfigError(f"--log-file {args.log_file}: cannot write there: {err.strerror or err}") from None
    fmt = logging.Formatter(f"%(asctime)s agent{args.vehicle_id} %(levelname)s %(name)s: %(message)s")
    for h in handlers:
        h.setFormatter(fmt)
    root = logging.getLogger()
    root.handlers[:] = handlers
    root.setLevel(args.log_level)


def node_config(args, warn: Callable[[str], None]):  # -> companion.node.config.NodeConfig
    """The node's checked configuration from the agent's arguments (add_arguments): the
    same for `swarmdrop agent` and `swarmdrop preflight`.

    Raises:
        ConfigError: a bad URL, mission file or value (named); EndpointError from the URL.
    """
    from companion.node.config import NodeConfig, check_node, load_mission_file

    parse_url(args.autopilot)
    mf = load_mission_file(args.mission)
    return check_node(NodeConfig(
        vehicle_id=args.vehicle_id, autopilot_url=args.autopilot, mission=mf, swarm_bind=args.swarm_bind,
        swarm_peers=args.swarm_peer, sysid=args.sysid, target_sysid=args.target_sysid, output=args.output,
        rate_hz=args.rate, plan_every=args.plan_every, launch=args.launch or mf.mission.launch,
        takeoff_alt_m=args.takeoff_alt if args.takeoff_alt is not None else mf.mission.takeoff_alt_m,
        lockstep=args.lockstep, setup_timeout_s=args.setup_timeout,
        stats_path=Path(args.stats) if args.stats else None, signing=args.signing,
        signing_key_file=Path(args.signing_key) if args.signing_key else None,
        allow_drifting_loss=args.allow_drifting_loss, set_loss_action=args.set_loss_action,
        stop_unread_streams=args.stop_unread_streams),
        strict=args.strict, warn=warn, source=str(args.mission))


def run(args) -> int:
    from companion.link.signing import SigningError
    from companion.node.runner import AgentNode, ExitCode, NodeFailure
    from companion.node.stats import check_writable

    try:
        _logging(args)
    except ConfigError as err:  # (no log yet: say it where the user looks)
        print(f"swarmdrop agent: error: {err}", file=sys.stderr)
        return int(ExitCode.CONFIG)
    log = logging.getLogger("swarmdrop.agent")
    try:
        factory, loop_name = event_loop_factory(args.event_loop)
        cfg = node_config(args, log.warning)
        if cfg.stats_path is not None:
            check_writable(cfg.stats_path)  # now, not in flight at the first write
        node = AgentNode(cfg)
        node.startup_s = process_age_s()
        node.event_loop = loop_name
    except (ConfigError, EndpointError, SigningError) as err:
        log.error("%s", err)
        return int(ExitCode.CONFIG)
    except NodeFailure as err:  # no TCP server within --setup-timeout (companion.node.setup.open_autopilot)
        log.error("%s", err)
        log.info("exit %d (%s)", int(err.code), err.code.name)
        return int(err.code)
    except OSError as err:
        log.error("cannot open a link (autopilot %s, swarm %s:%d): %s", args.autopilot, *args.swarm_bind, err)
        return int(ExitCode.CONFIG)
    if not cfg.swarm_peers:
        log.warning("no --swarm-peer: this vehicle hears the swarm but nobody hears it")
    log.info("event loop: %s", loop_name)
    with asyncio.Runner(loop_factory=factory) as runner:
        return int(runner.run(node.run()))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="swarmdrop agent", description="the companion process of one vehicle")
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
