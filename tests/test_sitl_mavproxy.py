"""Unmodified MAVProxy (PyPI MAVProxy) flies vehicle k of a SITL through its text commands."""
from __future__ import annotations

import queue
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from sim_bridge.sitl.background import BackgroundSitl
from sim_bridge.sitl.config import sitl_config
from sim_bridge.sitl.testing import local_endpoints

MAVPROXY = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent)) or shutil.which("mavproxy.py")
pytestmark = pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (test extra)")

N, K = 2, 1


def _until(pred, timeout_s: float, what: str, output: list[str]) -> None:
    """Poll a condition on the SITL's own state with a deadline."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.05)  # polling interval of the condition, not synchronisation
    pytest.fail(f"{what} not reached within {timeout_s} s; MAVProxy said:\n{''.join(output[-40:])}")


@pytest.mark.timeout(120)
def test_mavproxy_sets_param_arms_takes_off_lands(tmp_path):
    with BackgroundSitl(sitl_config(N, endpoints=local_endpoints(N))) as sitl:
        ap = sitl.autopilots[K]
        port = sitl.cfg.endpoints.vehicle_remote_port(K)
        proc = subprocess.Popen(
            [sys.executable, MAVPROXY, f"--master=udpin:127.0.0.1:{port}", f"--target-system={K + 1}",
             f"--state-basedir={tmp_path}", "--default-modules=param,arm,cmdlong,mode"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
        )
        output: list[str] = []
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True).start()

        def said(text: str) -> bool:
            while not lines.empty():
                output.append(lines.get())
            return any(text in line for line in output)

        def send(cmd: str) -> None:
            proc.stdin.write(cmd + "\n")
            proc.stdin.flush()

        try:
            _until(lambda: said("Detected vehicle"), 20, "MAVProxy detecting the vehicle", output)
            # MAVProxy sets only parameters it has fetched: wait for its full parameter list
            _until(lambda: said("parameters"), 30, "MAVProxy fetching the parameter list", output)
            send("param set MIS_TAKEOFF_ALT 3.5")
            _until(lambda: ap.params["MIS_TAKEOFF_ALT"] == pytest.approx(3.5), 10, "parameter set", output)
            send("arm throttle")
            _until(lambda: ap.armed, 10, "armed", output)
            send("long NAV_TAKEOFF 0 0 0 0 nan nan nan")
            home_z = sitl.home_ned_m[K][2]
            _until(lambda: abs(sitl.state.pos_ned_m[K, 2] - (home_z - 3.5)) < 0.3 and not ap.landed, 20,
                   "take-off to MIS_TAKEOFF_ALT", output)
            send("long NAV_LAND 0 0 0 0 nan nan nan")
            _until(lambda: ap.landed and not ap.armed, 40, "landing and auto-disarm", output)
            assert not sitl.autopilots[0].armed  # the other vehicle never moved
        finally:
            try:
                send("exit")
                proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                proc.kill()  # MAVProxy ignores SIGTERM while its threads run
                proc.wait(timeout=10)
