"""The console's two data feeds behind one interface: live (swarm link, GCS, commands) and replay.

A feed gives the server (swarmdrop.console.server) what the page needs and takes what the
page asks for:

* `meta()`: the page's static picture (mode, vehicles, the mission, replay range, commands);
* `snapshot()`: the fleet now and the frame flags (swarmdrop.console.protocol);
* `status(snapshot)`: fleet health and the slower-changing parts (2 Hz);
* `request(message)`: a command or a replay control; returns the answer.

`health` computes the fleet health of a snapshot: vehicles per phase, formation error,
minimum separation now, state ages (p50, p99) and the formation centre's speed.
"""
from __future__ import annotations

import asyncio
import math
import time
from typing import Any

import numpy as np

from companion.link.endpoints import StreamLink
from swarmdrop.console.live import PHASE_NAMES, FleetModel, GcsSource, SwarmSource
from swarmdrop.console.mission import MissionInfo
from swarmdrop.console.protocol import FLAG_LIVE_CLOCK, FLAG_PLAYING, FLAG_REPLAY, Snapshot
from swarmdrop.console.replay import Playhead, Recording

STREAM_EOF_WAKEUPS = 50
"""A stream link woken this many times in a row with nothing to read has been closed."""
FORMATION_PHASES = (2, 3, 4)
"""ASSEMBLE, TRANSIT, HOVER: the vehicles whose mean velocity is the formation centre's."""
STALE_S = 0.5
"""A state older than this is stale (the swarm's stale_after_s default)."""


def _num(x: Any, digits: int = 3) -> float | None:
    return round(float(x), digits) if x is not None and math.isfinite(x) else None


def min_separation(pos: np.ndarray) -> tuple[float, int, int]:
    """Smallest distance between two of the (k, 3) points, and the pair (rows); inf if < 2."""
    if len(pos) < 2:
        return math.inf, -1, -1
    from scipy.spatial import cKDTree

    d, j = cKDTree(pos).query(pos, k=2)
    i = int(np.argmin(d[:, 1]))
    return float(d[i, 1]), i, int(j[i, 1])


def health(s: Snapshot) -> dict[str, Any]:
    """Fleet health of a snapshot (the page's health panel; None where nothing is known).
    The minimum separation is between vehicles that have left the carrier (phase not LAUNCH)."""
    known = s.known
    valid = known & np.isfinite(s.pos).all(axis=1)
    counts = np.bincount(s.phase[known], minlength=len(PHASE_NAMES))[:len(PHASE_NAMES)]
    ferr = s.ferr[valid]
    ferr = ferr[np.isfinite(ferr)]
    flying = valid & (s.phase != 0)  # LAUNCH: still docked on the carrier, all at one point
    ids = np.flatnonzero(flying)
    sep, i, j = min_separation(s.pos[flying].astype(float))
    ages = s.age[known]
    ages = ages[np.isfinite(ages)]
    form = valid & np.isin(s.phase, FORMATION_PHASES) & np.isfinite(s.vel).all(axis=1)
    if not form.any():
        form = valid & np.isfinite(s.vel).all(axis=1)
    centre_v = s.vel[form].mean(axis=0) if form.any() else np.full(3, np.nan)
    centre_p = s.pos[form].mean(axis=0) if form.any() else np.full(3, np.nan)
    return {
        "n": s.n, "heard": int(known.sum()), "unknown": int(s.n - known.sum()),
        "phases": dict(zip(PHASE_NAMES, counts.tolist())),
        "stale": int((ages > STALE_S).sum()),
        "ferr_max_m": _num(ferr.max()) if len(ferr) else None,
        "ferr_mean_m": _num(ferr.mean()) if len(ferr) else None,
        "min_sep_m": _num(sep) if math.isfinite(sep) else None,
        "min_sep_pair": [int(ids[i]), int(ids[j])] if math.isfinite(sep) else None,
        "age_p50_s": _num(np.percentile(ages, 50)) if len(ages) else None,
        "age_p99_s": _num(np.percentile(ages, 99)) if len(ages) else None,
        "centre_speed_mps": _num(np.linalg.norm(centre_v[:2]), 3) if np.isfinite(centre_v).all() else None,
        "centre_vspeed_mps": _num(-centre_v[2], 3) if np.isfinite(centre_v).all() else None,
        "centre_ned_m": [_num(c, 2) for c in centre_p] if np.isfinite(centre_p).all() else None,
    }


def holders(s: Snapshot, limit: int = 50) -> dict[str, Any]:
    """seq -> {count, ids (up to limit)} of the vehicles that hold each plan (0: the mission's)."""
    out: dict[str, Any] = {}
    seqs = s.plan_seq[s.known]
    ids = np.flatnonzero(s.known)
    for seq in np.unique(seqs).tolist()[:64]:
        who = ids[seqs == seq]
        out[str(seq)] = {"count": int(len(who)), "ids": who[:limit].tolist()}
    return out


class LiveFeed:
    """The swarm link (and a GCS link) into a FleetModel, and commands out.

    Args:
        mission: the mission (--mission), or one without a config.
        swarm: the swarm socket's reader.
        gcs: the GCS link's reader, or None.
        commands: the command panel (swarmdrop.console.commands), or None when commands
            are off; `commands_why` says why.
    """

    mode = "live"

    def __init__(self, mission: MissionInfo, model: FleetModel, swarm: SwarmSource, gcs: GcsSource | None = None,
                 commands=None, commands_why: str = "", clock=time.monotonic):
        self.mission = mission
        self.model = model
        self.swarm = swarm
        self.gcs = gcs
        self.commands = commands
        self.commands_why = commands_why
        self.clock = clock
        self.errors = 0
        """Exceptions while reading a link (counted; the console goes on)."""
        self.gcs_closed = False
        """The GCS link was a stream (TCP, serial) and its other end closed it: no longer read."""
        self._empty = 0
        self._loop: asyncio.AbstractEventLoop | None = None

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        loop.add_reader(self.swarm.ep.link.fileno(), self._read, self.swarm)
        if self.gcs is not None:
            loop.add_reader(self.gcs.ep.link.fileno(), self._read, self.gcs)
        if self.commands is not None:
            self.commands.start(loop)
            self.swarm.on_plan = self.commands.note_plan_message

    def _read(self, source) -> None:
        link = source.ep.link
        before = link.bytes_in
        try:
            source.poll()
        except Exception:  # hostile input must never stop the console
            self.errors += 1
        if isinstance(link, StreamLink):  # a TCP or serial GCS link: readable with nothing to read is its end
            self._empty = 0 if link.bytes_in != before else self._empty + 1
            if self._empty > STREAM_EOF_WAKEUPS and self._loop is not None:
                self._loop.remove_reader(link.fileno())
                self.gcs_closed = True

    def close(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        for src in (self.swarm, self.gcs):
            if src is None:
                continue
            if loop is not None:
                try:
                    loop.remove_reader(src.ep.link.fileno())
                except (ValueError, OSError):
                    pass
            src.ep.link.close()
        if self.commands is not None:
            self.commands.close()
        if self.swarm.tlog is not None:
            self.swarm.tlog.close()

    def meta(self) -> dict[str, Any]:
        cmd = self.commands
        return {"type": "meta", "mode": "live", "n": self.model.n_seen, "phases": list(PHASE_NAMES),
                "mission": self.mission.to_json(), "replay": None,
                "commands": cmd.describe() if cmd is not None else {"enabled": False, "why": self.commands_why},
                "gcs": self.gcs is not None, "signing": self.swarm.ep.signing.mode if self.swarm.ep.signing else "off"}

    def snapshot(self) -> tuple[Snapshot, int]:
        s = self.model.snapshot(self.clock())
        if self.commands is not None:
            self.commands.note_swarm(s)
        return s, FLAG_LIVE_CLOCK

    def status(self, s: Snapshot) -> dict[str, Any]:
        now = self.clock()
        out: dict[str, Any] = {"type": "status", "t": _num(s.t, 3), "health": health(s),
                               "counters": self.model.counters.to_json(self.swarm.ep) | {"errors": self.errors},
                               "plans": [p.to_json() for p in reversed(self.model.plans.values())][:16],
                               "holders": holders(s), "ap": None, "peers": len(self.swarm.peers)}
        if self.gcs is not None:
            out["ap"] = self.gcs.to_json(s.n, now) | {"closed": self.gcs_closed}
        if self.commands is not None:
            out["sent"] = self.commands.sent_json()
        return out

    async def request(self, msg: dict[str, Any]) -> dict[str, Any]:
        if msg.get("type") == "command":
            if self.commands is None:
                return {"ok": False, "text": f"commands are off: {self.commands_why}"}
            return self.commands.request(msg)
        return {"ok": False, "text": "a live console has no replay controls"}


class ReplayFeed:
    """A recording and its playhead."""

    mode = "replay"

    def __init__(self, rec: Recording, mission: MissionInfo | None, clock=time.monotonic):
        self.rec = rec
        self.mission = mission or MissionInfo("replay", None, [])
        self.play = Playhead(rec, clock)

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.play.play()

    def close(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        pass

    def meta(self) -> dict[str, Any]:
        return {"type": "meta", "mode": "replay", "n": self.rec.n, "phases": list(PHASE_NAMES),
                "mission": self.mission.to_json(), "replay": self.play.to_json(),
                "commands": {"enabled": False, "why": "a replay"}, "gcs": False, "signing": "off"}

    def snapshot(self) -> tuple[Snapshot, int]:
        t = self.play.now()
        return self.rec.snapshot(t), FLAG_REPLAY | (FLAG_PLAYING if self.play.playing else 0)

    def status(self, s: Snapshot) -> dict[str, Any]:
        return {"type": "status", "t": _num(s.t, 3), "health": health(s), "counters": None, "plans": [],
                "holders": holders(s), "ap": None, "replay": self.play.to_json()}

    async def request(self, msg: dict[str, Any]) -> dict[str, Any]:
        if msg.get("type") != "replay":
            return {"ok": False, "text": "a replay takes no commands"}
        op = msg.get("op")
        try:
            if op == "play":
                self.play.play()
            elif op == "pause":
                self.play.pause()
            elif op == "seek":
                self.play.seek(float(msg.get("t")))  # type: ignore[arg-type]
            elif op == "speed":
                self.play.set_speed(float(msg.get("speed")))  # type: ignore[arg-type]
            else:
                return {"ok": False, "text": f"unknown replay op {str(op)[:20]!r}"}
        except (TypeError, ValueError) as err:
            return {"ok": False, "text": str(err)[:200]}
        return {"ok": True, "text": op, "replay": self.play.to_json()}
