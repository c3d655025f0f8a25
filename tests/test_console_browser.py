"""The console's page in a real browser: Debian's Chromium driven by Playwright.

Skipped, with the reason, when Chromium (/usr/bin/chromium) or Playwright's Python package
is missing (`make test` says so too). Never `playwright install`: the system Chromium is
launched by path. Every process a test starts it stops by PID; everything listens on
127.0.0.1; the tests wait for page conditions (Playwright's waits, with deadlines), never
for a fixed time. Screenshots go to the test's tmp directory (and to docs/img/ when
SWARMDROP_DOCS_IMG=1: docs/img/console_live.png and console_replay.png).

Pages are opened with Playwright's bypass_csp, which its wait_for_function needs (it
evaluates its predicate with eval); test_page_runs_under_its_own_csp checks that the page
itself works under the console's Content-Security-Policy.
"""
from __future__ import annotations

import math
import os
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
SMALL6 = ROOT / "configs" / "small_6.yaml"
DOCS_IMG = ROOT / "docs" / "img"

try:
    from playwright.sync_api import expect, sync_playwright
except ImportError:
    pytest.skip("Playwright's Python package is not installed (pip install playwright, in the test extra); the "
                "console's browser tests are skipped", allow_module_level=True)
if not os.access(CHROMIUM, os.X_OK):
    pytest.skip(f"no Chromium at {CHROMIUM} (apt-get install -y chromium); the console's browser tests are skipped",
                allow_module_level=True)
try:
    import aiohttp  # noqa: F401  (the console's web stack, in the test extra)
except ImportError:
    pytest.skip("aiohttp is not installed (pip install 'swarmdrop[console]'); the console's browser tests are skipped",
                allow_module_level=True)

pytestmark = pytest.mark.browser


def _stop(proc: subprocess.Popen | None, grace_s: float = 10.0) -> None:
    """SIGTERM, then SIGKILL: by PID, only the process the test started."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _wait_for_line(log: Path, proc: subprocess.Popen, pattern: str, timeout_s: float) -> re.Match:
    """The first match of pattern in a process's output file (polled with a deadline)."""
    deadline = time.monotonic() + timeout_s
    while True:
        text = log.read_text(errors="replace") if log.exists() else ""
        m = re.search(pattern, text, re.M)
        if m:
            return m
        assert proc.poll() is None, f"exited with {proc.returncode}:\n{text[-3000:]}"
        assert time.monotonic() < deadline, f"no {pattern!r} within {timeout_s} s:\n{text[-3000:]}"
        time.sleep(0.05)  # (polling a log file for a line; not a wait for the page)


class Console:
    """A `swarmdrop console` process on free ports."""

    def __init__(self, tmp: Path, *args: str):
        self.log = tmp / f"console-{time.monotonic_ns()}.log"
        self.proc = subprocess.Popen([sys.executable, "-m", "swarmdrop.cli", "console", "--port", "0", *args], cwd=ROOT,
                                     stdout=open(self.log, "w"), stderr=subprocess.STDOUT)
        _wait_for_line(self.log, self.proc, r"^CONSOLE READY", 60)
        text = self.log.read_text()
        self.url = re.search(r"^console: (\S+)", text, re.M).group(1)  # type: ignore[union-attr]
        m = re.search(r"swarm link udp [\d.]+:(\d+)", text)
        self.swarm_port = int(m.group(1)) if m else None

    def stop(self) -> None:
        _stop(self.proc)


@pytest.fixture(scope="module")
def browser():
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def _page(browser, bypass_csp: bool = True):
    ctx = browser.new_context(viewport={"width": 1400, "height": 860}, bypass_csp=bypass_csp)
    page = ctx.new_page()
    page.errors = []  # type: ignore[attr-defined]
    page.on("pageerror", lambda e: page.errors.append(str(e)))  # type: ignore[attr-defined]
    page.on("console", lambda m: page.errors.append(m.text) if m.type == "error" else None)  # type: ignore[attr-defined]
    return page


def _shot(page, tmp_path: Path, name: str, docs: bool = False) -> Path:
    out = tmp_path / f"{name}.png"
    page.screenshot(path=str(out))
    if docs and os.environ.get("SWARMDROP_DOCS_IMG") == "1":
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(DOCS_IMG / f"{name}.png"))
    return out


class Feed:
    """Synthetic SWARMDROP_STATEs of n vehicles at 10 Hz from a thread (swarmdrop.console.synthetic)."""

    def __init__(self, port: int, n: int = 6):
        from swarmdrop.console import synthetic

        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=synthetic.run, args=(n, 10.0, ("127.0.0.1", port)),
                                       kwargs={"stop": self.stop_event.is_set}, daemon=True)
        self.thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(5)


def _moved(page, before: list[float], n: int, metres: float = 0.1, timeout_ms: int = 10_000) -> None:
    page.wait_for_function(
        """([before, n, d]) => { const p = SDConsole.positions(); if (p.length < 3 * n) return false;
             for (let i = 0; i < n; i++) { if (!(Math.hypot(p[3*i] - before[3*i], p[3*i+1] - before[3*i+1]) > d)) return false; }
             return true; }""", arg=[before, n, metres], timeout=timeout_ms)


# ---------------------------------------------------------------------------- (a) a synthetic feed
def test_synthetic_feed_of_six_vehicles_drawn_moving_and_tabled(browser, tmp_path):
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    con = Console(tmp_path, "--mission", str(SMALL6), "--swarm-bind", "127.0.0.1:0", "--swarm-peer",
                  f"127.0.0.1:{peer.getsockname()[1]}")
    feed = Feed(con.swarm_port)
    page = _page(browser)
    try:
        page.goto(con.url)
        page.wait_for_function("() => window.SDConsole && SDConsole.info().known === 6 && SDConsole.info().drawn === 6",
                               timeout=15_000)
        _moved(page, page.evaluate("() => SDConsole.positions()"), 6)
        # the table: every vehicle with its phase and the age of its last state, heard at ~10 states/s
        page.wait_for_function("() => document.querySelectorAll('#vtab tbody tr:not([hidden])').length === 6",
                               timeout=5_000)
        # every age under 1 s (awaited, not read once: the feed's thread may lag a moment)
        page.wait_for_function("() => [...document.querySelectorAll('#vtab tbody tr:not([hidden]) td:nth-child(3)')]"
                               ".every(td => { const a = parseFloat(td.textContent); return a >= 0 && a < 1.0; })",
                               timeout=5_000)
        rows = page.locator("#vtab tbody tr:not([hidden])")
        phases = ["launch", "stabilise", "assemble", "transit", "hover", "land"]
        for k in range(6):
            cells = rows.nth(k).locator("td").all_inner_texts()
            assert cells[0] == str(k) and cells[1].strip() == phases[k], cells
        page.wait_for_function("() => [...document.querySelectorAll('#vtab tbody tr:not([hidden]) td:nth-child(4)')]"
                               ".every(td => parseFloat(td.textContent) >= 8)", timeout=15_000)
        expect(page.locator("#h-heard")).to_have_text("6 / 6")
        assert page.locator("#h-age99").inner_text().endswith(" s")
        # the cursor's geodetic readout, and the page's WGS-84 conversion against pymap3d's
        box = page.locator("#map").bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        expect(page.locator("#readout")).to_contain_text("°N")
        import numpy as np

        from companion.frames import ned_to_geodetic

        for ned in ((0.0, 0.0, 0.0), (1234.5, -987.6, -120.0), (-5000.0, 3000.0, 40.0)):
            js = page.evaluate("(p) => SDConsole.geo(p[0], p[1], p[2])", list(ned))
            lat, lon, alt = ned_to_geodetic(np.array(ned), 47.397742, 8.545594, 488.0)
            assert js[0] == pytest.approx(float(lat), abs=1e-9) and js[1] == pytest.approx(float(lon), abs=1e-9)
            assert js[2] == pytest.approx(float(alt), abs=1e-3)
        _shot(page, tmp_path, "synthetic_six")
        # a command from the page: HOLD goes out at once as a plan to the swarm peer
        page.click("#cmd-hold")
        expect(page.locator("#cmdlog")).to_contain_text("HOLD sent as plan 1")
        assert _plans_received(peer, 1)[0]["kind"] == 1
        # LAND asks first: cancelled, nothing is sent; confirmed, the plan lands every vehicle
        page.click("summary:has-text('LAND')")
        page.click("#cmd-land")
        expect(page.locator("#confirm")).to_be_visible()
        page.click("#confirmno")
        expect(page.locator("#cmdlog")).to_contain_text("cancelled")
        page.click("#cmd-land")
        page.click("#confirmyes")
        expect(page.locator("#cmdlog")).to_contain_text("LAND sent as plan 2")
        plans = _plans_received(peer, 2)
        assert plans[-1]["kind"] == 7 and plans[-1]["landing"][0] == 0b111111
        assert page.errors == [] and page.evaluate("() => SDConsole.info().lastError") is None, page.errors  # type: ignore[attr-defined]
    finally:
        feed.stop()
        page.context.close()
        con.stop()
        peer.close()


def _plans_received(sock: socket.socket, seq: int, timeout_s: float = 5.0) -> list[dict]:
    """SWARMDROP_PLANs received on sock until one with this seq (decoded field by field)."""
    from companion.link.enums import MsgId
    from companion.link.framing import split_datagram
    from companion.link.msgdef import swarmdrop as sd
    from companion.link.wire import Codec

    codec = Codec(sd)
    out: list[dict] = []
    deadline = time.monotonic() + timeout_s
    while not any(p["seq"] == seq for p in out):
        left = deadline - time.monotonic()
        assert left > 0, f"no plan {seq} received"
        if not select.select([sock], [], [], left)[0]:
            continue
        for f in split_datagram(sock.recv(65536))[0]:
            if (f[7] | f[8] << 8 | f[9] << 16) == MsgId.SWARMDROP_PLAN:
                m = codec.decode(f)
                out.append({"seq": m.seq, "kind": m.kind, "landing": m.landing})
    return out


def test_page_runs_under_its_own_csp(browser, tmp_path):
    """No bypass: the page's scripts, styles and websocket are all allowed by the console's CSP."""
    con = Console(tmp_path, "--swarm-bind", "127.0.0.1:0", "--no-commands")
    feed = Feed(con.swarm_port, n=3)
    page = _page(browser, bypass_csp=False)
    try:
        page.goto(con.url)
        expect(page.locator("#conn")).to_have_text("connected", timeout=10_000)
        expect(page.locator("#h-heard")).to_have_text("3 / 3", timeout=10_000)
        expect(page.locator("#vtab tbody tr:not([hidden])")).to_have_count(3)
        assert not [e for e in page.errors if "Content Security Policy" in e], page.errors  # type: ignore[attr-defined]
    finally:
        feed.stop()
        page.context.close()
        con.stop()


# ---------------------------------------------------------------------------- (b) replay
@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    import yaml

    from companion.config import read_yaml

    tmp = tmp_path_factory.mktemp("replay")
    data = read_yaml(SMALL6)
    data["duration_s"] = 50.0
    cfg = tmp / "small_6_50s.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    proc = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "simulate", str(cfg), "--out", str(tmp / "run"),
                           "--quiet", "--no-figures"], cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    return tmp / "run"


def test_replay_of_a_run_directory_scrubs_the_vehicles(browser, tmp_path, run_dir):
    con = Console(tmp_path, "--replay", str(run_dir))
    page = _page(browser)
    try:
        page.goto(con.url)
        expect(page.locator("#mode")).to_have_text("REPLAY", timeout=10_000)
        expect(page.locator("#replaybar")).to_be_visible()
        page.wait_for_function("() => SDConsole.info().drawn === 6", timeout=10_000)
        page.click("#play")  # it plays from the start: pause it
        page.wait_for_function("() => SDConsole.state.status && SDConsole.state.status.replay.playing === false",
                               timeout=5_000)
        at = page.evaluate("() => SDConsole.info().t")
        # The run stops when its mission completes (before duration_s): the slider spans what was recorded.
        t0, t1 = page.evaluate("() => [SDConsole.state.status.replay.t0, SDConsole.state.status.replay.t1]")
        assert 30.0 < t1 - t0 <= 50.0
        before = page.evaluate("() => SDConsole.positions()")
        for value, where in (("800", 0.8), ("150", 0.15)):
            page.locator("#scrub").fill(value)  # dragging the time slider
            t_want = t0 + where * (t1 - t0)
            page.wait_for_function("(t) => Math.abs(SDConsole.info().t - t) < 0.5", arg=t_want, timeout=5_000)
            after = page.evaluate("() => SDConsole.positions()")
            moved = [math.hypot(after[3 * i] - before[3 * i], after[3 * i + 1] - before[3 * i + 1]) for i in range(6)]
            assert min(moved) > 1.0, (where, moved)
            before = after
            expect(page.locator("#rtime")).to_contain_text(f"t {page.evaluate('() => SDConsole.info().t'):.1f} s")
        assert at < 45.0
        page.select_option("#speed", "8")
        page.click("#play")
        page.wait_for_function("() => SDConsole.info().t > 12.0", timeout=10_000)  # 8x from 7.5 s
        page.click("#fit")
        page.locator("#scrub").fill("700")
        page.wait_for_function("(t) => SDConsole.info().t > t", arg=t0 + 0.68 * (t1 - t0), timeout=5_000)
        page.click("#play")  # pause there for the picture
        page.wait_for_function("() => SDConsole.state.status && SDConsole.state.status.replay.playing === false",
                               timeout=5_000)
        page.click("#fit")
        _shot(page, tmp_path, "console_replay", docs=True)
        assert page.errors == [] and page.evaluate("() => SDConsole.info().lastError") is None, page.errors  # type: ignore[attr-defined]
    finally:
        page.context.close()
        con.stop()


# ---------------------------------------------------------------------------- (c) the fleet, end to end
@pytest.mark.timeout(600)
def test_fleet_end_to_end_hold_resume_formation_land(browser, tmp_path):
    out = tmp_path / "fleet"
    log = tmp_path / "fleet.log"
    harness = subprocess.Popen([sys.executable, "-m", "swarmdrop.cli", "run", str(SMALL6), "--out", str(out), "--quiet",
                                "--no-figures"], cwd=ROOT, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    page = _page(browser)
    try:
        url = _wait_for_line(log, harness, r"^console: (\S+)", 90).group(1)
        page.goto(url)
        page.wait_for_function("() => SDConsole.info().known === 6 && SDConsole.info().drawn === 6", timeout=60_000)
        _moved(page, page.evaluate("() => SDConsole.positions()"), 6, metres=0.5, timeout_ms=60_000)
        # in formation flight (TRANSIT) with the autopilots' modes on the page
        page.wait_for_function("() => { const s = SDConsole.state.status; return s && s.health.phases.transit === 6 "
                               "&& s.ap && s.ap.mode.every(m => m.length > 0); }", timeout=120_000)
        page.click("#fit")
        _shot(page, tmp_path, "console_live", docs=True)
        speed = "() => { const s = SDConsole.state.status; return s && s.health.centre_speed_mps; }"
        # HOLD: the formation centre stops (the plan takes effect 0.3 s after it is sent, then brakes
        # from 3 m/s: about 1.6 s of flight; the wait allows a busy machine's SITL under real time)
        page.click("#cmd-hold")
        expect(page.locator("#cmdlog")).to_contain_text("HOLD sent")
        page.wait_for_function(f"() => ({speed})() !== null && ({speed})() < 0.1", timeout=8_000)
        # RESUME: it moves on
        page.click("#cmd-resume")
        page.wait_for_function(f"() => ({speed})() > 0.5", timeout=10_000)
        # FORMATION: a line; every vehicle takes the new plan and reaches its slot
        page.click("summary:has-text('FORMATION')")
        page.select_option("#f-shape", "line")
        page.fill("#f-spacing", "4")
        page.click("#cmd-formation")
        expect(page.locator("#cmdlog")).to_contain_text("FORMATION sent as plan 3")
        page.wait_for_function("() => { const s = SDConsole.state.status; return s && s.holders['3'] && "
                               "s.holders['3'].count === 6 && s.health.ferr_max_m !== null && s.health.ferr_max_m < 1.0; }",
                               timeout=60_000)
        _shot(page, tmp_path, "console_formation")
        # LAND (confirmed): every vehicle lands and its autopilot disarms
        page.click("summary:has-text('LAND')")
        page.click("#cmd-land")
        page.click("#confirmyes")
        expect(page.locator("#cmdlog")).to_contain_text("LAND sent")
        page.wait_for_function("() => { const s = SDConsole.state.status; return s && s.ap && "
                               "s.ap.armed.every(a => a === 0) && s.health.phases.land === 6; }", timeout=120_000)
        _shot(page, tmp_path, "console_landed")
    finally:
        page.context.close()
        _stop(harness, 30.0)  # the harness stops the SITL, the agents and the console it started
