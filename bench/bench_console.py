"""Console bench: the page's frame time with 1,000 vehicles at 10 Hz, measured in the browser.

A `swarmdrop console` (no mission: vehicles only, as a feed of any size is shown) listens on
a free port; `python -m swarmdrop.console.synthetic` sends 1,000 vehicles' SWARMDROP_STATEs at
10 Hz each (10,000 states/s, the banked ids past 249) to it; Debian's Chromium (headless,
software rendering: --disable-gpu) opens the page with Playwright. After a warm-up the page's
own requestAnimationFrame timing is read for MEASURE_S seconds: the interval between frames
(what the operator sees; the target is p95 <= 50 ms) and the time the drawing itself took.
Every process it starts, it stops.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

from sim_bridge.runs.procs import cpu_s

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
VEHICLES = 1000
RATE_HZ = 10.0
WARM_S = 5.0
MEASURE_S = 15.0
TARGET_P95_MS = 50.0


def start_console(args: list[str], log: Path) -> tuple[subprocess.Popen, str, int]:
    """A console process, ready: (process, page URL, swarm port)."""
    proc = subprocess.Popen([sys.executable, "-m", "swarmdrop.cli", "console", "--port", "0", *args], cwd=ROOT,
                            stdout=open(log, "w"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    text = ""
    while "CONSOLE READY" not in text:
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError("the console did not start:\n" + text)
        time.sleep(0.05)  # (polling its log for the ready line)
        text = log.read_text(errors="replace")
    url = re.search(r"^console: (\S+)", text, re.M)
    port = re.search(r"swarm link udp [\d.]+:(\d+)", text)
    assert url and port
    return proc, url.group(1), int(port.group(1))


def run(vehicles: int = VEHICLES, measure_s: float = MEASURE_S, screenshot: Path | None = None) -> dict:
    import tempfile

    from playwright.sync_api import sync_playwright

    from sim_bridge.sitl.ports import find_free_udp_range

    with tempfile.TemporaryDirectory(prefix="swarmdrop-console-bench-") as d:
        swarm_port = find_free_udp_range(1, os.getpid())
        console, url, port = start_console(["--swarm-bind", f"127.0.0.1:{swarm_port}", "--no-commands"],
                                           Path(d) / "console.log")
        feed = None
        try:
            feed = subprocess.Popen([sys.executable, "-m", "swarmdrop.console.synthetic", "--vehicles", str(vehicles),
                                     "--rate", str(RATE_HZ), "--to", f"127.0.0.1:{port}"], cwd=ROOT,
                                    stdout=subprocess.DEVNULL, stderr=open(Path(d) / "feed.log", "w"))
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                try:
                    page = browser.new_context(viewport={"width": 1600, "height": 1000}, bypass_csp=True).new_page()
                    page.goto(url)
                    page.wait_for_function(f"() => window.SDConsole && SDConsole.info().known >= {vehicles}",
                                           timeout=60_000)
                    page.click("#fit")
                    page.evaluate("() => SDConsole.setFlushDraw(true)")  # time the rasterisation too
                    page.wait_for_timeout(WARM_S * 1000)  # (the bench's warm-up: JIT, caches, a full trail)
                    page.evaluate("() => SDConsole.resetTimes()")
                    info0 = page.evaluate("() => SDConsole.info()")
                    cpu0 = (cpu_s(console.pid), time.monotonic())
                    page.wait_for_timeout(measure_s * 1000)  # (the measuring window)
                    stats = page.evaluate("() => SDConsole.frameStats()")
                    info1 = page.evaluate("() => SDConsole.info()")
                    cpu1 = (cpu_s(console.pid), time.monotonic())
                    if screenshot is not None:
                        page.screenshot(path=str(screenshot))
                finally:
                    browser.close()
        finally:
            for proc in (feed, console):
                if proc is not None and proc.poll() is None:
                    proc.terminate()
                    try:
                        proc.wait(10)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
    span = measure_s
    console_cpu = (cpu1[0] - cpu0[0]) / (cpu1[1] - cpu0[1]) if cpu0[0] is not None and cpu1[0] is not None else None
    return {
        "name": "console",
        "description": f"swarmdrop console page, {vehicles} synthetic vehicles at {RATE_HZ:g} Hz each over UDP, "
                       "headless Chromium (software rendering), requestAnimationFrame timing read by Playwright",
        "vehicles": vehicles, "states_per_s": vehicles * RATE_HZ, "measured_s": span,
        "frame_interval_ms": {"p50": stats["frame_p50"], "p95": stats["frame_p95"], "max": stats["frame_max"],
                              "count": stats["count"]},
        "draw_ms": {"p50": stats["draw_p50"], "p95": stats["draw_p95"]},
        "frames_received_per_s": (info1["frames"] - info0["frames"]) / span,
        "frames_drawn_per_s": (info1["framesDrawn"] - info0["framesDrawn"]) / span,
        "vehicles_known": info1["known"], "vehicles_drawn": info1["drawn"],
        "console_cpu_fraction_of_core": console_cpu,
        "target_p95_ms": TARGET_P95_MS, "target_met": stats["frame_p95"] is not None and stats["frame_p95"] <= TARGET_P95_MS,
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
