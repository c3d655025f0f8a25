"""`python -m sim_bridge.sitl` (the `swarmdrop sitl` entry): endpoints printed, flies, clean
shutdown on SIGINT/SIGTERM, .tlog of everything sent and received."""
from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from sim_bridge.sitl.testing import MavClient, free_udp_base_port  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _reader(stream, q: queue.Queue) -> None:
    for line in stream:
        q.put(line)
    q.put(None)


def _wait_line(q: queue.Queue, text: str, timeout_s: float) -> list[str]:
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = q.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            break
        if line is None:
            break
        lines.append(line)
        if text in line:
            return lines
    pytest.fail(f"{text!r} not printed within {timeout_s} s; got {lines}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.timeout(60)
def test_cli_runs_prints_endpoints_and_stops_cleanly(tmp_path, sig):
    base = free_udp_base_port(2)
    cfg = tmp_path / "sitl.yaml"
    cfg.write_text(f"endpoints:\n  bind_host: 127.0.0.1\n  remote_base_port: {base}\n  local_base_port: 0\n"
                   "params:\n  MIS_TAKEOFF_ALT: 4.0\n")
    tlog = tmp_path / "run.tlog"
    proc = subprocess.Popen([sys.executable, "-m", "sim_bridge.sitl", "--vehicles", "2", "--config", str(cfg),
                             "--speed", "2", "--tlog", str(tlog)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    q: queue.Queue = queue.Queue()
    threading.Thread(target=_reader, args=(proc.stdout, q), daemon=True).start()
    client = None
    try:
        lines = _wait_line(q, "SITL READY", 40)
        text = "".join(lines)
        assert f"-> 127.0.0.1:{base + 1}" in text and "sysid 2" in text and "speed x2" in text
        client = MavClient(base + 1)
        hb = client.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 2, 5)
        assert hb is not None
        client.mav.param_request_read_send(2, 1, b"MIS_TAKEOFF_ALT", -1)
        pv = client.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT", 3)
        assert pv is not None and pv.param_value == 4.0  # config params applied
        proc.send_signal(sig)
        assert proc.wait(timeout=15) == 0
        assert "stopped" in "".join(_wait_line(q, "stopped", 5))
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    log = mavutil.mavlink_connection(str(tlog))
    seen = set()
    for _ in range(100000):
        m = log.recv_match()
        if m is None:
            break
        seen.add((m.get_type(), m.get_srcSystem()))
    assert ("HEARTBEAT", 1) in seen and ("HEARTBEAT", 2) in seen  # sent
    assert ("PARAM_REQUEST_READ", 255) in seen  # received


def test_cli_rejects_bad_config(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("version: 2\nscenario: {mission: {n_vehicles: 2}}\nno_such_field: 1\n")
    proc = subprocess.run([sys.executable, "-m", "sim_bridge.sitl", "--config", str(cfg)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "no_such_field" in proc.stderr


def test_cli_says_a_scenario_given_as_config_is_a_scenario():
    proc = subprocess.run([sys.executable, "-m", "sim_bridge.sitl", "--config", "configs/small_6.yaml"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "pass it as --scenario configs/small_6.yaml" in proc.stderr, proc.stderr


@pytest.mark.parametrize("flag", [["--record", "rec"], ["--stop-when-done"]])
def test_cli_refuses_scenario_options_without_a_scenario(flag, tmp_path):
    # (--stop-when-done used to be accepted and never stop: with no mission nothing is ever done)
    args = [a if a != "rec" else str(tmp_path / "rec") for a in flag]
    proc = subprocess.run([sys.executable, "-m", "sim_bridge.sitl", "--duration", "1", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and f"{flag[0]} needs --scenario" in proc.stderr, proc.stderr
