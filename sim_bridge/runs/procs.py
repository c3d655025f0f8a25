"""The fleet harness's processes and ports: the 3N+1 UDP ports of a run, children that die
with the harness, their CPU and memory from /proc, and stopping them all (no orphans).
Used by `swarmdrop run` (sim_bridge/runs/fleet.py), the fuzzer and the benchmarks."""
from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from sim_bridge.sitl.ports import bind_udp_range, find_free_udp_range

PR_SET_PDEATHSIG = 1
PORT_MAX = 65535


def die_with_parent() -> None:  # runs in the child before exec (Linux)
    """Ask the kernel to SIGTERM this process when its parent dies (PR_SET_PDEATHSIG), so
    that no child of a killed harness is left running."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class Ports:
    """The UDP ports of a fleet run of n vehicles on 127.0.0.1: 3n + 1 consecutive ports from
    `base`, in order the agents' autopilot ports (n), the SITL's vehicle endpoints (n), the
    swarm radio (1) and the agents' swarm ports (n); ports.json records them (as_dict)."""

    base: int
    n: int

    @property
    def agents(self) -> list[int]:  # where vehicle k's agent listens for its autopilot
        return [self.base + k for k in range(self.n)]

    @property
    def sitl(self) -> int:  # vehicle k's SITL endpoint is sitl + k
        return self.base + self.n

    @property
    def medium(self) -> int:
        return self.base + 2 * self.n

    @property
    def agent_swarm(self) -> int:  # vehicle k's agent receives the radio's copies on agent_swarm + k
        return self.base + 2 * self.n + 1

    @property
    def count(self) -> int:
        return 3 * self.n + 1

    def as_dict(self) -> dict:
        return {"agent_autopilot_ports": [self.agents[0], self.agents[-1]], "sitl_vehicle_ports":
                [self.sitl, self.sitl + self.n - 1], "swarm_radio_port": self.medium,
                "agent_swarm_ports": [self.agent_swarm, self.agent_swarm + self.n - 1], "host": "127.0.0.1"}


def precompile() -> None:
    """Byte-compile the onboard packages once, so that N agents starting together load
    .pyc files instead of each compiling the sources (with PYTHONDONTWRITEBYTECODE set, as
    in some containers, every process would compile every module again)."""
    import compileall

    root = Path(__file__).resolve().parents[2]
    for pkg in ("companion", "swarmdrop"):
        compileall.compile_dir(str(root / pkg), quiet=1)


def check_base_port(n: int, base: int | None) -> None:
    """The run's 3N+1 ports from base must all be real ports (1..65535).

    Raises:
        ConfigError: naming --base-port, the range the run needs and the largest base that fits.
    """
    from companion.config import ConfigError

    if base is None:
        return
    count = Ports(0, n).count
    if not 1 <= base <= PORT_MAX or base + count - 1 > PORT_MAX:
        raise ConfigError(f"--base-port {base}: a run of {n} vehicles needs 3N+1 = {count} consecutive UDP ports, "
                          f"{base}..{base + count - 1}, and a port is 1 to {PORT_MAX}: use a base port from 1 to "
                          f"{PORT_MAX - count + 1}")


def choose_ports(n: int, base: int | None) -> Ports:
    """3N+1 consecutive free UDP ports on 127.0.0.1 (from base, or found).

    Raises:
        ConfigError: base given and its range passes 65535 (check_base_port).
        OSError: base given and one of its ports is taken; or none found.
    """
    count = Ports(0, n).count
    if base is None:
        return Ports(find_free_udp_range(count, os.getpid()), n)
    check_base_port(n, base)
    try:
        bind_udp_range(base, count)
    except OSError as err:
        raise OSError(f"--base-port {base}: {err.strerror}") from None
    return Ports(base, n)


def pss_mb(pid: int) -> float | None:
    """Proportional set size of a process, MB (Linux /proc), None if unavailable."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process so far (Linux /proc), None if gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def log_tail(path: Path, lines: int = 12) -> str:
    """The last lines of a child's log, for an error message."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def terminate_all(procs, grace_s: float = 10.0) -> None:
    """SIGTERM every live process, then SIGKILL what has not exited after grace_s (no orphans)."""
    procs = [p for p in procs if p is not None]
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + grace_s
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
