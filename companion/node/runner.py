"""`swarmdrop agent`: one Agent, one autopilot, one swarm link, one asyncio loop.

AgentNode wires the parts together and runs the process's life: construct (links,
signing: companion.node.setup), set up and launch (companion.node.setup), fly (the
control ticks, companion.node.tick, run from the sockets' reader callbacks; the
offboard switch, companion.node.offboard), supervise (companion HEARTBEAT, autopilot
watchdog, statistics file: companion.node.stats) and stop. Exit codes: see ExitCode
(docs/companion.md).
"""
from __future__ import annotations

import asyncio
import dataclasses
import gc
import logging
import signal
import time

import numpy as np

from companion.agent import Agent
from companion.commands import PlanAssembler
from companion.config import ConfigError
from companion.link.msgdef import swarmdrop as md
from companion.link.wire import Codec
from companion.mission import Mission
from companion.node.config import NodeConfig, mission_sysids
from companion.node.exits import ExitCode, NodeFailure
from companion.node.offboard import Offboard
from companion.node.setup import Setup, link_signing, open_endpoints
from companion.node.stats import AgentStats, collect
from companion.node.swarmlink import SwarmLink, view_for
from companion.node.tick import TickPath
from companion.node.vehicle import VehicleLink

__all__ = ["AgentNode", "ExitCode", "NodeFailure"]

log = logging.getLogger("swarmdrop.agent")

STATS_PERIOD_S = 10.0
"""The statistics file is rewritten this often (and at exit), s. A rewrite (snapshot, JSON,
write and rename) cost a fleet agent 2.4-2.6 ms of CPU: every 5 s that was 2 % of its
50 Hz budget; every 10 s it is 1 %, and half the writes on a companion's SD card. Only an
agent killed outside its control (SIGKILL, power) leaves a file this old."""
SUPERVISE_PERIOD_S = 1.0
"""The companion HEARTBEAT and the autopilot-loss watchdog run this often, s."""


class AgentNode:
    """One companion process. `await run()` returns an ExitCode.

    Raises (construction):
        ConfigError: the mission has no origin, or a link cannot be opened.
        SigningError: signing asked for without a usable key file.
    """

    def __init__(self, cfg: NodeConfig):
        self.cfg = cfg
        mf = cfg.mission
        mcfg = dataclasses.replace(mf.mission, setpoint=dataclasses.replace(mf.mission.setpoint,
                                                                            lead_s=1.0 / cfg.rate_hz))
        self.mission = Mission(mcfg)
        self.agent = Agent(self.mission, np.array([cfg.vehicle_id]))
        self.codec = Codec(md)
        ap_sign, sw_sign = link_signing(cfg, self.codec.crc_extra)
        if mcfg.origin is None:  # check_node refuses such a mission first; this keeps the type honest
            raise ConfigError("mission.origin is required by the agent")
        self.ap_ep, self.sw_ep = open_endpoints(cfg, self.codec, ap_sign, sw_sign)
        self.vehicle = VehicleLink(self.ap_ep, cfg.autopilot_sysid, mcfg.origin, cfg.autopilot_url)
        self.swarm = SwarmLink(self.sw_ep, cfg.vehicle_id, cfg.swarm_peers, view_for(self.mission.n),
                               mission_sysids(mcfg), PlanAssembler.for_mission(self.mission, 0.0),
                               lambda plan: self.agent.plans.receive([0], plan))
        self.offboard = Offboard(self.vehicle)
        self.tick = TickPath(cfg, self.mission, self.agent, self.vehicle, self.swarm, self.offboard)
        self._stop = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self.start_wall = time.monotonic()  # wall_s, cpu_s and setup_s count from a constructed node
        self.start_cpu = time.process_time()
        self.startup_s: float | None = None
        """From process start to a constructed node (imports, mission, sockets), s (the CLI sets it)."""
        self.event_loop: str | None = None
        """The event loop run() flies on, name and version (the CLI sets it: --event-loop)."""
        self.setup = Setup(cfg, self.vehicle, self.swarm, self.start_wall)
        self.stats_failures = 0
        """Statistics writes that failed in a row (write_stats)."""

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop run() runs on. Raises RuntimeError before run()."""
        if self._loop is None:
            raise RuntimeError("AgentNode.loop before run()")
        return self._loop

    # ------------------------------------------------------------------ lifecycle
    def _attach(self) -> None:
        """Start flying: ticks run from now on (TickPath.attach).

        The garbage collector is taken off the tick path: what start-up built is frozen
        (never scanned again) and collection runs in the 1 Hz supervision loop instead of
        at whatever allocation a tick happens to make (a full pass costs milliseconds).
        Ticks allocate no reference cycles, so nothing accumulates meanwhile."""
        gc.collect()
        gc.freeze()
        gc.disable()
        self.tick.attach(self.setup.epoch_us, self.setup.hover_thrust, self.setup.loop)

    async def _supervise(self) -> None:
        """Companion HEARTBEAT at 1 Hz, autopilot-loss watchdog, statistics file.

        Raises:
            NodeFailure(LINK_LOST): no autopilot HEARTBEAT for --heartbeat-timeout.
        """
        v = self.vehicle
        next_stats = self.loop.time() + STATS_PERIOD_S
        while not self._stop.is_set():
            v.heartbeat()
            if not v.tick_aligned:  # (lockstep: it goes with the next tick)
                self.ap_ep.flush()
            gc.collect(1)  # between ticks (see _attach)
            if self.loop.time() - v.hb_loop_time > self.cfg.heartbeat_timeout_s:
                raise NodeFailure(ExitCode.LINK_LOST,
                                  f"no HEARTBEAT from {self.setup.ap_name} for {self.cfg.heartbeat_timeout_s:g} s")
            if self.loop.time() >= next_stats:
                self.write_stats()
                next_stats += STATS_PERIOD_S
            # A plain sleep: one timer and one wake-up a second (wait_for on the stop event
            # made a task and a timeout each second, several loop turns); run() cancels
            # this on stop.
            await asyncio.sleep(SUPERVISE_PERIOD_S)

    async def _body(self) -> None:
        await self.setup.set_up()
        await self.setup.launch(self._attach)
        await self._supervise()

    async def run(self, handle_signals: bool = True) -> ExitCode:
        """Set up, launch, fly until SIGINT/SIGTERM (or request_stop) or a failure; then stop
        everything, write the statistics a last time and close the links.

        Returns:
            ExitCode.OK when stopped, else the failure's code (logged at ERROR; an
            unexpected exception is logged with its traceback: ERROR).
        """
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._loop.add_reader(self.ap_ep.link.fileno(), self.tick.on_autopilot)
        if self.cfg.lockstep:  # the radio's end-of-tick marker may be the last input of a tick
            self._loop.add_reader(self.sw_ep.link.fileno(), self.tick.on_swarm)
        if handle_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(sig, self._stop.set)
        body = asyncio.ensure_future(self._body())
        stop = asyncio.ensure_future(self._stop.wait())
        code = ExitCode.OK
        try:
            await asyncio.wait({body, stop}, return_when=asyncio.FIRST_COMPLETED)
            if body.done() and body.exception() is not None:
                err = body.exception()
                if isinstance(err, NodeFailure):
                    log.error("%s", err)
                    code = err.code
                else:
                    log.error("internal error", exc_info=err)
                    code = ExitCode.ERROR
        finally:
            for task in (body, stop, self.offboard.task, self.setup.streams_task):
                if task is not None and not task.done():
                    task.cancel()
            self._loop.remove_reader(self.ap_ep.link.fileno())
            if self.cfg.lockstep:
                self._loop.remove_reader(self.sw_ep.link.fileno())
            self.write_stats()
            self.ap_ep.close()
            self.sw_ep.close()
        log.info("exit %d (%s)", int(code), code.name)
        return code

    def request_stop(self) -> None:
        """Stop run() from another thread (as SIGTERM does)."""
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    # ------------------------------------------------------------------ statistics
    def stats(self) -> AgentStats:
        """A snapshot of everything the node counts."""
        return collect(self)

    def write_stats(self) -> None:
        """Rewrite the --stats file (if any) with a snapshot. A write that fails (the directory
        removed, the disk full) is logged at ERROR, once until it works again, and the flight
        goes on: statistics are never worth a vehicle."""
        path = self.cfg.stats_path
        if path is None:
            return
        try:
            self.stats().save(path)
        except OSError as err:
            self.stats_failures += 1
            if self.stats_failures == 1:
                log.error("cannot write the statistics to --stats %s: %s (flying on; retried every %g s)", path,
                          err.strerror or err, STATS_PERIOD_S)
            return
        if self.stats_failures:
            log.info("statistics written to --stats %s again (after %d failed write(s))", path, self.stats_failures)
            self.stats_failures = 0
