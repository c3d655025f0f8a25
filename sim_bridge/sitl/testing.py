"""Helpers for tests that talk to the SITL over 127.0.0.1 (free ports, waiting clients)."""
from __future__ import annotations

import contextlib
import os
import time
from typing import Callable, Iterator

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from sim_bridge.sitl.config import EndpointConfig, sitl_config  # noqa: E402
from sim_bridge.sitl.ports import find_free_udp_range  # noqa: E402


def free_udp_base_port(count: int) -> int:
    """A base port b such that b .. b+count-1 are all free UDP ports on 127.0.0.1."""
    return find_free_udp_range(count, os.getpid() ^ time.monotonic_ns())


def local_endpoints(n_remote: int) -> EndpointConfig:
    """SITL endpoints for a test: ephemeral local ports, remotes on free 127.0.0.1 ports."""
    return EndpointConfig(remote_host="127.0.0.1", remote_base_port=free_udp_base_port(n_remote),
                          bind_host="127.0.0.1", local_base_port=0)


class MavClient:
    """A pymavlink (mavutil) ground station listening where vehicle k sends."""

    def __init__(self, port: int, source_system: int = 255, source_component: int = 190):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=source_system,
                                               source_component=source_component)
        self.mav = self.conn.mav

    def wait(self, types: str | list[str], pred: Callable = lambda m: True, timeout_s: float = 5.0):
        """First message of the given type(s) satisfying pred within the deadline, or None."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            msg = self.conn.recv_match(type=types, blocking=True, timeout=min(left, 0.2))
            if msg is not None and pred(msg):
                return msg

    def drain(self) -> None:
        for _ in range(100000):
            if self.conn.recv_match(blocking=False) is None:
                return

    def command(self, target: int, command: int, *params: float, target_component: int = 1,
                timeout_s: float = 3.0):
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(target, target_component, command, 0, *p)
        return self.wait("COMMAND_ACK", lambda m: m.command == command, timeout_s)

    def close(self) -> None:
        self.conn.close()


@contextlib.contextmanager
def running_sitl(vehicles: int) -> Iterator:
    """A SITL of `vehicles` on its own thread, on 127.0.0.1 test ports; stopped on exit."""
    from sim_bridge.sitl.background import BackgroundSitl  # the numba-heavy import only when used

    bg = BackgroundSitl(sitl_config(vehicles, endpoints=local_endpoints(vehicles)))
    try:
        yield bg.start()
    finally:
        bg.stop()


def vehicle_client(server, k: int) -> MavClient:
    """A MavClient where vehicle k sends, once its HEARTBEAT has been heard (deadline 5 s)."""
    c = MavClient(server.cfg.endpoints.remote_base_port + k)
    assert c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == k + 1, 5.0) is not None
    return c


def pack_frame(msg, sysid: int = 255) -> bytes:
    """msg as an unsigned MAVLink 2 frame from sysid, component 190 (pymavlink)."""
    return msg.pack(mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190))
