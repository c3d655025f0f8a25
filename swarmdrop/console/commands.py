"""Operator commands from the page to the swarm: checked, made into plans, signed, sent, repeated.

The page asks for a command (swarmdrop.console.protocol); `CommandPanel.request` checks
every argument (finite numbers in range, vehicle ids in the mission, a confirmation for
LAND and ABORT), has `companion.commands.CommandSource` make the plan (the one command
model the agents apply), and sends the plan's messages (`plan_messages`: SWARMDROP_PLAN and
its SWARMDROP_SLOTS chunks) on the swarm socket to every peer (`--swarm-peer`, e.g. the
radio medium; without one, to the addresses states came from), as a ground station
(`--sysid`, 255 by default, component MAV_COMP_ID_MISSIONPLANNER), signed when signing is
on. Each plan goes out `REPEATS` times, `REPEAT_S` apart (a newer plan stops the older
one's repeats); the agents relay the newest plan themselves.

Times: the CommandSource works in mission seconds; the console takes the swarm's clock
(Unix seconds of the vehicles' stamps) minus an epoch: `--epoch` if given, else the whole
second of the first state heard. Only differences of such times matter to a plan (its
effective time against the transit start the swarm agreed, which the console passes on
with `set_t_go`), and `plan_messages` turns them back into Unix time with the same epoch.
"""
from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from typing import Any, Callable

import numpy as np

from companion.link.endpoints import MavEndpoint
from companion.link.enums import MavComponent
from swarmdrop.console.mission import MissionInfo
from swarmdrop.console.protocol import Snapshot

REPEATS = 3
REPEAT_S = 0.3
GROUND_COMPID = MavComponent.MAV_COMP_ID_MISSIONPLANNER
SHAPES = ("circle", "line", "grid", "wedge", "shell")
MAX_WAYPOINTS = 7
"""A SWARMDROP_PLAN holds 8 centre waypoints; the first is where the centre is when it applies."""
COORD_MAX_M = 10_000.0
SPEED_MAX_MPS = 30.0
SIZE_MAX_M = 2_000.0
CONFIRM = ("land", "abort")
WIRE_VEHICLES_MAX = 255
"""Vehicles a plan carries (companion.commands.WIRE_VEHICLES_MAX)."""


class CommandError(ValueError):
    """A command the page asked for that cannot be sent; the message says why."""


def command_source_api() -> tuple[Any, Callable, str]:
    """(CommandSource class, plan_messages, "") from companion.commands, or (None, None, why)."""
    try:
        from companion.commands import CommandSource, plan_messages
    except ImportError as err:
        return None, lambda *_: [], f"companion.commands is not available ({err})"
    return CommandSource, plan_messages, ""


def _finite(msg: dict, key: str, lo: float, hi: float, default: float | None = None) -> float:
    v = msg.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        raise CommandError(f"{key}: a number from {lo:g} to {hi:g}")
    return float(v)


class CommandPanel:
    """Commands of one console (module docstring).

    Args:
        mission: the mission (vehicle count; CommandSource is built from it).
        endpoint: the swarm socket's MavEndpoint (its signing layer signs what is sent).
        peers: where to send (HOST, PORT) pairs; empty: where states came from (`learnt`).
        learnt: the source addresses of accepted states (SwarmSource.peers), newest last.
        sysid: the ground station's MAVLink system id.
        epoch_unix_s: the mission epoch (None: the first state heard, whole second).
        source: a CommandSource (default: companion.commands.CommandSource of the mission).
        plan_messages: companion.commands.plan_messages (default).
    """

    def __init__(self, mission: MissionInfo, endpoint: MavEndpoint, peers: list[tuple[str, int]], learnt,
                 sysid: int = 255, epoch_unix_s: float | None = None, source: Any = None,
                 plan_messages: Callable | None = None, clock=time.monotonic):
        if mission.config is None or mission.model is None:
            raise CommandError("commands need the mission (--mission)")
        if mission.config.n_vehicles > WIRE_VEHICLES_MAX:
            raise CommandError(f"a plan carries at most {WIRE_VEHICLES_MAX} vehicles; the mission has "
                               f"{mission.config.n_vehicles}")
        cls, pm, why = command_source_api()
        if source is None:
            if cls is None:
                raise CommandError(why)
            source = cls(mission.model)
        self.source = source
        self.plan_messages = plan_messages or pm
        self.mission = mission
        self.ep = endpoint
        self.peers = list(peers)
        self.learnt = learnt
        self.sysid = sysid
        self.epoch_unix_s = epoch_unix_s
        self.clock = clock
        self.t_unix = math.nan
        """The swarm's clock at the last snapshot (Unix s)."""
        self._t_go = math.nan
        self._t_s = -math.inf
        """The last command's mission time (commands go in time order)."""
        self.heard_seq = 0
        """The newest plan seq heard on the link (vehicles' plan_seq, plans assembled)."""
        self.assembler: Any = None
        """Plans heard on the link, reassembled (companion.commands.PlanAssembler), once the epoch is known."""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._repeat: asyncio.TimerHandle | None = None
        self.sent: deque[dict[str, Any]] = deque(maxlen=20)
        self.frames_sent = 0

    # ---- wiring --------------------------------------------------------------------
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    def close(self) -> None:
        if self._repeat is not None:
            self._repeat.cancel()

    def describe(self) -> dict[str, Any]:
        sg = self.ep.signing
        return {"enabled": True, "why": "", "signed": sg is not None, "sysid": self.sysid,
                "peers": [f"{h}:{p}" for h, p in self.peers] or "where states come from",
                "epoch_known": self.epoch_unix_s is not None,
                "note": f"sysid {self.sysid}" + (", signed" if sg is not None else ", unsigned")}

    def note_swarm(self, s: Snapshot) -> None:
        """The swarm's clock, agreed transit start and newest plan, from the latest snapshot;
        fills in the slots of the vehicles that hold a plan the console knows."""
        if math.isfinite(s.t):
            self.t_unix = s.t
            if self.epoch_unix_s is None:
                self.epoch_unix_s = float(math.floor(s.t))
        if math.isfinite(s.t_go) and s.t_go != self._t_go and self.epoch_unix_s is not None:
            self._t_go = s.t_go
            self.source.set_t_go(s.t_go - self.epoch_unix_s)
        if s.known.any():
            self.heard_seq = max(self.heard_seq, int(s.plan_seq[s.known].max()))
        if self.epoch_unix_s is not None and math.isfinite(s.t):
            try:
                self._plan_slots(s)
            except (ValueError, IndexError, TypeError):  # a heard plan the geometry cannot take: no slots drawn
                pass

    def _plan_slots(self, s: Snapshot) -> None:
        """Slots of vehicles under a plan: this console's plans exactly (centre and morph, as the
        CommandSource holds them), a plan assembled from the link at its target slots."""
        from companion.commands import centre_ned_m, plan_offsets_ned_m

        assert self.epoch_unix_s is not None
        held = s.plan_seq[:len(s.slot)]
        under = np.flatnonzero(s.known & (held > 0))
        if not len(under):
            return
        t = s.t - self.epoch_unix_s
        t_go = s.t_go - self.epoch_unix_s if math.isfinite(s.t_go) else math.nan
        src = self.source
        mission = self.mission.model
        assert mission is not None  # (a panel exists only with a mission)
        n = len(src.plan.slot_of)
        for seq in np.unique(held[under]).tolist():
            rows = under[held[under] == seq]
            rows = rows[rows < n]
            if seq == src.plan.seq:
                pts = src.centre_ned_m(t) + src.offsets_ned_m(t)
            elif seq < len(src.plans) and self.heard_seq <= src.plan.seq:
                p = src.plans[seq]
                pts = centre_ned_m(p, t, mission, t_go) + plan_offsets_ned_m(p)
            elif self.assembler is not None and self.assembler.newest_seq == seq:
                p = self.assembler.newest
                pts = centre_ned_m(p, t, mission, t_go) + plan_offsets_ned_m(p)
            else:
                continue
            s.slot[rows] = pts[rows]

    def note_plan_message(self, msgid: int, fields: dict[str, Any]) -> None:
        """A SWARMDROP_PLAN or SLOTS heard on the link (ours relayed, or another source's)."""
        if self.epoch_unix_s is None:
            return
        if self.assembler is None:
            from companion.commands import PlanAssembler

            assert self.mission.model is not None
            self.assembler = PlanAssembler.for_mission(self.mission.model, self.epoch_unix_s)
        plan = self.assembler.feed_fields(msgid, fields)
        if plan is not None:
            self.heard_seq = max(self.heard_seq, plan.seq)

    def sent_json(self) -> list[dict[str, Any]]:
        return list(self.sent)

    # ---- a request -----------------------------------------------------------------
    def request(self, msg: dict[str, Any]) -> dict[str, Any]:
        """Check, make and send one command; the answer for the page."""
        try:
            cmd = msg.get("cmd")
            if not isinstance(cmd, str) or len(cmd) > 16:
                raise CommandError("no command")
            cmd = cmd.lower()
            if cmd in CONFIRM and msg.get("confirm") is not True:
                raise CommandError(f"{cmd.upper()} needs a confirmation")
            if self.epoch_unix_s is None or not math.isfinite(self.t_unix):
                raise CommandError("no swarm clock yet: no vehicle has been heard")
            if self.heard_seq > self.source.plan.seq:
                raise CommandError(f"the swarm follows plan {self.heard_seq} of another source (or of this console "
                                   f"before a restart); this console's next plan would be {self.source.plan.seq + 1} "
                                   "and the agents would ignore it")
            t_s = max(self.t_unix - self.epoch_unix_s, self._t_s)
            plan = self._plan(cmd, t_s, msg)
            self._t_s = t_s
        except CommandError as err:
            return {"ok": False, "text": f"{str(msg.get('cmd'))[:16].upper()}: {err}"}
        except (ValueError, TypeError) as err:  # the command model refused it
            return {"ok": False, "text": f"{str(msg.get('cmd'))[:16].upper()}: refused: {str(err)[:200]}"}
        messages = list(self.plan_messages(plan, self.epoch_unix_s))
        n = self._send(messages)
        seq = getattr(plan, "seq", None)
        entry = {"seq": seq, "cmd": cmd, "at": round(self.t_unix, 3), "frames": n, "peers": len(self._targets())}
        self.sent.append(entry)
        self._schedule_repeats(messages, REPEATS - 1)
        where = f"{entry['peers']} peer(s)" if entry["peers"] else "nobody yet (no peer, no state heard)"
        return {"ok": n > 0, "text": f"{cmd.upper()} sent as plan {seq} to {where}", "seq": seq}

    def _ids(self, msg: dict[str, Any], key: str = "ids", allow_all: bool = False) -> list[int] | None:
        ids = msg.get(key)
        if ids is None and allow_all:
            return None
        n = self.mission.n or 0
        if not isinstance(ids, list) or not ids or len(ids) > n:
            raise CommandError(f"{key}: a list of vehicle ids")
        out = []
        for k in ids:
            if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < n:
                raise CommandError(f"vehicle {k!r} is not in the mission (0..{n - 1})")
            out.append(k)
        return sorted(set(out))

    def _plan(self, cmd: str, t_s: float, msg: dict[str, Any]):
        src = self.source
        if cmd == "hold":
            return src.hold(t_s)
        if cmd == "resume":
            return src.resume(t_s)
        if cmd == "rtl":
            return src.rtl(t_s)
        if cmd == "abort":
            return src.abort(t_s)
        if cmd == "goto":
            wps = msg.get("waypoints")
            if not isinstance(wps, list) or not 1 <= len(wps) <= MAX_WAYPOINTS:
                raise CommandError(f"waypoints: 1 to {MAX_WAYPOINTS} of [N, E, D]")
            pts = []
            for w in wps:
                if not isinstance(w, list) or len(w) != 3:
                    raise CommandError("a waypoint is [N, E, D] in metres")
                pts.append(tuple(_finite({"waypoint": c}, "waypoint", -COORD_MAX_M, COORD_MAX_M) for c in w))
            return src.goto(t_s, pts, _finite(msg, "speed", 0.1, SPEED_MAX_MPS))
        if cmd == "formation":
            shape = msg.get("shape")
            if shape not in SHAPES:
                raise CommandError(f"shape: one of {', '.join(SHAPES)}")
            spec = self._formation_spec(str(shape), _finite(msg, "radius", 0.5, SIZE_MAX_M, 10.0),
                                        _finite(msg, "spacing", 0.5, SIZE_MAX_M, 4.0),
                                        math.radians(_finite(msg, "rotation_deg", -360.0, 360.0, 0.0)))
            return src.formation(t_s, spec)
        if cmd == "exclude":
            land = msg.get("land", False)
            if not isinstance(land, bool):
                raise CommandError("land: true or false")
            return src.exclude(t_s, self._ids(msg), land=land)
        if cmd == "rejoin":
            return src.rejoin(t_s, self._ids(msg))
        if cmd == "land":
            return src.land(t_s, self._ids(msg, allow_all=True))
        raise CommandError("unknown command")

    def _formation_spec(self, shape: str, radius: float, spacing: float, rotation_rad: float) -> Any:
        """The FormationSpec CommandSource.formation takes (the circle's slot order is the
        mission's: the source sets it)."""
        from companion.control.shapes import FormationSpec

        return FormationSpec(shape=shape, radius_m=radius, spacing_m=spacing, rotation_rad=rotation_rad)  # type: ignore[arg-type]

    # ---- sending -------------------------------------------------------------------
    def _targets(self) -> list:
        return self.peers or list(self.learnt)[-16:]

    def _send(self, messages: list[tuple[int, Any]]) -> int:
        targets = self._targets()
        for addr in targets:
            for msgid, values in messages:
                self.ep.queue_fields(msgid, values, addr, sysid=self.sysid, compid=GROUND_COMPID)
        sent = self.ep.flush()
        self.frames_sent += sent
        return sent

    def _schedule_repeats(self, messages: list, left: int) -> None:
        if self._repeat is not None:
            self._repeat.cancel()
            self._repeat = None
        if left <= 0 or self._loop is None:
            return

        def again() -> None:
            self._send(messages)
            self._schedule_repeats(messages, left - 1)

        self._repeat = self._loop.call_later(REPEAT_S, again)


