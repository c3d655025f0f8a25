"""The SITL's clocks: the simulation tick loop (free-running or lockstep), the wall-clock
heartbeat task and the status line (docs/sitl.md, "Lockstep").

A mixin of SitlServer (sim_bridge.sitl.server), split out to keep the server readable:
it reads the server's state and calls its step, stream and radio methods.
"""
from __future__ import annotations

import asyncio

import numpy as np

from companion.link.dialects import Mode
from companion.swarm import PHASE_COUNT
from sim_bridge.sitl.status import SitlStatus

HEARTBEAT_POLL_S = 0.02
STATUS_PERIOD_S = 0.25
"""A fleet harness acts on these (progress, fault injection at a simulated time)."""


class SitlClock:
    """Clock and pacing methods of SitlServer (see the module docstring)."""

    def lockstep_waiting(self) -> bool:
        """True while a companion that drives the clock has not answered the current tick.

        Lockstep companions (they send SWARMDROP_TICK) answer every LOCAL_POSITION_NED
        they get; their swarm state for the tick must also have reached the radio when
        one is due. Other clients in Offboard drive the clock with their setpoints.
        """
        t_us = int(round(self.sim_s * 1e6))
        unix_us = self._unix_us(self.sim_s)
        wall = self.wall_clock()
        detach = self.cfg.time.lockstep_detach_s
        md = self.medium
        for k, ap in enumerate(self.autopilots):
            if self._companion_us[k] >= 0:
                if wall - self._companion_wall[k] > detach:
                    continue  # silent companion (crashed?): it no longer holds the clock
                if self._control_us[k] == t_us and self._companion_us[k] < unix_us:
                    return True
                if md is not None and md.latest_stamp_us[k] < unix_us and self._publish_ticks()[k]:
                    return True
            elif ap.px4 and ap.mode == Mode.OFFBOARD and not self._sp_fresh[k]:
                return True  # a plain client (MAVSDK) in Offboard drives the clock with its setpoints
        return False

    def any_clock_driver(self) -> bool:
        wall = self.wall_clock()
        if ((self._companion_us >= 0) & (wall - self._companion_wall <= self.cfg.time.lockstep_detach_s)).any():
            return True
        return any(ap.px4 and ap.mode == Mode.OFFBOARD for ap in self.autopilots)

    async def _heartbeat_task(self) -> None:
        """Heartbeats and paced parameter listings, on the wall clock (they flow while a
        lockstep clock waits, as MAVSDK's timeouts are wall-clock)."""
        last = self.wall_clock()
        while not self._stop.is_set():
            now = self.wall_clock()
            ks, _ = self.heartbeats.due(now)
            for k in ks.tolist():
                self.broadcast(k, self.telemetry.heartbeat(k))
            listed = self.router.pump_params(now - last)
            last = now
            if len(ks):
                self._flush_all()
            else:
                for ep in listed:
                    ep.flush()
            try:
                await asyncio.wait_for(self._stop.wait(), HEARTBEAT_POLL_S)
            except asyncio.TimeoutError:
                pass

    def _clock_held(self) -> bool:
        need = self.cfg.time.start_when_attached
        if self.ticks != 0 or need <= 0:
            return False
        if self.cfg.time.lockstep and not (self._fix_t > 0).any():
            # A lockstep companion holds the clock only once it has declared itself (its first
            # SWARMDROP_TICK); starting before all have would let the first ticks pass some of
            # them by, and the run would depend on the wall clock. (With delayed GPS fixes the
            # companions' set-up needs simulated time, so there the clock starts on attach.)
            return int((self._companion_us >= 0).sum()) < need
        return int(self.attached.sum()) < need

    async def _sim_task(self) -> None:
        """Take ticks; the decision to step and the step itself have no await between them."""
        tc = self.cfg.time
        wall0, sim0 = self.wall_clock(), self.sim_s
        while not self._stop.is_set():
            if self._clock_held():
                await asyncio.sleep(0.02)
                wall0, sim0 = self.wall_clock(), self.sim_s
                continue
            if self.wall_started is None:
                self.wall_started, self.sim_started_s = self.wall_clock(), self.sim_s
            if tc.lockstep and self.any_clock_driver():
                if self.lockstep_waiting():
                    self._sp_event.clear()
                    try:
                        await asyncio.wait_for(self._sp_event.wait(), 0.05)
                    except asyncio.TimeoutError:
                        pass
                    continue
                wall0, sim0 = self.wall_clock(), self.sim_s + self.tick_s
            else:
                delay = wall0 + (self.sim_s + self.tick_s - sim0) / tc.speed - self.wall_clock()
                if delay > 0:
                    await asyncio.sleep(delay)
                    continue  # re-evaluate: commands may have arrived meanwhile
                if delay < -0.5:  # overloaded: drop the debt instead of bursting
                    wall0, sim0 = self.wall_clock(), self.sim_s
            self.step_once()
            self.emit_streams()
            if self.medium is not None:
                self._radio_tick(tc.lockstep)
            self._flush_all()
            self._sp_fresh[:] = False
            # Stop decided on simulation time, in this loop: a lockstep run ends on the same tick.
            if self._stop_when_done and self.mission_done:
                print("MISSION COMPLETE", flush=True)
                self._stop.set()
                break
            if self._stop_at_s is not None and self.sim_s >= self._stop_at_s - 1e-9:
                print("DURATION REACHED", flush=True)
                self._stop.set()
                break
            await asyncio.sleep(0)  # let the sockets be read

    def status(self) -> SitlStatus:
        """One line of progress for a fleet harness."""
        md = self.medium
        wall = 0.0 if self.wall_started is None else self.wall_clock() - self.wall_started
        return SitlStatus(
            sim_s=round(self.sim_s, 3), wall_s=round(wall, 3),
            rtf=round((self.sim_s - self.sim_started_s) / wall, 3) if wall > 0 else None,
            attached=int(self.attached.sum()), armed=int(sum(ap.armed for ap in self.autopilots)),
            complete=self.mission_done,
            phases=tuple(np.bincount(md.phase, minlength=PHASE_COUNT).tolist()) if md is not None else (),
            link_bytes_per_s_per_vehicle=round(float(md.bytes_in.sum()) / max(self.sim_s, 1e-9) / self.n, 1)
            if md is not None else None)

    async def _status_task(self, out) -> None:
        while not self._stop.is_set():
            try:
                await asyncio.wait_for(self._stop.wait(), STATUS_PERIOD_S)
            except asyncio.TimeoutError:
                pass
            print(self.status().to_line(), file=out, flush=True)
