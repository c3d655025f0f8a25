"""The SITL's MAVLink endpoints: one UDP link per vehicle, the optional shared GCS link,
the tlog and the signing layers, over the lean codec (companion.link). Messages go out
as data (`Outgoing`: message id and field values), packed when an endpoint flushes.
"""
from __future__ import annotations

import asyncio
import dataclasses
import os
from typing import Callable

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.endpoints import MavEndpoint, UdpLink  # noqa: E402
from companion.link.enums import MavComponent  # noqa: E402
from companion.link.msgdef import swarmdrop  # noqa: E402
from companion.link.signing import SigningCounters  # noqa: E402
from companion.link.tlog import Tlog  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from sim_bridge.sitl.config import SitlConfig  # noqa: E402
from sim_bridge.sitl.signing import SitlSigning  # noqa: E402
from sim_bridge.sitl.telemetry import Outgoing  # noqa: E402

MAV_COMP_ID_AUTOPILOT1 = MavComponent.MAV_COMP_ID_AUTOPILOT1


class SitlLinks:
    """Endpoints of n vehicles (sysid k+1, compid 1) and the shared GCS endpoint.

    Args:
        cfg: the SITL configuration (endpoints, signing, tlog path).
        on_setup_refused: called with (vehicle, reason) when a signing layer drops a
            SETUP_SIGNING (the router counts and answers it).
    Raises:
        SigningError: a signing mode without a usable key (before any port opens).
    """

    def __init__(self, cfg: SitlConfig, on_setup_refused: Callable[[int, str], None]):
        self.cfg = cfg
        self.n = cfg.vehicles
        self.codec = Codec(mavlink, swarmdrop)
        """Decodes any common message a client sends; builds what the SITL sends."""
        self.signing = SitlSigning(cfg.signing, self.n, self.codec.crc_extra, on_setup_refused)
        self.endpoints: list[MavEndpoint] = []
        self.gcs: MavEndpoint | None = None
        self.tlog: Tlog | None = None

    @property
    def open(self) -> bool:
        """The sockets are bound (start() has run)."""
        return bool(self.endpoints)

    def start(self, loop: asyncio.AbstractEventLoop, on_readable: Callable[[MavEndpoint, int | None], None],
              tlog_clock: Callable[[], float]) -> None:
        """Bind every endpoint and read them on loop (on_readable(endpoint, vehicle or None)).

        Raises:
            OSError: a port cannot be bound (the message names it).
        """
        ec = self.cfg.endpoints
        if self.cfg.tlog_path:
            self.tlog = Tlog(self.cfg.tlog_path, clock=tlog_clock)
        for k in range(self.n):
            local = ec.local_base_port + k if ec.local_base_port else 0
            # As PX4 (mavlink_receiver: the UDP client address is set at first contact), an
            # autopilot keeps answering whoever spoke to it first: a stranger's unsigned frames
            # cannot take its link from the companion (with signing on, trusted frames decide).
            link = UdpLink(bind=(ec.bind_host, local), remote=(ec.remote_host, ec.vehicle_remote_port(k)),
                           first_contact_only=True)
            ep = MavEndpoint(link, self.codec, k + 1, MAV_COMP_ID_AUTOPILOT1, self.tlog,
                             signing=self.signing.endpoint(k))
            self.endpoints.append(ep)
            loop.add_reader(link.fileno(), on_readable, ep, k)
        if ec.gcs_enabled:
            link = UdpLink(bind=(ec.bind_host, ec.gcs_local_port), remote=(ec.remote_host, ec.gcs_remote_port))
            self.gcs = MavEndpoint(link, self.codec, 1, MAV_COMP_ID_AUTOPILOT1, self.tlog,
                                   signing=self.signing.endpoint(None))
            loop.add_reader(link.fileno(), on_readable, self.gcs, None)

    def close(self, loop: asyncio.AbstractEventLoop) -> None:
        """Stop reading, close every socket and the tlog."""
        for ep in self.endpoints + ([self.gcs] if self.gcs else []):
            loop.remove_reader(ep.link.fileno())
            ep.close()
        if self.tlog is not None:
            self.tlog.close()

    def send(self, k: int, msg: Outgoing, endpoint: MavEndpoint, addr) -> None:
        """A reply of vehicle k (autopilot component) to addr on one endpoint."""
        endpoint.queue_fields(msg[0], msg[1], addr, sysid=k + 1, compid=MAV_COMP_ID_AUTOPILOT1)

    def broadcast(self, k: int, msg: Outgoing, vehicle: bool = True, gcs: bool = True) -> None:
        """A message of vehicle k to its own endpoint (vehicle) and the shared GCS endpoint (gcs)."""
        msgid, values = msg
        if vehicle and self.endpoints:
            self.endpoints[k].queue_fields(msgid, values, sysid=k + 1, compid=MAV_COMP_ID_AUTOPILOT1)
        if gcs and self.gcs is not None:
            self.gcs.queue_fields(msgid, values, sysid=k + 1, compid=MAV_COMP_ID_AUTOPILOT1)

    def flush_all(self) -> None:
        """Send everything queued on every endpoint."""
        for ep in self.endpoints:
            if ep.pending:
                ep.flush()
        if self.gcs is not None and self.gcs.pending:
            self.gcs.flush()

    def signing_stats(self) -> dict[str, SigningCounters]:
        """Per endpoint (vehicle index, or "gcs"): what signing dropped (a copy)."""
        out = {}
        named = [(str(k), e) for k, e in enumerate(self.endpoints)] + ([("gcs", self.gcs)] if self.gcs else [])
        for name, ep in named:
            if ep.signing is not None:
                out[name] = dataclasses.replace(ep.signing.counters)
        return out

    def describe(self) -> list[str]:
        """One line per endpoint: who it is, where it listens and where it sends."""
        ec = self.cfg.endpoints

        def where(ep: MavEndpoint) -> str:
            link = ep.link
            assert isinstance(link, UdpLink)  # (the SITL's links are all UDP)
            remote = f"{link.remote[0]}:{link.remote[1]}" if link.remote else "nobody yet"
            return f"udp {ec.bind_host}:{link.local_port} -> {remote}"

        lines = [f"vehicle {k} sysid {k + 1} compid 1: {where(ep)}" for k, ep in enumerate(self.endpoints)]
        if self.gcs is not None:
            lines.append(f"gcs (all vehicles): {where(self.gcs)}")
        return lines
