"""Free UDP ports on 127.0.0.1, for the fleet harness and tests: the SITL's own helpers,
so that nothing of the SITL needs the harness that launches it."""
from __future__ import annotations

import socket

import numpy as np


def bind_udp_range(base: int, count: int, host: str = "127.0.0.1") -> None:
    """Check that UDP ports base .. base+count-1 on host are free by binding (and closing) them.

    Raises:
        OSError: naming the first port that is taken.
    """
    socks = []
    try:
        for p in range(base, base + count):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            socks.append(s)
            try:
                s.bind((host, p))
            except OSError as err:
                raise OSError(err.errno, f"port {p} is in use ({err})") from None
    finally:
        for s in socks:
            s.close()


def bind_tcp_port(port: int, host: str = "127.0.0.1") -> None:
    """Check that TCP port on host can be listened on now (bound and closed, with
    SO_REUSEADDR as a server binds: a port in TIME_WAIT counts as free).

    Raises:
        OSError: it cannot be bound (in use, no such address, not allowed).
    """
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))


def find_free_udp_range(count: int, seed: int, attempts: int = 60) -> int:
    """A base port b with b .. b+count-1 all free on 127.0.0.1, tried at seeded random
    places between 20000 and 60000.

    Raises:
        OSError: none found in attempts tries.
    """
    rnd = np.random.default_rng(seed)
    for _ in range(attempts):
        b = int(rnd.integers(20000, 60000 - count))
        try:
            bind_udp_range(b, count)
            return b
        except OSError:
            continue
    raise OSError(f"no {count} consecutive free UDP ports found")
