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
    console.tlog     with the console: every swarm-link frame it heard (`swarmdrop console --replay`)

With `console` (`swarmdrop run` does it unless --no-console) it also starts `swarmdrop console`
first: the SITL's radio copies every state to the console's swarm port (--medium-monitor)
and forwards the console's commands, the SITL's shared GCS endpoint feeds it the
autopilots' modes, armed states and batteries, and the harness prints the page's address.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from companion.node.stats import AgentStats
from sim_bridge.runs.fleet_report import FleetReport, FleetSection, agent_figures, signing_totals
from sim_bridge.runs.procs import (
    PORT_MAX,
    Ports,
    check_base_port,
    choose_ports,
    cpu_s,
    die_with_parent,
    log_tail,
    precompile,
    pss_mb,
    terminate_all,
)
from sim_bridge.scenario import ScenarioConfig, expected_end_s
from sim_bridge.sitl.ports import bind_tcp_port, find_free_udp_range
from sim_bridge.sitl.status import SitlStatus

NICE_MAX = 19
"""The most niceness that can be added (Linux: nice values go up to 19)."""
EXIT_INTERRUPTED = 130
EXIT_AGENTS_FAILED = 3
"""`swarmdrop run` stopped because no agent was left that could fly the mission (every
agent exited, or one exited while the SITL's clock waited for all of them to attach)."""
EPOCH_UNIX_S = 1767225600.0  # 2026-01-01T00:00:00Z: a fixed SITL clock, so lockstep runs repeat exactly
READY_TIMEOUT_S = 60.0
STOP_GRACE_S = 5.0
CPU_WINDOW_START_S = 10.0
"""Agents' CPU share is measured from this simulated time on (after start-up and setup)."""


AGENT_EXIT_GRACE_S = 2.0
"""When agents exit before the SITL's clock starts, how long the others are given to exit too
(Fleet._await_failing_agents), s."""


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
    agent_python: str | None = None
    """The interpreter the agents run on (None: `python`), e.g. a venv with only the onboard
    install (`pip install swarmdrop`) to fly the agents as a companion computer has them."""
    agent_nice: int = 0
    """Added niceness of agents (the SITL keeps priority, so simulated physics stays honest)."""
    signing: bool = False
    """Sign every link (SITL endpoints, autopilot links, swarm link) with a fresh key in the run directory."""
    overwrite: bool = False
    """Clear a non-empty out_dir first (without it, a non-empty out_dir is refused)."""
    strict: bool = False
    """Refuse a mission with feasibility warnings too (sim_bridge.scenario.scenario_findings)."""
    console: bool = False
    """Start `swarmdrop console` for the run (the CLI's default; off here so that library callers
    and benches fly without one)."""
    console_port: int = 0
    """The console page's HTTP port on 127.0.0.1 (0: a free one)."""

    def check(self) -> None:
        """Refuse options the agents or the SITL would refuse only once everything has started
        (the harness would then blame one agent for the user's option).

        Raises:
            ConfigError: naming the option, the value and the range it must be in.
        """
        from companion.config import ConfigError
        from companion.node.config import RATE_HZ_MAX, RATE_HZ_MIN

        r = self.rate_hz
        if not (math.isfinite(r) and RATE_HZ_MIN < r <= RATE_HZ_MAX):
            raise ConfigError(f"--rate {r:g}: the agents' setpoint rate must be above {RATE_HZ_MIN:g} and at most "
                              f"{RATE_HZ_MAX:g} Hz (swarmdrop agent --rate)")
        d = self.fix_delay_max_s
        if not (math.isfinite(d) and d >= 0):
            raise ConfigError(f"--fix-delay-max {d:g}: must be a finite number of seconds, 0 or more")
        if not 0 <= self.agent_nice <= NICE_MAX:
            raise ConfigError(f"--agent-nice {self.agent_nice}: must be 0 to {NICE_MAX} (niceness added to the "
                              "agents; the SITL keeps its priority)")
        py = self.agent_python
        if py is not None and shutil.which(py) is None:  # (a path, or a name on PATH)
            raise ConfigError(f"--agent-python {py}: no executable file there (give PATH/bin/python of a venv "
                              "where `pip install swarmdrop` was run)")
        if self.base_port is not None and not 1 <= self.base_port <= PORT_MAX:
            raise ConfigError(f"--base-port {self.base_port}: a UDP port is 1 to {PORT_MAX}")
        if not 0 <= self.console_port <= PORT_MAX:
            raise ConfigError(f"--console-port {self.console_port}: a TCP port is 0 to {PORT_MAX}")


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
        self._told_conflict = False
        self._sitl_told_to_stop = False
        self.aborted = ""
        """Why the harness stopped the run itself (no agent left that can fly it), or ""."""
        self.started_wall = time.time()
        """Unix time the run began: a recording older than this is not this run's."""
        self.console: subprocess.Popen | None = None
        self.console_url: str | None = None
        """The console page's address, once it is ready."""
        self._console_ports: tuple[int, int] | None = None
        """(swarm port, GCS port) the console listens on."""

    # ------------------------------------------------------------------ processes
    def _popen(self, args: list[str], stdout, nice: int = 0) -> subprocess.Popen:
        def pre() -> None:
            # Own process group: a terminal's Ctrl-C reaches only the harness, which then
            # stops the SITL and the agents in order (and reports them as stopped, not dead).
            os.setpgid(0, 0)
            die_with_parent()
            if nice:
                os.nice(nice)
        return subprocess.Popen(args, stdout=stdout, stderr=subprocess.STDOUT, preexec_fn=pre, text=True,
                                cwd=Path(__file__).resolve().parents[2])

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
        if self._console_ports is not None:
            swarm, gcs = self._console_ports
            args += ["--medium-monitor", f"127.0.0.1:{swarm}", "--gcs", "--gcs-port", str(gcs)]
        args += self._signing_args()
        self.sitl = self._popen(args, subprocess.PIPE)
        self._sitl_lines: list[str] = []
        threading.Thread(target=self._read_sitl, daemon=True).start()
        deadline = time.monotonic() + READY_TIMEOUT_S
        while "SITL READY" not in self._sitl_lines:
            if self.interrupted:
                return  # Ctrl-C while the SITL starts: stop there (run() reports an interrupted run)
            if self.sitl.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the SITL did not start:\n" + "\n".join(self._sitl_lines[-20:]))
            time.sleep(0.05)

    def _read_sitl(self) -> None:
        assert self.sitl is not None and self.sitl.stdout is not None  # (started with stdout=PIPE before this thread)
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

    def _start_console(self, ports: Ports) -> None:
        """Start `swarmdrop console` on free ports and wait for its address (a console that cannot
        start is reported and the run goes on without it)."""
        import re

        o = self.opts
        (self.out / "agents").mkdir(parents=True, exist_ok=True)
        free = find_free_udp_range(2, os.getpid() + 1)  # the console's swarm and GCS ports
        args = [o.python, "-m", "swarmdrop.cli", "console", "--mission", str(self.config_path),
                "--swarm-bind", f"127.0.0.1:{free}", "--swarm-peer", f"127.0.0.1:{ports.medium}",
                "--gcs", f"udpin://127.0.0.1:{free + 1}", "--host", "127.0.0.1", "--port", str(o.console_port),
                "--tlog", str(self.out / "console.tlog")] + self._signing_args()
        self.console = self._popen(args, subprocess.PIPE)
        lines: list[str] = []
        ready = threading.Event()

        def read() -> None:
            assert self.console is not None and self.console.stdout is not None
            with open(self.out / "agents" / "console.log", "w") as log:
                for line in self.console.stdout:
                    log.write(line)
                    log.flush()
                    if not ready.is_set():
                        lines.append(line.rstrip("\n"))
                        if line.startswith("CONSOLE READY"):
                            ready.set()

        threading.Thread(target=read, daemon=True).start()
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not ready.wait(0.05):
            if self.interrupted or self.console.poll() is not None or time.monotonic() > deadline:
                msg = "the console did not start (the run goes on without it):\n" + "\n".join(lines[-10:])
                self.events.append(msg)
                print(f"warning: {msg}", file=sys.stderr, flush=True)
                terminate_all([self.console], 2.0)
                self.console = None
                return
        text = "\n".join(lines)
        swarm = re.search(r"swarm link udp [\d.]+:(\d+)", text)
        gcs = re.search(r"gcs link \S+ \(udp port (\d+)\)", text)
        url = re.search(r"^console: (\S+)", text, re.M)
        if not (swarm and gcs and url):
            raise RuntimeError("the console did not say where it listens:\n" + text)
        self._console_ports = (int(swarm.group(1)), int(gcs.group(1)))
        self.console_url = url.group(1)
        print(f"console: {self.console_url}", flush=True)

    def _start_agents(self, ports: Ports) -> None:
        o = self.opts
        adir = self.out / "agents"
        adir.mkdir(parents=True, exist_ok=True)
        for k in range(self.n):
            args = [o.agent_python or o.python, "-m", "swarmdrop.cli", "agent", "--vehicle-id", str(k),
                    "--autopilot", f"udpin://127.0.0.1:{ports.agents[k]}", "--mission", str(self.config_path),
                    "--swarm-bind", f"127.0.0.1:{ports.agent_swarm + k}", "--swarm-peer", f"127.0.0.1:{ports.medium}",
                    "--output", o.output, "--rate", str(o.rate_hz), "--log-file", str(adir / f"agent_{k:02d}.log"),
                    "--no-stderr-log", "--stats", str(adir / f"agent_{k:02d}.json"),
                    # The SITL's autopilots boot with their stock loss action (PX4 COM_OBL_RC_ACT 0: with
                    # no RC a descent with no horizontal control, which the agents refuse): as an operator
                    # would, the agents set Hold at set-up (ArduPilot's GUIDED holds anyway).
                    "--set-loss-action", "hold",
                    # Each SITL companion port is its agent's alone (the console and ground stations
                    # use the GCS port): the streams an agent does not read only cost it CPU.
                    "--stop-unread-streams"]
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
        terminate_all(self.agents + [self.sitl, self.console], STOP_GRACE_S)

    def _ports_json(self, ports: Ports) -> dict:
        out = ports.as_dict()
        if self._console_ports is not None:
            out |= {"console_swarm_port": self._console_ports[0], "console_gcs_port": self._console_ports[1],
                    "console_url": self.console_url}
        return out

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
        if self.interrupted or self.status.complete:
            # agents stopping now are being stopped, not crashing; after MISSION COMPLETE the
            # SITL writes its recording (seconds on a loaded machine) with its autopilots
            # silent, and agents that give up on them (LINK_LOST) have done their job
            return
        for k, p in enumerate(self.agents):
            if k in self.opts.kill and k not in self.killed and sim_s >= self.opts.kill[k]:
                p.kill()
                self.killed.add(k)
                self.events.append(f"t={sim_s:.1f} s: killed agent {k} (fault injection)")
            code = p.poll()
            if code is not None and k not in self.dead:
                self.dead[k] = code
                msg = (f"agent {k} exited with code {code} at t={sim_s:.1f} s; its log ends:\n"
                       f"{log_tail(self.out / 'agents' / f'agent_{k:02d}.log')}")
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

    def _watch_identity(self, st: SitlStatus) -> None:
        """Say once when the radio refuses a second sender of a vehicle id (an agent started
        by hand with a --vehicle-id the fleet already flies): the run goes on, the impostor
        is avoided by the vehicle whose id it claims (docs/swarm.md)."""
        if st.id_conflicts and not self._told_conflict:
            self._told_conflict = True
            msg = (f"t={st.sim_s:.1f} s: the swarm radio refused {st.id_conflicts} state(s) from a second sender of a "
                   "vehicle id (two agents with one --vehicle-id?); see sitl.log")
            self.events.append(msg)
            print(f"warning: {msg}", file=sys.stderr, flush=True)

    def _await_failing_agents(self) -> None:
        """Agents that fail at start usually fail alike: give the others up to
        AGENT_EXIT_GRACE_S to exit by themselves, so that the report names every one that
        did, with its own exit code, not only the first (the run is stopped either way; the
        clock is still held at 0)."""
        deadline = time.monotonic() + AGENT_EXIT_GRACE_S
        for p in self.agents:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                p.wait(timeout=left)
            except subprocess.TimeoutExpired:
                break  # still running: it is not failing at start like the others
        self._watch_agents(0.0)

    def _hopeless(self) -> str:
        """Why the run cannot go on (no agent left that can attach or fly), or "".

        The SITL holds its clock at 0 until every vehicle's agent has attached: an agent
        that exits before then means the clock never starts. Once it runs, the mission
        goes on while any agent lives (a killed or crashed one is the autopilot's to hold).
        """
        if self.interrupted or not self.dead or self.status.complete:
            return ""
        held = self.status.rtf is None and self.status.sim_s == 0.0  # the clock is still held
        if held:
            self._await_failing_agents()
        gone = ", ".join(f"agent {k} (exit code {c})" for k, c in sorted(self.dead.items()))
        if held:
            return (f"{gone} exited before every vehicle had attached: the SITL's clock waits for all "
                    f"{self.n}, so nothing can fly; see agents/*.log")
        if all(p.poll() is not None for p in self.agents):
            return f"every agent has exited ({gone}): nobody flies the mission; see agents/*.log"
        return ""

    def run(self) -> FleetReport:
        """Fly the mission; returns metrics (written to out/metrics.json)."""
        from tqdm import tqdm

        self.out.mkdir(parents=True, exist_ok=True)
        self.started_wall = time.time()
        precompile()
        ports = choose_ports(self.n, self.opts.base_port)
        (self.out / "config.json").write_text(json.dumps(dataclasses.asdict(self.cfg), indent=1))
        wall0 = time.monotonic()
        bar = None
        try:
            if self.opts.console:
                self._start_console(ports)
            (self.out / "ports.json").write_text(json.dumps(self._ports_json(ports), indent=1))
            self._start_sitl(ports)
            assert self.sitl is not None  # (_start_sitl sets it or raises)
            if not self.interrupted:
                self._start_agents(ports)
            bar = tqdm(total=round(expected_end_s(self.cfg)), unit="sim-s", disable=not self.opts.progress,
                       desc=f"{self.cfg.name} fleet", mininterval=0.5)
            while self.sitl.poll() is None:
                if self.interrupted and not self._sitl_told_to_stop:
                    # Ctrl-C before the SITL existed (the handler found none to stop): stop it now,
                    # so that it writes what it has and exits, and this loop ends
                    self._sitl_told_to_stop = True
                    self.sitl.send_signal(signal.SIGTERM)
                st = self.status
                sim_s = st.sim_s
                self._watch_agents(sim_s)
                self._watch_sitl(sim_s)
                self._watch_identity(st)
                why = self._hopeless()
                if why:
                    self.aborted = why
                    self.events.append(f"t={sim_s:.1f} s: run stopped: {why}")
                    print(f"error: {why}", file=sys.stderr, flush=True)
                    break
                if bar is not None:
                    # the bar runs to the expected end of the mission (from the agreed transit
                    # start once there is one), so its ETA is one to completion, not to duration_s
                    bar.total = max(round(expected_end_s(self.cfg, math.nan if st.t_go_s is None else st.t_go_s)),
                                    int(sim_s))
                    bar.n = int(sim_s)
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
    def _agent_stats(self) -> list[AgentStats]:
        """Every agent's last statistics file (an empty AgentStats for one that wrote none)."""
        return [AgentStats.load(self.out / "agents" / f"agent_{k:02d}.json", vehicle_id=k) for k in range(self.n)]

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
            signing=signing_totals(stats) if self.opts.signing else None, aborted=self.aborted,
        )

    def _recorded_here(self) -> bool:
        """The SITL of this run wrote run.json and telemetry.npz (not an earlier run)."""
        try:
            return all((self.out / f).stat().st_mtime >= self.started_wall - 1.0 for f in ("run.json", "telemetry.npz"))
        except OSError:
            return False

    def report(self, wall_s: float) -> FleetReport:
        """Score the recording (if this run made one), write metrics.json and the figures.

        An interrupted or aborted run is scored as far as it got, but never as a
        completed mission (sim_bridge.reports.metrics.compute_metrics, `ended_early`).
        """
        from sim_bridge.reports.figures import write_figures
        from sim_bridge.reports.metrics import compute_metrics
        from sim_bridge.reports.record import load_run

        if not self._recorded_here():
            if not (self.interrupted or self.aborted):
                raise RuntimeError("the SITL wrote no recording (see sitl.log)")
            # Stopped before the SITL's first sample: report the processes, score nothing.
            report = FleetReport(self.fleet_section(wall_s))
            (self.out / "metrics.json").write_text(json.dumps(report.to_json(), indent=2))
            return report
        result = load_run(self.out, self.cfg)
        ended_early = "interrupted" if self.interrupted else ("aborted" if self.aborted else None)
        report = FleetReport(self.fleet_section(wall_s), compute_metrics(result, None, ended_early=ended_early))
        (self.out / "metrics.json").write_text(json.dumps(report.to_json(), indent=2))
        if self.opts.figures:
            write_figures(result, None, self.out)
        return report


def run_fleet(config_path: str | Path, opts: FleetOptions, warn=None) -> tuple[FleetReport, int]:
    """Load, check, fly, report.

    Returns (the report, exit code: 0 ok, EXIT_AGENTS_FAILED when no agent was left that
    could fly the mission, EXIT_INTERRUPTED on Ctrl-C or SIGTERM).

    Raises:
        ConfigError: a bad or infeasible scenario; an option out of range (FleetOptions.check,
            --base-port past 65535); --kill-agent naming no vehicle of it, or a time at or
            after its duration_s; or a --console-port that cannot be listened on. All before
            anything is created or started.
        RunDirError: out_dir cannot be used (not empty without overwrite, not writable).
    """
    from companion.config import ConfigError
    from sim_bridge.runs.rundir import prepare_run_dir
    from sim_bridge.scenario import load_scenario

    opts.check()
    cfg = load_scenario(config_path, runner="fleet", strict=opts.strict, warn=warn)
    n = cfg.mission.n_vehicles
    bad = sorted(k for k in opts.kill if not 0 <= k < n)
    if bad:
        raise ConfigError(f"--kill-agent {bad[0]}@...: the mission has vehicles 0..{n - 1} (mission.n_vehicles {n})")
    late = sorted((t, k) for k, t in opts.kill.items() if t >= cfg.duration_s)
    if late:
        t, k = late[0]
        raise ConfigError(f"--kill-agent {k}@{t:g}: {t:g} s is at or after the run's duration_s ({cfg.duration_s:g} s "
                          f"in {config_path}): the agent would never be killed")
    check_base_port(n, opts.base_port)
    if opts.console and opts.console_port:  # a port asked for by name must be free (0: any free one)
        try:
            bind_tcp_port(opts.console_port)
        except OSError as err:
            raise ConfigError(f"--console-port {opts.console_port}: cannot listen there ({err.strerror or err}); "
                              "choose another port, or 0 for any free one") from None
    opts = dataclasses.replace(opts, out_dir=prepare_run_dir(opts.out_dir, opts.overwrite))
    fleet = Fleet(Path(config_path).resolve(), cfg, opts)

    def on_sigint(signum, frame) -> None:  # Ctrl-C: stop the children, then report what there is
        fleet.interrupted = True
        if fleet.sitl is not None and fleet.sitl.poll() is None:
            fleet._sitl_told_to_stop = True
            fleet.sitl.send_signal(signal.SIGTERM)

    old = signal.signal(signal.SIGINT, on_sigint)
    old_term = signal.signal(signal.SIGTERM, on_sigint)
    try:
        report = fleet.run()
    finally:
        signal.signal(signal.SIGINT, old)
        signal.signal(signal.SIGTERM, old_term)
    code = EXIT_INTERRUPTED if fleet.interrupted else (EXIT_AGENTS_FAILED if fleet.aborted else 0)
    return report, code


def parse_kill(items: list[str]) -> dict[int, float]:
    """['2@20'] -> {2: 20.0}.

    Raises:
        ValueError: naming the offending item (not VEHICLE@SECONDS, a vehicle id that is
            negative, a time that is negative or not finite, or one vehicle given twice).
    """
    out: dict[int, float] = {}
    for item in items:
        k, at, t = item.partition("@")
        try:
            when = float(t)
        except ValueError:
            when = math.nan
        if at and k.startswith("-") and k[1:].isdigit():
            raise ValueError(f"--kill-agent {item!r}: vehicle id {k} is not a vehicle: ids are 0-based, 0 to "
                             "mission.n_vehicles - 1")
        if not (k.isascii() and k.isdigit() and math.isfinite(when) and when >= 0):
            raise ValueError(f"--kill-agent {item!r}: expected VEHICLE@SIM_SECONDS with SIM_SECONDS >= 0, e.g. 2@20")
        if int(k) in out:
            raise ValueError(f"--kill-agent {item!r}: agent {k} is already killed at {out[int(k)]:g} s")
        out[int(k)] = when
    return out
