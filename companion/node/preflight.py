"""`swarmdrop preflight`: is this companion ready to fly its vehicle? (docs/field-kit.md)

Takes the agent's own arguments and goes through what `swarmdrop agent` would do before it
launches, over the same links and with the same code (AgentNode, its VehicleLink, SwarmLink
and the set-up's parameter rules), but changes nothing on the vehicle: no arming, no mode
change, no parameter written (what the agent *would* write is reported), no state published
on the swarm link. The only command that alters the autopilot is the one the agent sends too:
SET_MESSAGE_INTERVAL for the streams it reads, on its own link.

Then it listens for `--listen` seconds: the rate at which LOCAL_POSITION_NED and
ATTITUDE_QUATERNION really arrive (a 57600-baud telemetry port cannot carry 50 Hz of both),
and who is heard on the swarm link (a neighbour flying as this vehicle's id is a failure).

Each check ends PASS, WARN or FAIL with one line that says what was found and, for a
failure, what to change. Exit 0 when nothing failed (warnings allowed), PREFLIGHT_FAILED
(8) when something did, CONFIG (2) for bad arguments, as the agent. `--json FILE` writes the
same as a PreflightReport.
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from companion.config import ConfigError
from companion.link.dialects.base import AfterLoss
from companion.link.enums import MavLandedState, MsgId
from companion.node.exits import ExitCode, NodeFailure
from companion.node.setup import (
    LOSS_PARAM_RETRIES,
    LOSS_PARAM_TIMEOUT_S,
    SHAPING_PARAM_RETRIES,
    SHAPING_PARAM_TIMEOUT_S,
)
from companion.node.setup_rules import loss_changes, loss_refusal, mission_epoch_s, off_site, telemetry_streams
from companion.node.vehicle import CommandError

log = logging.getLogger("swarmdrop.preflight")

PASS, WARN, FAIL = "PASS", "WARN", "FAIL"
PREFLIGHT_FAILED = 8
"""Exit status when a check failed (ExitCode's values 0-7 are the agent's)."""
LISTEN_S = 5.0
"""Default listening window for telemetry rates and neighbours, s."""
RATE_OK, RATE_POOR = 0.9, 0.5
"""Telemetry at this fraction of --rate or more passes; below RATE_POOR it fails."""
SETUP_TIMEOUT_S = 10.0
"""Preflight's default --setup-timeout (the agent's is 120 s: it may start before its autopilot)."""


@dataclass
class Check:
    """One preflight item: name, PASS / WARN / FAIL, and what was found."""

    name: str
    status: str
    detail: str


@dataclass
class PreflightReport:
    """Everything preflight found (`--json`)."""

    vehicle_id: int
    autopilot_url: str
    checks: list[Check] = field(default_factory=list)

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if c.status == FAIL]

    @property
    def warned(self) -> list[Check]:
        return [c for c in self.checks if c.status == WARN]

    def add(self, name: str, status: str, detail: str) -> None:
        self.checks.append(Check(name, status, detail))

    def as_dict(self) -> dict:
        return {"vehicle_id": self.vehicle_id, "autopilot_url": self.autopilot_url, "passed": not self.failed,
                "failures": len(self.failed), "warnings": len(self.warned),
                "checks": [dataclasses.asdict(c) for c in self.checks]}

    def text(self) -> str:
        width = max((len(c.name) for c in self.checks), default=0)
        lines = [f"swarmdrop preflight: vehicle {self.vehicle_id} on {self.autopilot_url}"]
        lines += [f"  {c.status}  {c.name:<{width}}  {c.detail}" for c in self.checks]
        verdict = "ready to fly" if not self.failed else "NOT ready: fix what failed"
        lines.append(f"{len(self.failed)} failed, {len(self.warned)} warning(s): {verdict}")
        return "\n".join(lines)


class Preflight:
    """The checks, on a constructed AgentNode (its links open) and the running event loop.

    Args:
        node: an AgentNode (never run: its ticks never start). listen_s: the listening window, s.
        report: where the checks go.
    """

    def __init__(self, node, listen_s: float, report: PreflightReport):
        self.node = node
        self.cfg = node.cfg
        self.listen_s = listen_s
        self.report = report
        self._lpn_ms: set[int] = set()
        self._att_ms: set[int] = set()
        self._counting = False
        """Listening: the telemetry stamps are being counted."""
        self.frames_in = self.signed_in = 0
        """Frames from the autopilot link, and how many of them were signed (_count_signed)."""
        self._count_signed()
        self._count_telemetry()

    def _count_signed(self) -> None:
        """Count the signed MAVLink 2 frames that reach the autopilot link (before signing checks):
        an autopilot that signs while this companion does not probably requires signing, and
        then ignores every command of ours."""
        link = self.node.ap_ep.link
        recv = link.recv

        def counted(*args, **kw):
            frames = recv(*args, **kw)
            for frame, _addr in frames:
                self.frames_in += 1
                if len(frame) > 2 and frame[0] == 0xFD and frame[2] & 0x01:  # MAVLink 2, incompat flag SIGNED
                    self.signed_in += 1
            return frames

        link.recv = counted

    def _count_telemetry(self) -> None:
        """Count every LOCAL_POSITION_NED and ATTITUDE_QUATERNION the vehicle link takes (by its
        stamp, once each), not one a read: a serial or TCP link delivers bursts in one read."""
        v = self.node.vehicle
        handle = v.handle_raw

        def counted(msgid: int, sysid: int, compid: int, w: tuple) -> None:
            handle(msgid, sysid, compid, w)
            if self._counting:
                if v.lpn is not None:
                    self._lpn_ms.add(v.lpn.time_boot_ms)
                if v.att is not None:
                    self._att_ms.add(v.att.time_boot_ms)

        v.handle_raw = counted  # type: ignore[method-assign]

    async def run(self) -> None:
        """Every check in order; one that cannot go on (no autopilot) ends the list there."""
        loop = asyncio.get_running_loop()
        fd = self.node.ap_ep.link.fileno()
        loop.add_reader(fd, self.node.tick.on_autopilot)  # (the agent's reader: not flying, it never ticks)
        try:
            if await self._autopilot():
                await self._streams_clock_origin()
                await self._parameters()
                await self._listen()
                self._vehicle_state()  # (after listening: EXTENDED_SYS_STATE has brought the landed state)
        finally:
            loop.remove_reader(fd)

    # ------------------------------------------------------------------ the autopilot
    async def _autopilot(self) -> bool:
        node, r = self.node, self.report
        setup, v = node.setup, node.vehicle
        t0 = time.monotonic()
        try:
            await setup.wait_for_autopilot()
        except NodeFailure as err:
            link = node.ap_ep.link
            hint = ""
            sg = node.ap_ep.signing
            dropped = 0 if sg is None else sg.counters.unsigned + sg.counters.bad_signature + sg.counters.replayed
            if err.code != ExitCode.NO_AUTOPILOT or (link.bytes_in and not link.frames_in):
                pass  # (the message says it: another sysid, or bytes without frames)
            elif dropped and sg is not None:
                c = sg.counters
                hint = (f" ({link.frames_in} frames came, and signing dropped them: {c.unsigned} unsigned, "
                        f"{c.bad_signature} with a bad signature, {c.replayed} replayed: does the autopilot sign with "
                        "this key? docs/field-kit.md, 'Install')")
            elif not link.bytes_in:
                hint = (" (nothing at all came: check the wiring or the address, and that the autopilot sends "
                        "MAVLink on that port)")
            r.add("autopilot", FAIL, f"{err}{hint}")
            return False
        d, hb = v.ap, v.hb
        assert hb is not None  # ours_heard
        r.add("autopilot", PASS, f"{d.name} autopilot sysid {v.target_sysid}, HEARTBEAT after "
                                 f"{time.monotonic() - t0:.1f} s, mode {d.mode_name(hb.custom_mode)}")
        return True

    def _signs_but_we_do_not(self) -> str:
        """A hint for an unanswered command: the autopilot signs its frames and we do not."""
        if self.node.ap_ep.signing is None and self.signed_in:
            return (f" ({self.signed_in} of the {self.frames_in} frames from the autopilot were signed: it probably "
                    "requires signing and ignores unsigned commands; pass --signing require --signing-key FILE)")
        return ""

    def _vehicle_state(self) -> None:
        v, r = self.node.vehicle, self.report
        if v.other_autopilots:  # (after listening: every sysid heard by then)
            r.add("other autopilots", WARN, "also on this link: sysid " + ", ".join(
                str(k) for k in sorted(v.other_autopilots)) + " (ignored: a router or a shared port?)")
        hb = v.hb
        assert hb is not None  # _autopilot
        if hb.armed and (hb.in_air or v.landed_state in (MavLandedState.MAV_LANDED_STATE_IN_AIR,
                                                          MavLandedState.MAV_LANDED_STATE_TAKEOFF,
                                                          MavLandedState.MAV_LANDED_STATE_LANDING)):
            r.add("vehicle state", FAIL, f"armed and {_landed(v.landed_state)}: the agent's set-up and launch are for a "
                                         "vehicle on the ground or on the carrier, not one already flying")
        elif hb.armed:
            r.add("vehicle state", WARN, f"ARMED ({_landed(v.landed_state)}): the agent will not arm it again")
        else:
            r.add("vehicle state", PASS, f"disarmed ({_landed(v.landed_state)})")

    async def _streams_clock_origin(self) -> None:
        node, cfg, r = self.node, self.cfg, self.report
        v = node.vehicle
        refused = []
        for msgid, interval in telemetry_streams(cfg.rate_hz):
            try:
                await v.set_message_interval(msgid, interval)
            except CommandError as err:
                refused.append(f"{msgid.name}: {err}")
        if refused:
            r.add("streams", FAIL, "SET_MESSAGE_INTERVAL refused or unanswered: " + "; ".join(refused)
                  + self._signs_but_we_do_not())
        else:
            r.add("streams", PASS, f"LOCAL_POSITION_NED and ATTITUDE_QUATERNION at {cfg.rate_hz:g} Hz, "
                                   "EXTENDED_SYS_STATE, SYSTEM_TIME accepted (rates measured below)")
        try:
            msg = await v.request_message(MsgId.SYSTEM_TIME)
        except CommandError as err:
            r.add("clock", FAIL, f"no SYSTEM_TIME: {err}; the agent takes its time from the autopilot's clock"
                  + self._signs_but_we_do_not())
        else:
            if v.unix_offset_us is None or not msg.time_unix_usec:
                r.add("clock", FAIL, "SYSTEM_TIME carries no Unix time (no GNSS time yet?): the agent waits for it "
                                     "and mission time cannot start")
            else:
                skew = msg.time_unix_usec * 1e-6 - time.time()
                r.add("clock", PASS if abs(skew) < 1.0 else WARN,
                      f"autopilot UTC {_utc(msg.time_unix_usec * 1e-6)}, {skew:+.2f} s from this computer's clock"
                      + ("" if abs(skew) < 1.0 else " (the agent uses the autopilot's; the logs' times will differ)"))
        try:
            await v.request_message(MsgId.GPS_GLOBAL_ORIGIN, timeout_s=1.0, retries=2)
        except CommandError:
            pass
        if v.offset_ned_m is None or v.origin_e7 is None:
            r.add("EKF origin", FAIL, "no GPS_GLOBAL_ORIGIN: the autopilot has no EKF origin yet (no GNSS fix?); "
                                      "the agent waits for it before it can place the vehicle in the mission frame"
                  + self._signs_but_we_do_not())
        else:
            lat, lon, alt = v.origin_e7
            off = v.offset_ned_m
            dist = math.hypot(float(off[0]), float(off[1]))
            far = off_site((float(off[0]), float(off[1]), float(off[2])), cfg.mission.mission.waypoints_ned_m)
            r.add("EKF origin", PASS if far is None else WARN,
                  f"{lat * 1e-7:.7f}, {lon * 1e-7:.7f}, {alt * 1e-3:.1f} m: {dist:.0f} m from the mission origin"
                  + ("" if far is None else " (far from the mission: see 'position')"))

    # ------------------------------------------------------------------ parameters
    async def _parameters(self) -> None:
        node, cfg, r = self.node, self.cfg, self.report
        setup, d = node.setup, node.vehicle.ap
        if not d.loss_params:
            r.add("companion loss", WARN, f"the {d.name} dialect does not say what its autopilot does if this "
                                          "companion stops: unchecked")
        else:
            values = await setup.read_params(d.loss_required_params, LOSS_PARAM_TIMEOUT_S, LOSS_PARAM_RETRIES)
            missing = [n for n in d.loss_required_params if n not in values]
            if missing:
                r.add("companion loss", FAIL, f"no answer for {', '.join(missing)}: the agent refuses to fly without "
                                              "knowing what the vehicle does if it stops" + self._signs_but_we_do_not())
            else:
                shaping = tuple(n for n in d.loss_params if n not in d.loss_required_params)
                values |= await setup.read_params(shaping, SHAPING_PARAM_TIMEOUT_S, SHAPING_PARAM_RETRIES)
                stock = [n for n in shaping if n not in values]
                self._loss(values, f" (no answer for {', '.join(stock)}: the {d.name} defaults assumed, as the agent "
                                   "does)" if stock else "")
        try:
            if cfg.output == "attitude":
                to_set = []
                for name, bits in d.attitude_params().items():
                    current = int(await node.vehicle.get_param(name))
                    if current & int(bits) != int(bits):
                        to_set.append(f"{name} {current} -> {current | int(bits)}")
                hover = await node.vehicle.get_param(d.hover_thrust_param)
                r.add("attitude output", WARN if to_set else PASS,
                      f"{d.hover_thrust_param} = {hover:.3f} (the agent estimates hover thrust from here)"
                      + ("; the agent will set " + ", ".join(to_set) if to_set else ""))
            elif d.loop_params:
                got = await setup.read_params(d.loop_params, SHAPING_PARAM_TIMEOUT_S, SHAPING_PARAM_RETRIES)
                stock = [n for n in d.loop_params if n not in got]
                parts = [", ".join(f"{n} = {got[n]:g}" for n in d.loop_params if n in got)] if got else []
                if stock:
                    parts.append(f"no answer for {', '.join(stock)}: the slot hold assumes the {d.name} defaults"
                                 + self._signs_but_we_do_not())
                r.add("position loops", WARN if stock else PASS, "; ".join(parts))
            if cfg.launch == "carrier":
                change = []
                for name, value in d.carrier_params().items():
                    now = await node.vehicle.get_param(name)
                    if now != value:
                        change.append(f"{name} {now:g} -> {value:g}")
                if change:
                    r.add("carrier launch", WARN, "the agent will set " + ", ".join(change))
                else:
                    r.add("carrier launch", PASS, ", ".join(f"{n} = {x:g}" for n, x in d.carrier_params().items())
                          or "no parameter to set")
        except CommandError as err:
            r.add("parameters", FAIL, f"{err}")

    def _loss(self, values: dict[str, float], stock: str) -> None:
        cfg, r, setup, d = self.cfg, self.report, self.node.setup, self.node.vehicle.ap
        envelope = cfg.mission.mission.swarm.loss
        will = stock
        if cfg.set_loss_action is not None:
            try:
                fix = loss_changes(d, AfterLoss(cfg.set_loss_action), values, envelope.timeout_s)
            except ValueError as err:
                r.add("companion loss", FAIL, f"--set-loss-action {cfg.set_loss_action}: {err}")
                return
            changes = {n: x for n, x in fix.items() if values.get(n) != x}
            if changes:
                will += " (after --set-loss-action writes " + ", ".join(
                    f"{n} {values[n]:g} -> {x:g}" if n in values else f"{n} = {x:g}" for n, x in changes.items()) + ")"
            values = {**values, **fix}
        loss = d.loss_behaviour(values)
        text = loss_refusal(setup.ap_name, d, loss, envelope)
        if text is None:
            r.add("companion loss", WARN if will else PASS, f"if this companion stops: {loss.describe()}{will}")
        elif cfg.allow_drifting_loss:
            r.add("companion loss", WARN, text.split(". Fix:")[0] + f" (--allow-drifting-loss: it flies anyway){will}")
        else:
            r.add("companion loss", FAIL, text + will)

    # ------------------------------------------------------------------ listening
    async def _listen(self) -> None:
        """Telemetry rates and the swarm link over the listening window."""
        node, cfg, r = self.node, self.cfg, self.report
        v, sw = node.vehicle, node.swarm
        if v.unix_offset_us is not None:
            sw.set_epoch(mission_epoch_s(v.unix_offset_us))  # (as set-up)
        self._lpn_ms.clear()
        self._att_ms.clear()
        self._counting = True
        loop = asyncio.get_running_loop()
        end = loop.time() + self.listen_s
        next_hb = loop.time()
        while loop.time() < end:
            if loop.time() >= next_hb:  # the companion's HEARTBEAT, as the agent sends it
                v.heartbeat()
                node.ap_ep.flush()
                next_hb += 1.0
            if v.unix_offset_us is not None:  # (the vehicle's clock, as the tick path sets it)
                sample = v.lpn or v.att
                sw.now_us = v.unix_us(sample.time_boot_ms) if sample is not None else int(time.time() * 1e6)
            sw.poll()
            await asyncio.sleep(0.1)
        self._counting = False
        sw.poll()
        rates = {"LOCAL_POSITION_NED": len(self._lpn_ms) / self.listen_s,
                 "ATTITUDE_QUATERNION": len(self._att_ms) / self.listen_s}
        for name, hz in rates.items():
            status = PASS if hz >= RATE_OK * cfg.rate_hz else WARN if hz >= RATE_POOR * cfg.rate_hz else FAIL
            hint = "" if status == PASS else f" of the {cfg.rate_hz:g} Hz asked: " + _rate_hint(
                name, hz, rates, cfg.rate_hz, cfg.autopilot_url) + self._signs_but_we_do_not()
            r.add(f"{name} rate", status, f"{hz:.1f} Hz over {self.listen_s:g} s{hint}")
        self._position()
        self._swarm()

    def _position(self) -> None:
        """Where the vehicle is in the mission frame, against where the mission flies: a wrong
        mission.origin (or a vehicle at another site) puts it kilometres away, and the agent
        would fly it there."""
        node, cfg, r = self.node, self.cfg, self.report
        v = node.vehicle
        if v.lpn is None or v.offset_ned_m is None:
            return  # (the EKF origin or the rate checks have said why)
        off = v.offset
        n, e, d = v.lpn.values[0] + off[0], v.lpn.values[1] + off[1], v.lpn.values[2] + off[2]
        far = off_site((n, e, d), cfg.mission.mission.waypoints_ned_m)  # (set-up's rule: check_site)
        if far is None:
            r.add("position", PASS, f"{n:.1f} m N, {e:.1f} m E of the mission origin")
        elif cfg.launch == "carrier":
            r.add("position", WARN, far + " (a carrier launch flies on: fine at another airfield before the carrier "
                                          "flies)")
        else:
            r.add("position", FAIL, far + " (the agent refuses it, exit 4)")

    def _swarm(self) -> None:
        node, cfg, r = self.node, self.cfg, self.report
        sw = node.swarm
        heard = [j for j, s in enumerate(sw.view.stamp_s[0].tolist()) if s == s and j != cfg.vehicle_id]
        bound = node.setup.swarm_bound()
        if sw.conflicts:
            r.add("swarm link", FAIL, f"{sw.conflicts} state(s) from {sw.last_conflict} claim this vehicle's id "
                                      f"{cfg.vehicle_id}: two vehicles would fly as one (check --vehicle-id on both); "
                                      f"heard {len(heard)} other vehicle(s)" + (f" ({_ids(heard)})" if heard else ""))
        elif heard:
            r.add("swarm link", PASS, f"on {bound}: heard {len(heard)} of {sw.view.n_vehicles - 1} other vehicles "
                                      f"({_ids(heard)})")
        else:
            r.add("swarm link", WARN, f"on {bound}: no other vehicle heard in {self.listen_s:g} s (fine alone on the "
                                      "bench; in the field, check the radio, --swarm-peer and the mission)")
        skipped = sw.ep.link.bytes_skipped
        if sw.rejected or sw.future or sw.ep.bad_frames or skipped:
            r.add("swarm traffic", WARN, f"dropped: {sw.rejected} rejected, {sw.future} stamped in the future, "
                                         f"{sw.ep.bad_frames} malformed frames, {skipped} bytes that were no frame "
                                         "(another mission, another program or a wrong clock on this port?)")


def _rate_hint(name: str, hz: float, rates: dict[str, float], asked_hz: float, url: str) -> str:
    """Why a stream comes slower than asked, as far as the rates tell."""
    other = max(x for k, x in rates.items() if k != name)
    if hz == 0.0 and name == "LOCAL_POSITION_NED" and other > 0.0:
        return ("none came while ATTITUDE_QUATERNION did: the autopilot has no local position yet (no GNSS fix, "
                "EKF not converged)")
    if other >= RATE_OK * asked_hz:
        return "the other stream comes at the rate asked, so the autopilot limits this one (its stream rate cap)"
    serial = url.lower().startswith(("serial:", "/dev/"))
    if serial:
        return ("a slow serial port (57600 baud carries about 5.7 kB/s, and 50 Hz of both streams need about "
                "5 kB/s besides the rest: use 921600), or lower --rate")
    return "the autopilot or a router between caps the rate (both streams are short), or lower --rate"


def _landed(state: int) -> str:
    """EXTENDED_SYS_STATE's landed state in words."""
    words: dict[int, str] = {MavLandedState.MAV_LANDED_STATE_ON_GROUND: "on the ground",
                             MavLandedState.MAV_LANDED_STATE_IN_AIR: "in the air",
                             MavLandedState.MAV_LANDED_STATE_TAKEOFF: "taking off",
                             MavLandedState.MAV_LANDED_STATE_LANDING: "landing"}
    return words.get(int(state), "landed state unknown")


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t))


def _ids(ids: list[int]) -> str:
    return ", ".join(str(j) for j in ids[:12]) + (", ..." if len(ids) > 12 else "")


def _local(report: PreflightReport, cfg, n_vehicles: int, loop_name: str, warnings: list[str]) -> None:
    """The checks that need no link: the mission, the host, signing, the swarm socket's peers."""
    report.add("mission", WARN if warnings else PASS,
               f"vehicle {cfg.vehicle_id} of {n_vehicles}, {cfg.launch} launch, {cfg.output} output at "
               f"{cfg.rate_hz:g} Hz" + (f"; {len(warnings)} feasibility warning(s): " + "; ".join(warnings)
                                        if warnings else ""))
    report.add("host", PASS, f"Python {sys.version.split()[0]}, event loop {loop_name}, {os.cpu_count()} CPU(s)")
    if cfg.signing == "off":
        report.add("signing", WARN, "off: anyone in radio range can send this vehicle's swarm link states and "
                                    "plans (docs/signing.md)")
    else:
        report.add("signing", PASS, f"{cfg.signing}, key {cfg.signing_key_file}")
    if not cfg.swarm_peers:
        report.add("swarm peers", WARN, "no --swarm-peer: this vehicle would hear the swarm but nobody would hear it")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from companion.node import cli
    cli.add_arguments(p)
    for action in p._actions:  # (preflight runs beside a powered autopilot: it need not wait as long)
        if action.dest == "log_level":  # (the report says it all; the log is for --log-level INFO)
            action.default = "WARNING"
            action.help = "log this level and above to stderr (default WARNING)"
        if action.dest == "setup_timeout":
            action.default = SETUP_TIMEOUT_S
            action.help = (f"wait this long for the autopilot's HEARTBEAT (or its TCP server), s (default "
                           f"{SETUP_TIMEOUT_S:g})")
    p.add_argument("--listen", type=float, default=LISTEN_S, metavar="S",
                   help=f"listen this long for telemetry rates and neighbours, s, 1 to 600 (default {LISTEN_S:g})")
    p.add_argument("--json", default=None, metavar="FILE",
                   help="also write the report as JSON to FILE ('-': standard output instead of the table)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("preflight", help="check a companion before flight: autopilot, streams, clock, "
                                                "EKF origin, loss parameters, swarm link (changes nothing)")
    add_arguments(p)
    return p


def run(args) -> int:
    """Preflight with parsed arguments; the exit status: 0, PREFLIGHT_FAILED, CONFIG for bad
    arguments, a --json, --stats or --log-file path that cannot be written, or a port in use,
    ERROR for an internal error (the report so far is still printed)."""
    from companion.link.endpoints import EndpointError
    from companion.link.signing import SigningError
    from companion.node import cli
    from companion.node.runner import AgentNode
    from companion.node.stats import check_writable

    warnings: list[str] = []
    try:
        cli._logging(args)  # (the agent's: --log-file is opened, or refused, as the agent would)
        if not 1.0 <= args.listen <= 600.0:
            raise ConfigError(f"--listen {args.listen:g}: expected 1 to 600 s")
        if args.json not in (None, "-"):
            _check_report_path(Path(args.json))
        factory, loop_name = cli.event_loop_factory(args.event_loop)
        cfg = cli.node_config(args, warnings.append)
        if cfg.stats_path is not None:
            check_writable(cfg.stats_path)  # (not written here: refused as the agent would refuse it)
    except (ConfigError, EndpointError, SigningError) as err:
        print(f"swarmdrop preflight: error: {err}", file=sys.stderr)
        return int(ExitCode.CONFIG)
    report = PreflightReport(cfg.vehicle_id, cfg.autopilot_url)
    # (the swarm link logs an identity conflict as the flying agent sees it, "avoiding it as an
    # obstacle"; here the report's swarm check says what it means)
    logging.getLogger("swarmdrop.swarm").setLevel(logging.CRITICAL)
    node = None
    code = 0
    previous = signal.signal(signal.SIGTERM, _interrupt)  # (a supervisor's stop: the partial report, as Ctrl-C)
    try:
        try:
            node = AgentNode(cfg)
        except NodeFailure as err:  # a TCP autopilot link with no server within --setup-timeout
            _local(report, cfg, cfg.mission.mission.n_vehicles, loop_name, warnings)
            report.add("autopilot", FAIL, str(err))
        except (ConfigError, EndpointError, SigningError, OSError) as err:
            print(f"swarmdrop preflight: error: cannot open a link (autopilot {args.autopilot}, swarm "
                  f"{args.swarm_bind[0]}:{args.swarm_bind[1]}): {err}", file=sys.stderr)
            return int(ExitCode.CONFIG)
        else:
            _local(report, cfg, node.mission.n, loop_name, warnings)
            with asyncio.Runner(loop_factory=factory) as runner:
                runner.run(Preflight(node, args.listen, report).run())
    except KeyboardInterrupt:
        report.add("interrupted", FAIL, "stopped before every check had run")
    except Exception as err:  # a bug, or an answer nobody foresaw: say so, and keep what was found
        log.exception("preflight failed")
        report.add("internal error", FAIL, f"{type(err).__name__}: {err} (a defect of swarmdrop: please report it)")
        code = int(ExitCode.ERROR)
    finally:
        signal.signal(signal.SIGTERM, previous)
        if node is not None:
            node.ap_ep.close()
            node.sw_ep.close()
    if args.json == "-":
        print(json.dumps(report.as_dict(), indent=1))
    else:
        print(report.text())
        if args.json:
            try:
                Path(args.json).write_text(json.dumps(report.as_dict(), indent=1) + "\n")
            except OSError as err:  # (checked at start; changed since)
                print(f"swarmdrop preflight: --json {args.json}: {err.strerror or err}", file=sys.stderr)
                return int(ExitCode.CONFIG)
    return code or (PREFLIGHT_FAILED if report.failed else 0)


def _check_report_path(path: Path) -> None:
    """Refuse a --json path the report could not be written to (a directory, a missing or
    read-only directory, a read-only file), before any check runs; nothing is created.

    Raises:
        ConfigError: naming the option, the path and the reason.
    """
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise ConfigError(f"--json {path}: is a directory, not a file")
    if not parent.is_dir():
        raise ConfigError(f"--json {path}: cannot write there: no directory {parent}")
    if not os.access(path if path.exists() else parent, os.W_OK):
        raise ConfigError(f"--json {path}: cannot write there: permission denied")


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="swarmdrop preflight",
                                description="check a companion before flight (docs/field-kit.md); changes nothing "
                                            "on the vehicle but the agent's own telemetry rates")
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
