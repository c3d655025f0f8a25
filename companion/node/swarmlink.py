"""The agent's link to its neighbours: SWARMDROP_STATE out, everyone's states in.

Each agent sends only its own state, signed with its own sysid (vehicle_id + 1),
to a list of peer addresses: the radio medium (one send, docs/swarm-link.md) or
every other vehicle (unicast). What arrives goes into the agent's SwarmView with
its stamp; a message for another mission slot than its sender's sysid says, from
this vehicle itself, with a non-finite stamp, or that does not decode, is counted
and dropped. In lockstep the medium ends each tick's batch with a SWARMDROP_TICK,
which tells the agent it has heard everything due.
"""
from __future__ import annotations

import logging
import math

from companion.link.endpoints import MavEndpoint
from companion.link.msgdef import swarmdrop as md
from companion.swarm import PHASE_COUNT, SwarmStates, SwarmView

log = logging.getLogger("swarmdrop.swarm")

_STATE = md.MAVLINK_MSG_ID_SWARMDROP_STATE
_TICK = md.MAVLINK_MSG_ID_SWARMDROP_TICK


class SwarmLink:
    """Neighbour states over MAVLink.

    Args:
        endpoint: a MavEndpoint on the swarm socket (sysid = own sysid, compid 191).
        vehicle_id: this vehicle's index in the mission.
        peers: addresses to send the own state to.
        view: the agent's SwarmView (one receiver row).

    The mission epoch (Unix time of mission time 0; message times are Unix µs) is None
    until the agent knows its autopilot's clock (set_epoch): states heard before then are
    dropped (counted as rejected), never stored with a stamp in another time base.
    """

    def __init__(self, endpoint: MavEndpoint, vehicle_id: int, peers: list[tuple[str, int]], view: SwarmView):
        self.ep = endpoint
        self.vehicle_id = vehicle_id
        self.peers = list(peers)
        self.view = view
        self.epoch_us: int | None = None
        self.marker_us = -1
        """time_usec of the newest SWARMDROP_TICK from the medium."""
        self.states_in = 0
        self.rejected = 0
        self.sent = 0

    def set_epoch(self, epoch_unix_s: float) -> None:
        self.epoch_us = int(round(epoch_unix_s * 1e6))

    def poll(self) -> int:
        """Take everything waiting; returns the number of states applied to the view."""
        applied = 0
        view, own, n, epoch = self.view, self.vehicle_id, self.view.n_vehicles, self.epoch_us
        for msgid, sysid, _compid, w, _addr in self.ep.poll_raw():
            if msgid == _STATE:
                # wire order: time_usec, t_go_usec, x, y, z, vx, vy, vz, q[4], phase, flags, vehicle_id
                j = w[14]
                if j == own or j >= n or sysid != j + 1 or epoch is None or w[12] >= PHASE_COUNT:
                    self.rejected += 1
                    continue
                self.states_in += 1
                if view.receive_one(0, j, (w[0] - epoch) * 1e-6, w[2:5], w[5:8], w[12], w[13],
                                    (w[1] - epoch) * 1e-6 if w[1] else math.nan):
                    applied += 1
            elif msgid == _TICK:
                self.marker_us = max(self.marker_us, w[0])
            else:
                self.rejected += 1
        return applied

    def publish(self, states: SwarmStates) -> None:
        """Queue this vehicle's state (one row) to every peer."""
        s = states
        if self.epoch_us is None:
            raise RuntimeError("SwarmLink.publish before set_epoch: no mission clock yet")
        t_us = self.epoch_us + int(round(float(s.stamp_s[0]) * 1e6))
        go = float(s.t_go_s[0])
        t_go_us = self.epoch_us + int(round(go * 1e6)) if math.isfinite(go) else 0
        p, v, q = s.pos_ned_m[0], s.vel_ned_mps[0], s.att_q_wxyz[0]
        values = [t_us, t_go_us, float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2]),
                  [float(x) for x in q], int(s.phase[0]), int(s.flags[0]), self.vehicle_id]
        for addr in self.peers:
            self.ep.queue_fields(_STATE, values, addr)
        self.sent += 1

    def counters(self) -> dict:
        ep = self.ep
        return {"states_in": self.states_in, "rejected": self.rejected, "bad_frames": ep.bad_frames,
                "stale_or_duplicate": int(self.view.ignored_old[0]), "published": self.sent,
                "bytes_out": ep.link.bytes_out, "bytes_in": ep.link.bytes_in}


def view_for(n_vehicles: int) -> SwarmView:
    """A one-receiver view of the mission's vehicles."""
    return SwarmView.unknown(1, n_vehicles)

