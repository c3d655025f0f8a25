"""Where a fleet agent's CPU goes: thread CPU of each part of `swarmdrop agent`, counted inside
the agent processes of a real `swarmdrop run`.

    python -m bench.agent_parts configs/paper_40.yaml --out runs/agent_parts

runs the fleet with `--agent-python` set to a launcher that starts each agent through this
file, which wraps the agent's parts (the tick path, the plan, Agent.step, the neighbour and
autopilot reads, the sends) in counters of the thread's CPU clock and writes them at exit;
then prints the mean over the agents, per second of flight since the agent attached, next
to the process's whole CPU. The parts nest (on_autopilot holds the tick, the tick holds the
plan, ...); udp_recv and udp_send are the socket reads and sends of both links (the system
calls and, for a send on the loopback, the kernel's delivery to the receiver). The counters
cost about two clock reads a call: the whole comes out 1-2 % high.
The agents run the same code as ever; nothing is patched outside this process.
"""
from __future__ import annotations

import argparse
import atexit
import json
import os
import runpy
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT_ENV = "SWARMDROP_AGENT_PARTS_DIR"
PARTS = (  # (module, class, method, name)
    ("companion.node.tick", "TickPath", "on_autopilot", "on_autopilot"),
    ("companion.node.tick", "TickPath", "_tick", "tick"),
    ("companion.node.tick", "TickPath", "_plan", "plan"),
    ("companion.node.tick", "TickPath", "_send", "send"),
    ("companion.node.swarmlink", "SwarmLink", "poll", "swarm_poll"),
    ("companion.agent", "Agent", "step", "agent_step"),
    ("companion.output", "OutputStage", "step", "output_step"),
    ("companion.link.endpoints", "MavEndpoint", "poll_split", "autopilot_read"),
    ("companion.link.endpoints", "MavEndpoint", "flush", "flush"),
    ("companion.node.runner", "AgentNode", "write_stats", "write_stats"),
    ("companion.link.endpoints", "UdpLink", "recv", "udp_recv"),
    ("companion.link.endpoints", "UdpLink", "send", "udp_send"),
)


def _instrument(out_dir: Path) -> None:
    """Wrap PARTS in thread-CPU counters; write them to out_dir/agent_<id>.json at exit."""
    import importlib

    clock = time.thread_time_ns
    acc: dict[str, list[int]] = {}

    def wrap(cls, name: str, key: str) -> None:
        f = getattr(cls, name)
        a = acc.setdefault(key, [0, 0])

        def counted(*args, **kw):
            t0 = clock()
            try:
                return f(*args, **kw)
            finally:
                a[0] += clock() - t0
                a[1] += 1

        setattr(cls, name, counted)

    for mod, cls, meth, key in PARTS:
        wrap(getattr(importlib.import_module(mod), cls), meth, key)
    runner = importlib.import_module("companion.node.runner")
    attach = runner.AgentNode._attach
    start: list[tuple[float, float]] = []

    def attached(self):  # count from the first tick: set-up is not flight
        start.append((time.monotonic(), time.process_time()))
        for v in acc.values():
            v[0] = v[1] = 0
        return attach(self)

    runner.AgentNode._attach = attached
    vid = sys.argv[sys.argv.index("--vehicle-id") + 1] if "--vehicle-id" in sys.argv else str(os.getpid())

    def dump() -> None:
        if not start:
            return
        w0, c0 = start[0]
        wall = time.monotonic() - w0
        doc = {"wall_s": wall, "cpu_ms_per_s": (time.process_time() - c0) * 1e3 / wall,
               "parts": {k: {"ms_per_s": v[0] / 1e6 / wall, "calls_per_s": v[1] / wall,
                             "us_per_call": v[0] / 1e3 / max(1, v[1])} for k, v in acc.items()}}
        (out_dir / f"agent_{vid}.json").write_text(json.dumps(doc, indent=1))

    atexit.register(dump)


def summarize(out_dir: Path) -> dict:
    """The mean over the agents' files in out_dir. Raises FileNotFoundError if there are none."""
    docs = [json.loads(p.read_text()) for p in sorted(out_dir.glob("agent_*.json"))]
    if not docs:
        raise FileNotFoundError(f"no agent_*.json in {out_dir}: did the agents attach and exit cleanly?")

    def mean(f) -> float:
        return sum(f(d) for d in docs) / len(docs)

    return {"agents": len(docs), "cpu_ms_per_s": mean(lambda d: d["cpu_ms_per_s"]),
            "parts": {k: {f: mean(lambda d: d["parts"][k][f]) for f in ("ms_per_s", "calls_per_s", "us_per_call")}
                      for k in docs[0]["parts"]}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.agent_parts", description=__doc__.split("\n\n")[0],
                                epilog="Any other option goes to `swarmdrop run` (e.g. --dialect ardupilot --lockstep).")
    p.add_argument("config", type=Path, help="the fleet config (e.g. configs/paper_40.yaml)")
    p.add_argument("--out", type=Path, required=True, help="a new or empty directory for the run and the counts")
    a, extra = p.parse_known_args(argv)  # the rest goes to `swarmdrop run` (e.g. --dialect ardupilot)
    out = a.out.resolve()
    counts = out / "parts"
    counts.mkdir(parents=True, exist_ok=True)
    launcher = out / "agent_python"
    launcher.write_text(f"#!/bin/sh\nexec {sys.executable} {Path(__file__).resolve()} --agent \"$@\"\n")
    launcher.chmod(launcher.stat().st_mode | stat.S_IXUSR)
    cmd = [sys.executable, "-m", "swarmdrop.cli", "run", str(a.config), "--out", str(out / "run"), "--overwrite",
           "--no-figures", "--quiet", "--agent-python", str(launcher), *extra]
    fleet = subprocess.Popen(cmd, cwd=ROOT, env={**os.environ, OUT_ENV: str(counts)})
    try:
        rc = fleet.wait()
    except KeyboardInterrupt:  # Ctrl-C: the harness stops its SITL and agents (they write their counts)
        fleet.send_signal(signal.SIGINT)
        rc = fleet.wait()
    try:
        doc = summarize(counts)
    except FileNotFoundError as err:
        print(f"bench.agent_parts: swarmdrop run exited {rc}; {err}", file=sys.stderr)
        return rc or 1
    (out / "agent_parts.json").write_text(json.dumps(doc, indent=1))
    print(f"{doc['agents']} agents, {doc['cpu_ms_per_s']:.2f} ms of CPU a second each since attach")
    for k, v in doc["parts"].items():
        print(f"  {k:15s} {v['ms_per_s']:6.2f} ms/s  {v['calls_per_s']:6.1f} calls/s  {v['us_per_call']:7.1f} us/call")
    return rc


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--agent":  # an agent process, started by the launcher
        sys.path.insert(0, str(ROOT))
        _instrument(Path(os.environ[OUT_ENV]))
        if sys.argv[2] != "-m":
            sys.exit("bench.agent_parts --agent: expected -m MODULE ARGS (as swarmdrop run starts an agent)")
        module = sys.argv[3]
        sys.argv = [module, *sys.argv[4:]]
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    else:
        sys.exit(main())
