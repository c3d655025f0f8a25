"""`swarmdrop console`: the operator's web page for a swarm (docs/console.md).

This module imports only argparse at load (the `swarmdrop` command builds every
subcommand's parser); the web stack (aiohttp) and the console's modules are imported
when the console runs, and a missing aiohttp is one clear line, not a traceback.
"""
from __future__ import annotations

import argparse
import asyncio
import signal
import sys

DEFAULT_HTTP_PORT = 8765
DEFAULT_SWARM_PORT = 14650
"""The console's swarm port by default (`swarmdrop simulate --live` sends there by default)."""
READY_LINE = "CONSOLE READY"
INSTALL_HINT = "pip install 'swarmdrop[console]'"


def _hostport(text: str) -> tuple[str, int]:
    from companion.node.cli import _hostport as agents_hostport  # the agent's HOST:PORT reader

    return agents_hostport(text)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from companion.link.signing import MODES

    src = p.add_argument_group("data sources")
    src.add_argument("--mission", metavar="FILE", default=None,
                     help="mission (scenario) YAML, read as `swarmdrop agent` reads it: vehicle count and sysids, "
                          "slots, obstacles, geofence, origin for the geodetic readout (default none: vehicles only; "
                          "commands need it)")
    src.add_argument("--swarm-bind", type=_hostport, default=("127.0.0.1", DEFAULT_SWARM_PORT), metavar="HOST:PORT",
                     help="listen for the swarm link's SWARMDROP_STATE / PLAN / SLOTS here: where a radio medium "
                          "copies states (swarmdrop sitl --medium-monitor), agents send them, or `swarmdrop simulate "
                          f"--live` streams (default 127.0.0.1:{DEFAULT_SWARM_PORT}; port 0: an ephemeral one)")
    src.add_argument("--swarm-peer", type=_hostport, action="append", default=[], metavar="HOST:PORT",
                     help="send commands here: the radio medium, or each agent (repeatable; default: the addresses "
                          "states come from)")
    src.add_argument("--gcs", metavar="URL", default=None,
                     help="a MAVLink link to the autopilots for mode, armed state and battery: udpin://HOST:PORT "
                          "(the SITL's shared GCS endpoint sends to it), tcp://HOST:PORT (a router), ... (default none)")
    src.add_argument("--replay", metavar="PATH", default=None,
                     help="replay a run directory (telemetry.npz of swarmdrop simulate or run) or a .tlog of "
                          "SWARMDROP_STATE frames, instead of the live link (default: live)")
    src.add_argument("--tlog", metavar="FILE", default=None,
                     help="write every swarm-link frame received to this .tlog (replay it with --replay) "
                          "(default none)")
    web = p.add_argument_group("the page")
    web.add_argument("--host", default="127.0.0.1",
                     help="serve the page on this address (default 127.0.0.1: this machine only; anyone who can "
                          "reach the page can command the swarm)")
    web.add_argument("--port", type=int, default=DEFAULT_HTTP_PORT,
                     help=f"HTTP port of the page, 0 = an ephemeral one (default {DEFAULT_HTTP_PORT})")
    web.add_argument("--frame-rate", type=float, default=20.0, metavar="HZ",
                     help="frames per second sent to each page, 1 to 60 (default 20)")
    cmd = p.add_argument_group("commands")
    cmd.add_argument("--no-commands", action="store_true",
                     help="a display only: send nothing on the swarm link (default: commands on when a mission is "
                          "given)")
    cmd.add_argument("--sysid", type=int, default=255,
                     help="the console's MAVLink system id as a ground station, 1-255 (default 255)")
    cmd.add_argument("--epoch", type=float, default=None, metavar="UNIX_S",
                     help="Unix time of mission time 0 (default: the first state heard, whole second; only time "
                          "differences reach a plan)")
    cmd.add_argument("--signing", choices=MODES, default="off",
                     help="MAVLink 2 signing on the swarm and GCS links, as the agents' --signing: require drops "
                          "unsigned states, and commands are signed (docs/signing.md) (default off)")
    cmd.add_argument("--signing-key", default=None, metavar="FILE",
                     help="the 32-byte signing key (64 hex digits) in a file only its owner can read; needs "
                          "--signing optional|require (default none)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "console", help="the operator's web page: live swarm picture, health, commands, replay",
        description="Serve the operator's page (a top-down map and side view of every vehicle, a vehicle table, fleet "
                    "health, swarm commands, replay) on http://127.0.0.1:PORT/. Live, it listens to the swarm link "
                    "(--swarm-bind) and optionally an autopilot link (--gcs); --replay opens a recorded run instead. "
                    f"Needs the console extra: {INSTALL_HINT}. Exit codes: 0 stopped (Ctrl-C, SIGTERM), "
                    "2 bad input or the extra missing.")
    add_arguments(p)
    p.set_defaults(func=run)
    return p


def _signing(args, crc_extra, link_id: int, sends: bool = True):
    """The signing layer of one link (None with --signing off), with the agents' key helpers
    (companion.link.signing). sends: the link signs what it sends (its timestamps are kept in
    KEY.timestamp-SYSID, as an agent keeps its own); the GCS link only checks."""
    from companion.link.signing import Signing, SigningError, TimestampStore, load_key

    if args.signing == "off":
        if args.signing_key:
            raise SigningError(f"--signing-key {args.signing_key} needs --signing optional|require")
        return None
    if not args.signing_key:
        raise SigningError(f"--signing {args.signing} needs --signing-key FILE")
    key = load_key(args.signing_key)
    store = TimestampStore(f"{args.signing_key}.timestamp-{args.sysid}" if sends else None)
    return Signing(args.signing, key, link_id=link_id, store=store, crc_extra=crc_extra)


CONSOLE_SWARM_LINK_ID = 2
CONSOLE_GCS_LINK_ID = 3
"""MAVLink 2 signing link ids of the console's links (agents use 0 and 1)."""


def build_feed(args, out=print):
    """The feed the arguments ask for (live or replay); prints what it listens on.

    Raises:
        ConfigError, SigningError, EndpointError, OSError: bad input (named).
    """
    from companion.config import ConfigError
    from swarmdrop.console.mission import load_mission

    mission = load_mission(args.mission) if args.mission else None
    if args.replay:
        from swarmdrop.console.feeds import ReplayFeed
        from swarmdrop.console.replay import open_recording

        rec, m = open_recording(args.replay, mission)
        out(f"swarmdrop console: replaying {rec.source}: {rec.n} vehicles, {rec.t[0]:.1f} .. {rec.t[-1]:.1f} s")
        return ReplayFeed(rec, m)
    from companion.link.endpoints import MavEndpoint, UdpLink, open_link
    from companion.link.msgdef import swarmdrop as sd
    from companion.link.wire import Codec
    from swarmdrop.console.commands import GROUND_COMPID, CommandError, CommandPanel
    from swarmdrop.console.feeds import LiveFeed
    from swarmdrop.console.live import FleetModel, GcsSource, SwarmSource
    from swarmdrop.console.mission import MissionInfo

    if not 1 <= args.sysid <= 255:
        raise ConfigError(f"--sysid {args.sysid}: a MAVLink system id is 1 to 255")
    info = mission or MissionInfo("", None, [])
    codec = Codec(sd)
    sw_sign = _signing(args, codec.crc_extra, CONSOLE_SWARM_LINK_ID)
    try:
        link = UdpLink(bind=args.swarm_bind, remote=None, learn_remote=False)
    except OSError as err:
        raise ConfigError(f"--swarm-bind {args.swarm_bind[0]}:{args.swarm_bind[1]}: {err.strerror or err}") from None
    ep = MavEndpoint(link, codec, args.sysid, GROUND_COMPID, signing=sw_sign)
    tlog = None
    if args.tlog:
        from companion.link.tlog import Tlog

        try:
            tlog = Tlog(args.tlog)
        except OSError as err:
            link.close()
            raise ConfigError(f"--tlog {args.tlog}: {err.strerror or err}") from None
    model = FleetModel(info)
    swarm = SwarmSource(ep, model, tlog)
    out(f"swarmdrop console: swarm link udp {args.swarm_bind[0]}:{link.local_port}"
        + (f", signing {args.signing}" if sw_sign is not None else ""))
    gcs = None
    if args.gcs:
        gcs_sign = _signing(args, codec.crc_extra, CONSOLE_GCS_LINK_ID, sends=False)
        try:
            glink = open_link(args.gcs, codec.crc_extra)
        except OSError as err:
            link.close()
            raise ConfigError(f"--gcs {args.gcs}: {err.strerror or err}") from None
        sysids = {s: k for k, s in enumerate(info.sysids)} if info.config is not None else \
            {k + 1: k for k in range(250)}
        gcs = GcsSource(MavEndpoint(glink, codec, args.sysid, GROUND_COMPID, signing=gcs_sign), sysids, model.capacity)
        port = getattr(glink, "local_port", None)
        out(f"swarmdrop console: gcs link {args.gcs}" + (f" (udp port {port})" if port is not None else ""))
    panel, why = None, "--no-commands"
    if not args.no_commands:
        try:
            panel = CommandPanel(info, ep, list(args.swarm_peer), swarm.peers, args.sysid, args.epoch)
        except CommandError as err:
            why = str(err)
            out(f"swarmdrop console: commands off: {why}")
    return LiveFeed(info, model, swarm, gcs, panel, why)


async def serve(args, feed, out=print) -> None:
    from swarmdrop.console.server import ConsoleServer

    server = ConsoleServer(feed, args.host, args.port, args.frame_rate)
    try:
        url = await server.start()
    except OSError as err:
        await server.close()
        raise OSError(err.errno, f"cannot serve the page on {args.host}:{args.port}: {err.strerror or err}") from None
    out(f"console: {url}")
    out(READY_LINE)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await server.close()


def run(args) -> int:
    def out(line: str) -> None:
        print(line, flush=True)

    try:
        import aiohttp  # noqa: F401
    except ImportError:
        print(f"swarmdrop console: the web stack is not installed: {INSTALL_HINT}", file=sys.stderr)
        return 2
    from companion.config import ConfigError
    from companion.link.endpoints import EndpointError
    from companion.link.signing import SigningError

    if not (1.0 <= args.frame_rate <= 60.0):
        print(f"swarmdrop console: --frame-rate {args.frame_rate:g}: from 1 to 60", file=sys.stderr)
        return 2
    if not 0 <= args.port <= 65535:
        print(f"swarmdrop console: --port {args.port}: a TCP port is 0 to 65535", file=sys.stderr)
        return 2
    if args.replay and (args.gcs or args.tlog):
        print("swarmdrop console: --replay shows a recording: --gcs and --tlog are for a live console", file=sys.stderr)
        return 2
    try:
        feed = build_feed(args, out)
        asyncio.run(serve(args, feed, out))
    except (ConfigError, SigningError, EndpointError, OSError) as err:
        print(f"swarmdrop console: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    out("swarmdrop console: stopped")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="swarmdrop console")
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
