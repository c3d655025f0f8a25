"""`swarmdrop run CONFIG`: the SITL and one `swarmdrop agent` process per vehicle.

Real OS processes on real sockets: the SITL (every vehicle a PX4- or ArduPilot-like
autopilot, the swarm radio, the recorder) and N agents, each talking MAVLink to
its own vehicle and publishing its state to the radio. The harness shows
progress, reports an agent that dies (exit code and the tail of its log) and goes
on, stops every process on completion or Ctrl-C (children also die with the
harness: PR_SET_PDEATHSIG), and writes one run directory:

    metrics.json     the same metrics as `swarmdrop simulate`, plus a "fleet" section
    telemetry.npz    true trajectories (the SITL's physics), run.json
    sitl.tlog        every MAVLink frame between the SITL and the agents (mavlogdump reads it)
    agents/          each agent's log and statistics
    ports.json       every port used; config.json; the figures
"""
from __future__ import annotations

import ctypes
import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim_bridge.fleet_report import FleetReport, FleetSection, agent_figures, signing_totals
from sim_bridge.scenario import ScenarioConfig
from sim_bridge.sitl.status import SitlStatus

PR_SET_PDEATHSIG = 1
EPOCH_UNIX_S = 1767225600.0  # 2026-01-01T00:00:00Z: a fixed SITL clock, so lockstep runs repeat exactly
READY_TIMEOUT_S = 60.0
STOP_GRACE_S = 5.0
CPU_WINDOW_START_S = 10.0
"""Agents' CPU share is measured from this simulated time on (after start-up and setup)."""


def _die_with_parent() -> None:  # runs in the child before exec (Linux)
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class FleetOptions:
    """What `swarmdrop run` was asked for."""

    out_dir: Path
    dialect: str = "px4"
    lockstep: bool = False
    output: str = "acceleration"
    base_port: int | None = None
    rate_hz: float = 50.0
    kill: dict[int, float] = field(default_factory=dict)
    """vehicle id -> simulation time at which the harness kills its agent (fault injection)."""
    fix_delay_max_s: float = 0.0
    progress: bool = True
    figures: bool = True
    python: str = sys.executable
    agent_nice: int = 0
    """Added niceness of agents (the SITL keeps priority, so simulated physics stays honest)."""
    signing: bool = False
    """Sign every link (SITL endpoints, autopilot links, swarm link) with a fresh key in the run directory."""


@dataclass
class Ports:
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

    root = Path(__file__).resolve().parents[1]
    for pkg in ("companion", "swarmdrop"):
        compileall.compile_dir(str(root / pkg), quiet=1)


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


def choose_ports(n: int, base: int | None) -> Ports:
    """3N+1 consecutive free UDP ports on 127.0.0.1 (from base, or found).

    Raises:
        OSError: base given and one of its ports is taken; or none found.
    """
    count = Ports(0, n).count
    if base is None:
        return Ports(find_free_udp_range(count, os.getpid()), n)
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


def _tail(path: Path, lines: int = 12) -> str:
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


class Fleet:
    """One fleet run: start, watch, stop, report."""

    def __init__(self, config_path: Path, cfg: ScenarioConfig, opts: FleetOptions):
        self.config_path, self.cfg, self.opts = config_path, cfg, opts
        self.n = cfg.mission.n_vehicles
        self.out = opts.out_dir
        self.agents: list[subprocess.Popen] = []
        self.sitl: subprocess.Popen | None = None
        self.status = SitlStatus()
        """The SITL's last STATUS line."""
        self.events: list[str] = []
        self.dead: dict[int, int] = {}
        self.killed: set[int] = set()
        self.pss: dict[int, float] = {}
        self._cpu0: dict[int | str, tuple[float, float]] = {}
        """(wall, CPU seconds) of each process ("sitl" or agent k) at the start of its CPU window."""
        self.steady_cpu: dict[int, float] = {}
        """Share of a core each agent used from CPU_WINDOW_START_S of simulated time to its end."""
        self.sitl_cpu: float | None = None
        self.interrupted = False
        """Set by SIGINT/SIGTERM to the harness: the run ends early and exits 130."""

    # ------------------------------------------------------------------ processes
    def _popen(self, args: list[str], stdout, nice: int = 0) -> subprocess.Popen:
        def pre() -> None:
            # Own process group: a terminal's Ctrl-C reaches only the harness, which then
            # stops the SITL and the agents in order (and reports them as stopped, not dead).
            os.setpgid(0, 0)
            _die_with_parent()
            if nice:
                os.nice(nice)
        return subprocess.Popen(args, stdout=stdout, stderr=subprocess.STDOUT, preexec_fn=pre, text=True,
                                cwd=Path(__file__).resolve().parents[1])

    def _start_sitl(self, ports: Ports) -> None:
        o = self.opts
        args = [o.python, "-m", "sim_bridge.sitl", "--scenario", str(self.config_path), "--dialect", o.dialect,
                "--remote-base-port", str(ports.agents[0]), "--local-base-port", str(ports.sitl),
                "--medium-port", str(ports.medium), "--agent-base-port", str(ports.agent_swarm),
                "--start-when-attached", str(self.n), "--status",
                "--record", str(self.out), "--tlog", str(self.out / "sitl.tlog"), "--stop-when-done",
                "--duration", str(self.cfg.duration_s), "--epoch", str(EPOCH_UNIX_S)]
        if o.lockstep:
            args.append("--lockstep")
        if o.fix_delay_max_s > 0:
            args += ["--fix-delay-max", str(o.fix_delay_max_s)]
        args += self._signing_args()
        self.sitl = self._popen(args, subprocess.PIPE)
        self._sitl_lines: list[str] = []
        threading.Thread(target=self._read_sitl, daemon=True).start()
        deadline = time.monotonic() + READY_TIMEOUT_S
        while "SITL READY" not in self._sitl_lines:
            if self.sitl.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the SITL did not start:\n" + "\n".join(self._sitl_lines[-20:]))
            time.sleep(0.05)

    def _read_sitl(self) -> None:
        with open(self.out / "sitl.log", "w") as log:
            for line in self.sitl.stdout:
                line = line.rstrip("\n")
                st = SitlStatus.from_line(line)
                if st is not None:
                    self.status = st
                elif not line.startswith("STATUS "):
                    self._sitl_lines.append(line)
                log.write(line + "\n")
                log.flush()

    def _start_agents(self, ports: Ports) -> None:
        o = self.opts
        adir = self.out / "agents"
        adir.mkdir(parents=True, exist_ok=True)
        for k in range(self.n):
            args = [o.python, "-m", "swarmdrop.cli", "agent", "--vehicle-id", str(k),
                    "--autopilot", f"udpin://127.0.0.1:{ports.agents[k]}", "--mission", str(self.config_path),
                    "--swarm-bind", f"127.0.0.1:{ports.agent_swarm + k}", "--swarm-peer", f"127.0.0.1:{ports.medium}",
                    "--output", o.output, "--rate", str(o.rate_hz), "--log-file", str(adir / f"agent_{k:02d}.log"),
                    "--no-stderr-log", "--stats", str(adir / f"agent_{k:02d}.json")]
            if o.lockstep:
                args.append("--lockstep")
            args += self._signing_args()
            self.agents.append(self._popen(args, subprocess.DEVNULL, o.agent_nice))

    def _signing_args(self) -> list[str]:
        """--signing require with this run's key (created once, owner-readable only)."""
        if not self.opts.signing:
            return []
        key = self.out / "signing.key"
        if not key.exists():
            from companion.link.signing import write_key

            write_key(key)
        return ["--signing", "require", "--signing-key", str(key)]

    def stop(self) -> None:
        """Stop every process: SIGTERM, then SIGKILL after a grace period (no orphans)."""
        terminate_all(self.agents + [self.sitl], STOP_GRACE_S)

    # ------------------------------------------------------------------ the run
    def _cpu_share(self, key: int | str, pid: int) -> float | None:
        """Share of a core process pid has used since its first call here (None at first)."""
        c = cpu_s(pid)
        if c is None:
            return None
        now = time.monotonic()
        if key not in self._cpu0:
            self._cpu0[key] = (now, c)
            return None
        t0, c0 = self._cpu0[key]
        return (c - c0) / (now - t0) if now > t0 + 1.0 else None

    def _watch_sitl(self, sim_s: float) -> None:
        if sim_s >= CPU_WINDOW_START_S and self.sitl is not None:
            share = self._cpu_share("sitl", self.sitl.pid)
            if share is not None:
                self.sitl_cpu = share

    def _watch_agents(self, sim_s: float) -> None:
        if self.interrupted:
            return  # agents stopping now are being stopped, not crashing
        for k, p in enumerate(self.agents):
            if k in self.opts.kill and k not in self.killed and sim_s >= self.opts.kill[k]:
                p.kill()
                self.killed.add(k)
                self.events.append(f"t={sim_s:.1f} s: killed agent {k} (fault injection)")
            code = p.poll()
            if code is not None and k not in self.dead:
                self.dead[k] = code
                msg = (f"agent {k} exited with code {code} at t={sim_s:.1f} s; its log ends:\n"
                       f"{_tail(self.out / 'agents' / f'agent_{k:02d}.log')}")
                self.events.append(msg)
                print(msg, file=sys.stderr, flush=True)
            if k not in self.pss and sim_s > 5.0 and code is None:
                value = pss_mb(p.pid)
                if value is not None:
                    self.pss[k] = value
            if code is None and sim_s >= CPU_WINDOW_START_S:
                share = self._cpu_share(k, p.pid)
                if share is not None:
                    self.steady_cpu[k] = share

    def run(self) -> FleetReport:
        """Fly the mission; returns metrics (written to out/metrics.json)."""
        from tqdm import tqdm

        self.out.mkdir(parents=True, exist_ok=True)
        precompile()
        ports = choose_ports(self.n, self.opts.base_port)
        (self.out / "ports.json").write_text(json.dumps(ports.as_dict(), indent=1))
        (self.out / "config.json").write_text(json.dumps(dataclasses.asdict(self.cfg), indent=1))
        wall0 = time.monotonic()
        bar = None
        try:
            self._start_sitl(ports)
            self._start_agents(ports)
            bar = tqdm(total=round(self.cfg.duration_s), unit="sim-s", disable=not self.opts.progress,
                       desc=f"{self.cfg.name} fleet", mininterval=0.5)
            while self.sitl.poll() is None:
                st = self.status
                sim_s = st.sim_s
                self._watch_agents(sim_s)
                self._watch_sitl(sim_s)
                if bar is not None:
                    bar.n = min(int(sim_s), bar.total)
                    ph = st.phases
                    names = ("launch", "stab", "asm", "transit", "hover", "land", "failed")
                    bar.set_postfix_str(" ".join(f"{n}:{c}" for n, c in zip(names, ph) if c)
                                        + f" rtf:{st.rtf} attached:{st.attached}/{self.n}"
                                        + (f" dead:{len(self.dead)}" if self.dead else ""), refresh=False)
                    bar.refresh()
                time.sleep(0.1)
            self._watch_agents(self.status.sim_s)
        finally:
            if bar is not None:
                bar.close()
            self.stop()
        return self.report(time.monotonic() - wall0)

    # ------------------------------------------------------------------ results
    def _agent_stats(self) -> list[dict]:
        out = []
        for k in range(self.n):
            p = self.out / "agents" / f"agent_{k:02d}.json"
            try:
                out.append(json.loads(p.read_text()))
            except (OSError, json.JSONDecodeError):
                out.append({"vehicle_id": k})
        return out

    def fleet_section(self, wall_s: float) -> FleetSection:
        stats = self._agent_stats()
        return FleetSection(
            dialect=self.opts.dialect, lockstep=self.opts.lockstep, output=self.opts.output, agents=self.n,
            setpoint_rate_hz=self.opts.rate_hz, wall_s=wall_s, interrupted=self.interrupted,
            sitl_status=self.status, dead_agents={str(k): code for k, code in self.dead.items()},
            killed_agents=sorted(self.killed), events=list(self.events),
            **agent_figures(stats, list(self.steady_cpu.values()), list(self.pss.values()), CPU_WINDOW_START_S),
            sitl_cpu_fraction_of_core=self.sitl_cpu,
            swarm_link_bytes_per_s_per_vehicle=self.status.link_bytes_per_s_per_vehicle,
            signing=signing_totals(stats) if self.opts.signing else None,
        )

    def report(self, wall_s: float) -> FleetReport:
        """Score the recording (if any), write metrics.json and the figures."""
        from sim_bridge.figures import write_figures
        from sim_bridge.metrics import compute_metrics
        from sim_bridge.record import load_run

        if not (self.out / "run.json").exists():
            if not self.interrupted:
                raise RuntimeError("the SITL wrote no recording (see sitl.log)")
            # Interrupted before the SITL's first sample: report the processes, score nothing.
            report = FleetReport(self.fleet_section(wall_s))
            (self.out / "metrics.json").write_text(json.dumps(report.to_json(), indent=2))
            return report
        result = load_run(self.out, self.cfg)
        report = FleetReport(self.fleet_section(wall_s), compute_metrics(result, None))
        (self.out / "metrics.json").write_text(json.dumps(report.to_json(), indent=2))
        if self.opts.figures:
            write_figures(result, None, self.out)
        return report


def run_fleet(config_path: str | Path, opts: FleetOptions) -> tuple[FleetReport, int]:
    """Load, fly, report. Returns (the report, exit code: 0 ok, 130 interrupted)."""
    from sim_bridge.simulate import load_scenario

    cfg = load_scenario(config_path)
    opts = dataclasses.replace(opts, out_dir=Path(opts.out_dir).resolve())
    fleet = Fleet(Path(config_path).resolve(), cfg, opts)

    def on_sigint(signum, frame) -> None:  # Ctrl-C: stop the children, then report what there is
        fleet.interrupted = True
        if fleet.sitl is not None and fleet.sitl.poll() is None:
            fleet.sitl.send_signal(signal.SIGTERM)

    old = signal.signal(signal.SIGINT, on_sigint)
    old_term = signal.signal(signal.SIGTERM, on_sigint)
    try:
        report = fleet.run()
    finally:
        signal.signal(signal.SIGINT, old)
        signal.signal(signal.SIGTERM, old_term)
    return report, 130 if fleet.interrupted else 0


def parse_kill(items: list[str]) -> dict[int, float]:
    """['2@20'] -> {2: 20.0}. Raises ValueError with the offending item."""
    out = {}
    for item in items:
        k, _, t = item.partition("@")
        if not (k.isdigit() and t):
            raise ValueError(f"--kill-agent {item!r}: expected VEHICLE@SIM_SECONDS, e.g. 2@20")
        out[int(k)] = float(t)
    return out
