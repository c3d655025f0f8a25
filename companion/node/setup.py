"""Connection set-up and launch: everything between opening the links and the first tick.

At construction (`link_signing`, `open_endpoints`): the signing layers of both links and
the sockets (a bad key, URL or port is a ConfigError: exit code CONFIG). A TCP autopilot
link whose server is not listening yet is retried until --setup-timeout, saying so every
WAIT_LOG_S (`open_autopilot`; NO_AUTOPILOT if none comes), as a UDP link waits for its
first HEARTBEAT.

Then `Setup.set_up`, as commands with timeouts and retries: wait for our autopilot's
HEARTBEAT (refusing another vehicle's autopilot: IDENTITY), ask for the telemetry
streams, the EKF origin and the clock, derive the mission epoch, set the parameters
the output and launch need, and read and verify the ones that decide what the autopilot
does if this companion stops (`verify_loss`: refused unless it stops and holds or lands,
docs/companion.md "Companion loss") (SETUP on failure). Every wait says at INFO what it waits
for, on which link, every WAIT_LOG_S. `Setup.launch` then arms for the carrier's throw,
or arms and takes off from the ground (LAUNCH on failure), calling `attach` when the
ticks are to start.
"""
from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import time
from collections.abc import AsyncIterator, Callable

from companion.config import ConfigError
from companion.link.dialects.base import AfterLoss, LossBehaviour, PositionLoop
from companion.link.endpoints import Link, MavEndpoint, UdpLink, open_link, parse_url
from companion.link.enums import MavCmd, MavComponent, MsgId
from companion.link.signing import Signing, SigningError, TimestampStore, load_key
from companion.link.wire import Codec
from companion.node.config import NodeConfig
from companion.node.exits import ExitCode, NodeFailure
from companion.node.setup_rules import (
    loss_changes,
    loss_refusal,
    mission_epoch_s,
    off_site,
    telemetry_streams,
)
from companion.node.streams import UnreadStreams
from companion.node.swarmlink import SwarmLink
from companion.node.vehicle import CommandError, VehicleLink

log = logging.getLogger("swarmdrop.agent")  # the agent's log lines keep one logger name

LAUNCH_RETRY_S = 1.0
LAUNCH_TIMEOUT_S = 60.0
WAIT_LOG_S = 3.0
SET_UP_LOG_TEXT = "set up in"
"""How the INFO line that ends set-up begins (the fuzz harness waits for it)."""
"""A set-up wait says what it waits for, on which link, this often (INFO)."""
IDENTITY_GRACE_S = 5.0
"""Only other autopilots heard on the link for this long (five of their 1 Hz HEARTBEATs,
none of ours): refuse (ExitCode.IDENTITY) rather than keep waiting."""
AUTOPILOT_LINK_ID, SWARM_LINK_ID = 0, 1
"""MAVLink 2 signing link ids of the node's two links."""
COMPANION = MavComponent.MAV_COMP_ID_ONBOARD_COMPUTER
"""Our component id on both links."""
LOSS_PARAM_TIMEOUT_S, LOSS_PARAM_RETRIES = 1.0, 3
"""Reading a parameter that decides the companion-loss action (as every parameter read)."""
SHAPING_PARAM_TIMEOUT_S, SHAPING_PARAM_RETRIES = 0.3, 2
"""Reading a braking limit: a real autopilot answers within milliseconds; one that does not
serve it (a simulator) costs 0.6 s once, and the stock value is assumed (a WARNING)."""


def link_signing(cfg: NodeConfig, crc_extra: Callable[[int], int | None]) -> tuple[Signing | None, Signing | None]:
    """Signing of the autopilot link and of the swarm link (None, None with --signing off):
    one key and one timestamp store for both.

    Args:
        cfg: --signing and --signing-key. crc_extra: the codec's (Codec.crc_extra).
    Raises:
        SigningError (a ConfigError for the CLI): no key file, or a missing or unsafe one.
    """
    if cfg.signing == "off":
        return None, None
    if cfg.signing_key_file is None:
        raise SigningError(f"signing {cfg.signing!r} needs --signing-key FILE")
    key = load_key(cfg.signing_key_file)
    store = TimestampStore(f"{cfg.signing_key_file}.timestamp-{cfg.own_sysid}")
    return (Signing(cfg.signing, key, link_id=AUTOPILOT_LINK_ID, store=store, crc_extra=crc_extra),
            Signing(cfg.signing, key, link_id=SWARM_LINK_ID, store=store, crc_extra=crc_extra))


def swarm_address(cfg: NodeConfig) -> str:
    """The swarm socket as given (--swarm-bind), for messages."""
    return f"{cfg.swarm_bind[0]}:{cfg.swarm_bind[1]}"


TCP_RETRY_S = 0.25
"""An autopilot link to a TCP server that is not listening yet is retried this often, s."""
TCP_WAIT_ERRNOS = frozenset({errno.ECONNREFUSED, errno.ETIMEDOUT, errno.ECONNRESET, errno.ECONNABORTED,
                             errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EAGAIN})
"""Connect errors that mean "the server is not there yet" (retried), not a bad address."""


def open_autopilot(cfg: NodeConfig, crc_extra: Callable[[int], int | None]) -> Link:
    """Open the autopilot link (--autopilot). A TCP server that is not there yet (the agent
    started before its autopilot or router) is waited for, as a UDP link waits for its first
    HEARTBEAT: the connection is retried every TCP_RETRY_S until --setup-timeout, and the wait
    is logged at INFO ("waiting for TCP server on URL: N s") every WAIT_LOG_S.

    Raises:
        ConfigError: the link cannot be opened (a serial device, a port in use, ...).
        NodeFailure(NO_AUTOPILOT): no TCP server accepted within --setup-timeout (exit 3, as a
            UDP link that hears no HEARTBEAT).
    """
    url = cfg.autopilot_url
    t0 = time.monotonic()
    deadline = t0 + cfg.setup_timeout_s
    next_log = t0 + WAIT_LOG_S
    tries = 0
    while True:
        try:
            link = open_link(url, crc_extra, connect_timeout_s=max(0.05, min(5.0, deadline - time.monotonic())),
                             peer_ids=(cfg.autopilot_sysid, MavComponent.MAV_COMP_ID_AUTOPILOT1))
        except OSError as err:
            if parse_url(url).scheme != "tcp" or err.errno not in TCP_WAIT_ERRNOS:
                raise ConfigError(f"autopilot link {url}: cannot open it: {err.strerror or err}") from None
            tries += 1
            now = time.monotonic()
            why = os.strerror(err.errno)
            if now >= deadline:
                raise NodeFailure(ExitCode.NO_AUTOPILOT, f"no TCP server accepted a connection on {url} within "
                                  f"--setup-timeout {cfg.setup_timeout_s:g} s ({why})") from None
            if tries == 1:
                log.info("waiting for TCP server on %s (%s): retrying for up to %g s (--setup-timeout)", url, why,
                         cfg.setup_timeout_s)
            elif now >= next_log:
                log.info("waiting for TCP server on %s: %.0f s", url, now - t0)
                next_log += WAIT_LOG_S
            time.sleep(min(TCP_RETRY_S, deadline - now))  # (a retry interval, in a process that has nothing else to do)
            continue
        if tries:
            log.info("connected to the TCP server on %s after %.1f s", url, time.monotonic() - t0)
        return link


def open_endpoints(cfg: NodeConfig, codec: Codec, ap_sign: Signing | None, sw_sign: Signing | None
                   ) -> tuple[MavEndpoint, MavEndpoint]:
    """Open the autopilot link (--autopilot) and bind the swarm socket (--swarm-bind).

    Returns:
        (autopilot endpoint, swarm endpoint), both as our sysid and the companion component.
    Raises:
        ConfigError: a link cannot be opened (the message names it; nothing is left open).
        NodeFailure(NO_AUTOPILOT): no TCP server within --setup-timeout (open_autopilot).
    """
    ap_link = open_autopilot(cfg, codec.crc_extra)
    try:
        sw_link = UdpLink(bind=cfg.swarm_bind, remote=None, learn_remote=False)
    except OSError as err:
        ap_link.close()
        raise ConfigError(f"swarm link --swarm-bind {swarm_address(cfg)}: cannot bind: {err}") from None
    return (MavEndpoint(ap_link, codec, cfg.own_sysid, COMPANION, signing=ap_sign),
            MavEndpoint(sw_link, codec, cfg.own_sysid, COMPANION, signing=sw_sign))


class Setup:
    """Set-up and launch of one node (runs on the node's event loop).

    Args:
        cfg: the node's configuration. vehicle: the autopilot link. swarm: the swarm link
            (set-up gives it the mission epoch). start_wall: time.monotonic() at node
            construction (set-up time is measured from it).

    After set_up: epoch_us, hover_thrust and ready_wall_s hold what it found.
    """

    def __init__(self, cfg: NodeConfig, vehicle: VehicleLink, swarm: SwarmLink, start_wall: float):
        self.cfg = cfg
        self.vehicle = vehicle
        self.swarm = swarm
        self.start_wall = start_wall
        self.ap_name = f"autopilot sysid {cfg.autopilot_sysid} on {cfg.autopilot_url}"
        """Which autopilot, on which link (every error about it names both)."""
        self.epoch_us = 0
        """Unix time of mission time 0, µs."""
        self.hover_thrust = float("nan")
        """The autopilot's hover thrust parameter (attitude output only), NaN otherwise."""
        self.ready_wall_s = float("nan")
        """From node construction to the end of set-up, s (NaN: not set up)."""
        self.loss: LossBehaviour | None = None
        """What the autopilot does if this companion stops (verify_loss; None: its dialect does not say)."""
        self.loop: PositionLoop | None = None
        """The autopilot's position-loop gains (acceleration output; None: not read, or its
        dialect does not say): the slot-hold integral is driven into it (companion.slot_hold)."""
        self.streams: UnreadStreams | None = None
        """--stop-unread-streams: what it stopped (from the end of set-up)."""
        self.streams_task: asyncio.Future | None = None

    def swarm_bound(self) -> str:
        """The swarm socket's address as bound (the port the OS chose for --swarm-bind HOST:0)."""
        link = self.swarm.ep.link
        port = link.local_port if isinstance(link, UdpLink) else self.cfg.swarm_bind[1]
        return f"{self.cfg.swarm_bind[0]}:{port}"

    # ------------------------------------------------------------------ waiting
    @contextlib.asynccontextmanager
    async def announced(self, what: str) -> AsyncIterator[None]:
        """Say at INFO every WAIT_LOG_S what set-up waits for, on which link, and for how long."""
        loop = asyncio.get_running_loop()
        t0 = loop.time()

        async def tell() -> None:
            while True:
                await asyncio.sleep(WAIT_LOG_S)
                log.info("waiting for %s on %s: %.0f s", what, self.cfg.autopilot_url, loop.time() - t0)

        task = asyncio.ensure_future(tell())
        try:
            yield
        finally:
            task.cancel()

    async def wait(self, cond: Callable[[], bool], timeout_s: float, what: str, code: ExitCode) -> None:
        """Poll cond every 50 ms (announced) until it holds.

        Raises:
            NodeFailure(code): not within timeout_s; or whatever cond raises.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        async with self.announced(what):
            while not cond():
                if loop.time() > deadline:
                    raise NodeFailure(code, f"{what}: nothing from {self.ap_name} within {timeout_s:g} s")
                await asyncio.sleep(0.05)

    def ours_heard(self) -> bool:
        """Our autopilot's HEARTBEAT has come.

        Raises:
            NodeFailure(IDENTITY): only autopilots of other sysids have been heard, for
                IDENTITY_GRACE_S (or the set-up timeout if shorter).
        """
        v, cfg = self.vehicle, self.cfg
        if v.dialect is not None:
            return True
        if v.other_autopilots and asyncio.get_running_loop().time() - v.other_since > min(IDENTITY_GRACE_S,
                                                                                           cfg.setup_timeout_s):
            raise self._identity_failure()
        return False

    def _identity_failure(self) -> NodeFailure:
        v, cfg = self.vehicle, self.cfg
        others = ", ".join(str(k) for k in sorted(v.other_autopilots))
        how = "--target-sysid" if cfg.target_sysid is not None else "the mission"
        return NodeFailure(ExitCode.IDENTITY, (
            f"the autopilot on {cfg.autopilot_url} is sysid {others}, but vehicle {cfg.vehicle_id} flies "
            f"autopilot sysid {cfg.autopilot_sysid} ({how}): refusing to fly another vehicle's autopilot. "
            f"Check --vehicle-id and the link; pass --target-sysid N only if this autopilot is meant"))

    async def wait_for_autopilot(self) -> None:
        """Wait for our autopilot's HEARTBEAT (ours_heard), up to --setup-timeout.

        Raises:
            NodeFailure(IDENTITY): only autopilots of other sysids were heard (also when the
                timeout ends before IDENTITY_GRACE_S has passed since the first of them).
            NodeFailure(NO_AUTOPILOT): nothing of ours came (saying so if bytes came but no frame).
        """
        link = self.vehicle.ep.link
        try:
            await self.wait(self.ours_heard, self.cfg.setup_timeout_s, "HEARTBEAT", ExitCode.NO_AUTOPILOT)
        except NodeFailure as err:
            if err.code != ExitCode.NO_AUTOPILOT:
                raise
            if self.vehicle.other_autopilots:
                raise self._identity_failure() from None
            if link.bytes_in and not link.frames_in:
                raise NodeFailure(err.code, f"{err}: {link.bytes_in} bytes came but no MAVLink frame "
                                            "(a serial link at the wrong baud rate?)") from None
            raise

    # ------------------------------------------------------------------ set-up
    async def set_up(self) -> None:
        """Autopilot, streams, EKF origin, clock and parameters (module docstring).

        Raises:
            NodeFailure: NO_AUTOPILOT, IDENTITY or SETUP, the message says what is missing.
        """
        cfg, v = self.cfg, self.vehicle
        loop = asyncio.get_running_loop()
        if cfg.autopilot_sysid != cfg.assigned_sysid:
            log.warning("--target-sysid %d overrides the mission's sysid %d of vehicle %d: flying that autopilot as "
                        "vehicle %d", cfg.autopilot_sysid, cfg.assigned_sysid, cfg.vehicle_id, cfg.vehicle_id)
        log.info("waiting for HEARTBEAT of %s (vehicle %d), swarm link on %s", self.ap_name, cfg.vehicle_id,
                 self.swarm_bound())
        await self.wait_for_autopilot()
        d = v.ap
        try:
            async with self.announced("telemetry streams (SET_MESSAGE_INTERVAL)"):
                for msgid, interval in telemetry_streams(cfg.rate_hz):
                    await v.set_message_interval(msgid, interval)
                await v.request_message(MsgId.SYSTEM_TIME)
        except CommandError as err:
            raise NodeFailure(ExitCode.SETUP, f"telemetry streams of {self.ap_name}: {err}") from None
        deadline = loop.time() + cfg.setup_timeout_s
        async with self.announced("the EKF origin (GPS_GLOBAL_ORIGIN)"):
            while v.offset_ned_m is None:  # no origin before the autopilot's first GNSS fix
                try:
                    await v.request_message(MsgId.GPS_GLOBAL_ORIGIN, timeout_s=1.0, retries=1)
                except CommandError:
                    if loop.time() > deadline:
                        raise NodeFailure(ExitCode.SETUP, f"no GPS_GLOBAL_ORIGIN from {self.ap_name} within "
                                                          f"{cfg.setup_timeout_s:g} s: it has no EKF origin") from None
        await self.wait(lambda: v.unix_offset_us is not None, cfg.setup_timeout_s, "SYSTEM_TIME", ExitCode.SETUP)
        # Mission time is Unix time less a whole hour near the autopilot's boot: small floats;
        # every exchanged time is absolute (µs), so agents need not share this epoch.
        assert v.unix_offset_us is not None  # the wait above
        epoch_s = mission_epoch_s(v.unix_offset_us)
        self.epoch_us = epoch_s * 1_000_000
        self.swarm.set_epoch(epoch_s)  # now: the swarm link drops states until it knows the epoch
        await self.check_site()
        try:
            async with self.announced("parameters"):
                if cfg.output == "attitude":
                    for name, bits in d.attitude_params().items():
                        current = int(await v.get_param(name))
                        if current & int(bits) != int(bits):
                            await v.set_param(name, current | int(bits))
                    self.hover_thrust = await v.get_param(d.hover_thrust_param)
                    log.info("%s = %.3f", d.hover_thrust_param, self.hover_thrust)
                if cfg.launch == "carrier":
                    for name, value in d.carrier_params().items():
                        if await v.get_param(name) != value:
                            await v.set_param(name, value)
                self.loss = await self.verify_loss()
                if cfg.output == "acceleration" and d.loop_params:
                    self.loop = await self.read_loop()
        except CommandError as err:
            raise NodeFailure(ExitCode.SETUP, f"parameters of {self.ap_name}: {err}") from None
        if cfg.stop_unread_streams:
            self.streams = UnreadStreams(v.stop_stream, loop.time)
            v.unread = self.streams.seen
            self.vehicle.ep.on_unknown = v.unknown_frame
            self.streams_task = asyncio.ensure_future(self.streams.run())
        self.ready_wall_s = time.monotonic() - self.start_wall
        log.info("%s %.2f s: %s, %s, %s output at %g Hz, %s launch%s", SET_UP_LOG_TEXT, self.ready_wall_s, self.ap_name,
                 d.name, cfg.output, cfg.rate_hz, cfg.launch, ", lockstep" if cfg.lockstep else "")

    async def check_site(self) -> None:
        """Before any parameter is written: a vehicle kilometres from the mission (off_site) is
        refused for a ground launch; a carrier launch only warns (the vehicle may sit at another
        airfield until the carrier flies). With no LOCAL_POSITION_NED streamed yet it is asked
        for once (MAV_CMD_REQUEST_MESSAGE, then up to 1 s); without one (in lockstep the SITL's clock has not
        started: not asked) the check is skipped, and said so.

        Raises:
            NodeFailure(SETUP): a ground launch off the mission's site.
        """
        v, cfg = self.vehicle, self.cfg
        if v.lpn is None and not cfg.lockstep:
            try:  # (the answer comes on the raw path, which answers no waiter: wait for the sample)
                await v.command(MavCmd.MAV_CMD_REQUEST_MESSAGE, [float(MsgId.LOCAL_POSITION_NED)], retries=2)
                await self.wait(lambda: v.lpn is not None, 1.0, "LOCAL_POSITION_NED", ExitCode.SETUP)
            except (CommandError, NodeFailure):
                pass
        if v.lpn is None:
            log.log(logging.INFO if cfg.lockstep else logging.WARNING,
                    "no LOCAL_POSITION_NED from %s yet: whether the vehicle is at the mission's site is not checked",
                    self.ap_name)
            return
        off = v.offset
        text = off_site((v.lpn.values[0] + off[0], v.lpn.values[1] + off[1], v.lpn.values[2] + off[2]),
                        cfg.mission.mission.waypoints_ned_m)
        if text is None:
            return
        if cfg.launch == "ground":
            raise NodeFailure(ExitCode.SETUP, f"{self.ap_name}: {text}")
        log.warning("%s: %s (carrier launch: flying on)", self.ap_name, text)

    async def read_loop(self) -> PositionLoop | None:
        """The autopilot's position-loop gains (its dialect's loop_params; one it does not answer
        for: the autopilot's default, with a WARNING), logged on one INFO line."""
        d = self.vehicle.ap
        values = await self.read_params(d.loop_params, SHAPING_PARAM_TIMEOUT_S, SHAPING_PARAM_RETRIES)
        stock = [n for n in d.loop_params if n not in values]
        if stock:
            log.warning("%s does not answer for %s: the slot hold assumes the %s defaults", self.ap_name,
                        ", ".join(stock), d.name)
        loop = d.position_loop(values)
        if loop is not None:
            si = self.cfg.mission.mission.slot_integral
            log.info("position loops: %s; slot-hold drive per metre of residual N/E/D %s (0: none on that axis)",
                     ", ".join(f"{n}={values.get(n, float('nan')):g}" for n in d.loop_params),
                     "/".join(f"{c:.3g}" for c in loop.drive_gain(si.autopilot_ki_per_s3)))
        return loop

    # ------------------------------------------------------------------ companion loss
    async def read_params(self, names: tuple[str, ...], timeout_s: float, retries: int) -> dict[str, float]:
        """The values of these parameters, read all at once; a parameter the autopilot does not
        answer for is left out (a missing parameter gets no reply: PX4, ArduPilot, our SITL)."""
        v = self.vehicle
        got = await asyncio.gather(*(v.get_param(n, timeout_s=timeout_s, retries=retries) for n in names),
                                   return_exceptions=True)
        for value in got:
            if isinstance(value, BaseException) and not isinstance(value, CommandError):
                raise value
        return {n: float(x) for n, x in zip(names, got) if not isinstance(x, BaseException)}

    async def verify_loss(self) -> LossBehaviour | None:
        """Read the parameters that decide what the autopilot does if this companion stops,
        set the loss action if --set-loss-action asks, log the behaviour (one INFO line), and
        refuse one the swarm's ghost does not cover (docs/companion.md, "Companion loss").

        Returns:
            The LossBehaviour; None for a dialect that does not describe it (a WARNING).
        Raises:
            NodeFailure(SETUP): a deciding parameter is not served; --set-loss-action asks for
                what this autopilot cannot do; or the behaviour leaves the vehicle drifting,
                flying home or falling and --allow-drifting-loss was not given (the message
                names the parameter, its value, what the vehicle would do and the fix).
            CommandError: --set-loss-action's PARAM_SET did not take.
        """
        cfg, v = self.cfg, self.vehicle
        d = v.ap
        if not d.loss_params:
            log.warning("the %s dialect does not say what its autopilot does if this companion stops: the "
                        "swarm's ghost of this vehicle is the mission's assumption, unchecked", d.name)
            return None
        required = d.loss_required_params
        values = await self.read_params(required, LOSS_PARAM_TIMEOUT_S, LOSS_PARAM_RETRIES)
        missing = [n for n in required if n not in values]
        if missing:
            raise NodeFailure(ExitCode.SETUP, (
                f"{self.ap_name} does not answer for {', '.join(missing)}: the agent reads it to know what the "
                f"vehicle does if this companion stops, and refuses to fly without it (every {d.name} autopilot "
                "has it: check the link, the sysid and the firmware; docs/companion.md, 'Companion loss')"))
        shaping = tuple(n for n in d.loss_params if n not in required)
        values |= await self.read_params(shaping, SHAPING_PARAM_TIMEOUT_S, SHAPING_PARAM_RETRIES)
        stock = [n for n in shaping if n not in values]
        if stock:
            log.warning("%s does not answer for %s: the loss behaviour assumes the %s defaults", self.ap_name,
                        ", ".join(stock), d.name)
        envelope = cfg.mission.mission.swarm.loss
        if cfg.set_loss_action is not None:
            values = await self.set_loss_action(AfterLoss(cfg.set_loss_action), values, envelope.timeout_s)
        loss = d.loss_behaviour(values)
        log.info("if this companion stops: %s", loss.describe())
        text = loss_refusal(self.ap_name, d, loss, envelope)
        if text is not None:
            if not cfg.allow_drifting_loss:
                raise NodeFailure(ExitCode.SETUP, text)
            log.warning("%s (--allow-drifting-loss: flying anyway)", text.split(". Fix:")[0])
        return loss

    async def set_loss_action(self, then: AfterLoss, values: dict[str, float], timeout_max_s: float) -> dict[str, float]:
        """Set the parameters that make the autopilot do `then` on companion loss, and its
        setpoint timeout down to timeout_max_s (the mission's loss envelope) if it is longer
        (each echo checked), logging every change at WARNING with its old value.

        Raises:
            NodeFailure(SETUP): this autopilot cannot be set to do that.
            CommandError: a PARAM_SET did not take.
        """
        d = self.vehicle.ap
        try:
            fix = loss_changes(d, then, values, timeout_max_s)
        except ValueError as err:
            raise NodeFailure(ExitCode.SETUP, f"--set-loss-action {then.value}: {err}") from None
        out = dict(values)
        for name, value in fix.items():
            old = out.get(name)
            if old != value:
                await self.vehicle.set_param(name, value)
                log.warning("set %s = %g (was %s) on %s: %s if this companion stops (--set-loss-action)", name, value,
                            "unknown" if old is None else f"{old:g}", self.ap_name, then.value)
                out[name] = value
        return out

    # ------------------------------------------------------------------ launch
    async def launch(self, attach: Callable[[], None]) -> None:
        """Carrier: arm for the throw, then attach (the autopilot's throw recovery takes over
        at release). Ground: attach, then mode, arm and take-off, retried until LAUNCH_TIMEOUT_S.

        Args:
            attach: starts the ticks (AgentNode._attach).
        Raises:
            NodeFailure(LAUNCH): the ground launch was refused until the timeout, or the
                autopilot never sent its HOME_POSITION (ground launch).
        """
        cfg, v = self.cfg, self.vehicle
        d = v.ap
        if cfg.launch == "carrier":
            await self.arm_for_throw()
            attach()
            return  # the carrier releases; the autopilot's throw recovery takes over
        attach()
        loop = asyncio.get_running_loop()
        try:
            home = await v.request_message(MsgId.HOME_POSITION)
        except CommandError as err:
            raise NodeFailure(ExitCode.LAUNCH, f"ground launch of {self.ap_name}: its home position: {err}") from None
        deadline = loop.time() + LAUNCH_TIMEOUT_S
        while True:
            hb = v.hb
            assert hb is not None  # set-up waited for the HEARTBEAT
            try:
                if d.mode_of(hb.custom_mode) != d.takeoff_from_mode:
                    await v.command(MavCmd.MAV_CMD_DO_SET_MODE, d.set_mode_params(d.takeoff_from_mode))
                if not hb.armed:
                    await v.command(MavCmd.MAV_CMD_COMPONENT_ARM_DISARM, [1.0])  # param1 1: arm
                await v.command(MavCmd.MAV_CMD_NAV_TAKEOFF, d.takeoff_params(cfg.takeoff_alt_m, home.altitude * 1e-3))
                log.info("taking off to %.1f m", cfg.takeoff_alt_m)
                return
            except CommandError as err:
                if loop.time() > deadline:
                    raise NodeFailure(ExitCode.LAUNCH, f"ground launch of {self.ap_name}: {err}") from None
                log.info("ground launch: %s; retrying", err)
            try:
                await v.sleep_s(LAUNCH_RETRY_S)  # (lockstep: simulated time, the same tick in every run)
            except CommandError as err:
                raise NodeFailure(ExitCode.LAUNCH, f"ground launch of {self.ap_name}: {err}") from None

    async def arm_for_throw(self) -> None:
        """On the carrier: select the autopilot's throw mode (ArduPilot THROW) and arm, so its
        throw launch recovers the vehicle. An autopilot that will not arm on the carrier
        (or is already flying) is left as it is: the carrier or the operator arms it."""
        v = self.vehicle
        d = v.ap
        if v.hb is None or v.hb.armed or v.hb.in_air:
            return
        try:
            if d.carrier_mode is not None and d.mode_of(v.hb.custom_mode) != d.carrier_mode:
                await v.command(MavCmd.MAV_CMD_DO_SET_MODE, d.set_mode_params(d.carrier_mode))
            await v.command(MavCmd.MAV_CMD_COMPONENT_ARM_DISARM, [1.0])  # param1 1: arm
            log.info("armed on the carrier for the throw launch")
        except CommandError as err:
            log.info("not armed on the carrier (%s): the carrier arms it at release", err)
