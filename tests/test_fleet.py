"""`swarmdrop run` end to end: the SITL and one agent process per vehicle over real
sockets on 127.0.0.1, every run in lockstep (deterministic, as fast as the machine).

Small 4-vehicle versions of configs/small_6.yaml keep each run near 10 s of wall time.
The runs are shared by the tests of this module (one fixture per run, made on first use).
What is checked is physics and protocol: where the vehicles are (telemetry.npz, the
SITL's true states), what crossed the MAVLink links (sitl.tlog, read with pymavlink),
and what the harness reports (metrics.json).
"""
from __future__ import annotations

import itertools
import json
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from companion.agent import Phase  # noqa: E402
from companion.avoidance import settled_rows  # noqa: E402
from companion.control.ghost import ghost_capsules  # noqa: E402
from companion.frames import geodetic_to_ned  # noqa: E402
from companion.link.dialects import Mode, dialect_named  # noqa: E402
from companion.link.dialects.base import AfterLoss  # noqa: E402
from companion.mission import MissionConfig  # noqa: E402
from sim_bridge.runs.fleet import EPOCH_UNIX_S  # noqa: E402
from sim_bridge.sitl.heartbeat import HEARTBEAT_PERIOD_S, HEARTBEAT_PHASE_STEP_S  # noqa: E402

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
PX4 = dialect_named("px4")
ARDUPILOT = dialect_named("ardupilot")
N = 4
RUN_TIMEOUT_S = 150.0
COMPANION_COMPID = 191
COM_OF_LOSS_T = 1.0  # the SITL's PX4 default (sim_bridge/sitl/autopilots/px4.py); the harness does not change it
AUTOPILOT_PERIOD_S = 0.02  # the SITL's mode/failsafe logic runs at 50 Hz of simulated time
KILLED = 2
KILL_WAYPOINTS = ((20.0, 0.0, -10.0), (45.0, 6.0, -12.0))
"""A longer leg for the kill runs: the station lies beyond the reach of the silent vehicle's
ghost, left where it fell silent (a slot within it is given up as far as its push goes)."""
KILL_AT_S = 14.0
"""This config with the shipped estimator bias: vehicles released 0-3 s and in ASSEMBLE by
~9 s (the agent's own stabilisation check). The harness kills on its 1 Hz (wall)
status, so the kill lands somewhere in [14 s, ~20 s]: once the vehicle has flown formation
(its agent has sent setpoints), before the mission completes. (At 8 s a vehicle could still
be in STABILISE, its agent never having sent a setpoint.)"""


# ---------------------------------------------------------------------------- helpers
def write_config(dir_: Path, name: str, waypoints=((20.0, 0.0, -10.0), (30.0, 6.0, -12.0)), **top) -> Path:
    """configs/small_6.yaml cut down to 4 vehicles, a 6 m circle and a short leg (no obstacle)."""
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["name"] = name
    data["duration_s"] = 90.0
    data["completion_hold_s"] = 1.0
    m = data["mission"]
    m["n_vehicles"] = N
    m["formation"] = {"radius_m": 6.0}
    m["waypoints_ned_m"] = [list(w) for w in waypoints]
    m["obstacles"] = []
    data["output"] = {"snapshot_times_s": [10.0], "attitude_vehicles": [1, 2, 3, 4], "avoidance_vehicles": [1, 4]}
    data.update(top)
    path = dir_ / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def processes_mentioning(text: str) -> list[tuple[int, str]]:
    """(pid, cmdline) of every live process whose command line contains text (Linux /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = next((ln for ln in (d / "status").read_text().splitlines() if ln.startswith("State:")), "")
        except OSError:
            continue
        if text in cmd and "zombie" not in state:
            out.append((int(d.name), cmd))
    return out


def wait_gone(out: Path, timeout_s: float = 10.0) -> list[tuple[int, str]]:
    """Wait until every process of a run (SITL, agents: all name the run directory) has
    ended; returns those still alive at the deadline."""
    deadline = time.monotonic() + timeout_s
    left = processes_mentioning(str(out))
    while left and time.monotonic() < deadline:
        time.sleep(0.1)  # polling a condition (process exit) with a deadline
        left = processes_mentioning(str(out))
    return left


class Run:
    """One `swarmdrop run` (CLI in a subprocess, as a user runs it) and its run directory."""

    def __init__(self, out: Path, proc: subprocess.CompletedProcess, wall_s: float):
        self.out, self.proc, self.wall_s = out, proc, wall_s
        assert proc.returncode in (0, 1), f"swarmdrop run failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
        self.metrics = json.loads((out / "metrics.json").read_text())
        with np.load(out / "telemetry.npz") as z:
            self.tel = {k: z[k] for k in z.files}
        self.leftovers = wait_gone(out)

    @property
    def tlog(self) -> Path:
        return self.out / "sitl.tlog"

    def released_mask(self) -> np.ndarray:
        """(T, N): the vehicle has left the carrier (docked vehicles share the carrier's point)."""
        return self.tel["t_s"][:, None] >= self.tel["release_s"][None, :] - 1e-9

    def min_separation_m(self) -> tuple[float, tuple[int, int], float]:
        """Smallest distance between any two released vehicles over the whole run."""
        pos, rel, t = self.tel["pos_ned_m"].astype(float), self.released_mask(), self.tel["t_s"]
        best = (np.inf, (-1, -1), np.nan)
        for i, j in itertools.combinations(range(pos.shape[1]), 2):
            both = rel[:, i] & rel[:, j]
            if not both.any():
                continue
            d = np.linalg.norm(pos[both, i] - pos[both, j], axis=1)
            k = int(np.argmin(d))
            if d[k] < best[0]:
                best = (float(d[k]), (i, j), float(t[both][k]))
        return best

    def final_slot_error_m(self) -> np.ndarray:
        """Distance of every vehicle from its formation slot at the end of the run."""
        return np.linalg.norm(self.tel["pos_ned_m"][-1].astype(float) - self.tel["slot_ned_m"][-1], axis=1)


def fly(out: Path, config: Path, *extra: str) -> Run:
    cmd = [sys.executable, "-m", "swarmdrop.cli", "run", str(config), "--out", str(out), "--lockstep", "--quiet",
           "--no-figures", *extra]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
    return Run(out, proc, time.monotonic() - t0)


def read_tlog(path: Path, types: list[str]) -> list:
    """Messages of the given types, in order, with their tlog timestamps (pymavlink)."""
    conn = mavutil.mavlink_connection(str(path))
    out = []
    try:
        while True:
            m = conn.recv_match(type=types)
            if m is None:
                return out
            out.append(m)
    finally:
        conn.close()


def check_completed_run(run: Run, dialect) -> None:
    """The acceptance checks, re-derived where possible from the true trajectories."""
    m = run.metrics
    assert m["checks"] and all(m["checks"].values()), m["checks"]
    assert m["fleet"]["dead_agents"] == {} and m["fleet"]["killed_agents"] == []
    assert m["fleet"]["dialect"] == dialect.name and m["fleet"]["lockstep"] is True
    assert m["separation"]["min_pair_distance_m"] >= 1.0
    assert m["formation_deviation"]["final_max_m"] < 0.05
    d_min, pair, t = run.min_separation_m()
    assert d_min >= 1.0, f"vehicles {pair} {d_min:.2f} m apart at t={t:.2f} s"
    err = run.final_slot_error_m()
    assert (err < 0.05).all(), err
    assert (run.tel["phase"][-1] == Phase.HOVER).all(), run.tel["phase"][-1]
    assert run.leftovers == [], run.leftovers
    # Every agent engaged offboard and never saw it left, although the SITL's PX4 shows the new
    # mode only in its next 1 Hz HEARTBEAT, after the ACK (the order of a false "left offboard").
    stats = [json.loads(p.read_text()) for p in sorted((run.out / "agents").glob("agent_*.json"))]
    assert len(stats) == N and all(st["left_offboard"] == 0 for st in stats), [st["left_offboard"] for st in stats]
    for k in range(N):
        assert "autopilot in " in (run.out / "agents" / f"agent_{k:02d}.log").read_text()


def check_tlog(run: Run, dialect) -> None:
    """pymavlink reads the tlog: the vehicles' heartbeats in the dialect, every agent's
    setpoints, timestamps on the SITL's clock (epoch + simulation time)."""
    msgs = read_tlog(run.tlog, ["HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED"])
    sim_end = run.metrics["performance"]["sim_s"]
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1]
    sp = [m for m in msgs if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert {m.get_srcSystem() for m in hb} == set(range(1, N + 1))
    assert all(m.autopilot == dialect.autopilot_id and m.type == 2 for m in hb)
    offboard = dialect.custom_mode(Mode.OFFBOARD)
    assert {m.get_srcSystem() for m in hb if m.custom_mode == offboard and m.base_mode & 128} == set(range(1, N + 1))
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in sp} == {(k, COMPANION_COMPID) for k in range(1, N + 1)}
    assert all(m.target_system == m.get_srcSystem() and m.coordinate_frame == 1 for m in sp)
    stamps = np.array([m._timestamp for m in msgs]) - EPOCH_UNIX_S
    assert stamps.min() >= -1e-6 and stamps.max() <= sim_end + 1e-6
    assert (np.diff(stamps) >= -1e-6).all()  # written in simulated-time order
    # pymavlink's own log tool reads it too
    tool = Path(sys.executable).parent / "mavlogdump.py"
    if not tool.exists():
        pytest.skip("mavlogdump.py is not installed beside the interpreter")
    dump = subprocess.run([sys.executable, str(tool), "--types", "HEARTBEAT,SET_POSITION_TARGET_LOCAL_NED",
                           str(run.tlog)], capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, MAVLINK20="1", TZ="UTC"))  # it prints local time
    assert dump.returncode == 0, dump.stderr[-2000:]
    assert "HEARTBEAT" in dump.stdout and "SET_POSITION_TARGET_LOCAL_NED" in dump.stdout
    assert dump.stdout.startswith("2026-01-01 00:00:00")  # the SITL's fixed epoch


def loss_params_from_tlog(run: Run, dialect, sysid: int) -> dict[str, float]:
    """The loss parameters the killed vehicle's autopilot reported (the agent reads them at
    set-up; integers travel bytewise in PX4's encoding)."""
    msgs = read_tlog(run.tlog, ["PARAM_VALUE"])
    out = {}
    for m in msgs:
        if m.get_srcSystem() == sysid and m.param_id in dialect.loss_params:
            v = m.param_value
            if m.param_id == "COM_OBL_RC_ACT":
                v = struct.unpack("<i", struct.pack("<f", v))[0]
            out[m.param_id] = v
    return out


def assert_path_inside_ghost(run: Run, config: Path, loss, t_last_s: float, killed: int) -> None:
    """The killed vehicle's true path from its last setpoint on lies inside its ghost
    (companion.control.ghost), from its true state at that time, twice over:

    * the bound: its own autopilot's loss behaviour with the feed-forward bound the output
      stage enforced (setpoint.acc_ff_hover_mps2 settled at station, acc_ff_max_mps2
      otherwise);
    * the swarm's ghost, the one every agent's APF avoids: the mission's loss envelope
      (swarm.loss, which the agent checked its autopilot against at set-up) and A as the
      agents take it (swarm.ghost_accel_mps2, or the enforced bound if smaller)."""
    mission = MissionConfig(**yaml.safe_load(config.read_text())["mission"])
    tel = run.tel
    i0 = int(np.searchsorted(tel["t_s"], t_last_s, side="right")) - 1  # the sample at or before it
    lag = float(t_last_s - tel["t_s"][i0]) + 0.05  # (and the last setpoint's own period)
    hover = bool(settled_rows(tel["phase"][i0, killed], tel["vel_ned_mps"][i0, killed], mission.phases.assembled_speed_mps))
    sp, sw = mission.setpoint, mission.swarm
    p0, v0 = tel["pos_ned_m"][i0, killed].astype(float), tel["vel_ned_mps"][i0, killed].astype(float)
    path = tel["pos_ned_m"][i0:, killed].astype(float)
    for what, behaviour, acc in (
            ("its autopilot's bound", loss, sp.acc_ff_hover_mps2 if hover else sp.acc_ff_max_mps2),
            ("the swarm's ghost", sw.loss.behaviour(),
             min(sp.acc_ff_hover_mps2 if hover else sp.acc_ff_max_mps2, sw.ghost_accel_mps2))):
        caps = ghost_capsules(p0, v0, 0.0, behaviour, acc, mission.ground_z_m, sw.ghost_radius_m, lag_s=lag)
        inside = caps.contains(path)
        assert inside.all(), f"left {what} at t = {tel['t_s'][i0 + int(np.argmin(inside))]:.2f} s"


# ---------------------------------------------------------------------------- runs (module-scoped)
@pytest.fixture(scope="module")
def cfg_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fleet_cfg")


@pytest.fixture(scope="module")
def px4_run(cfg_dir, tmp_path_factory) -> Run:
    return fly(tmp_path_factory.mktemp("px4") / "run", write_config(cfg_dir, "fleet4"), "--check")


# ---------------------------------------------------------------------------- tests
@pytest.mark.timeout(200)
def test_px4_fleet_completes_and_tlog_reads(px4_run):
    assert px4_run.proc.returncode == 0, px4_run.proc.stdout  # --check: every acceptance check passed
    check_completed_run(px4_run, PX4)
    check_tlog(px4_run, PX4)


@pytest.mark.timeout(200)
def test_ardupilot_fleet_completes_and_tlog_reads(cfg_dir, tmp_path):
    run = fly(tmp_path / "run", write_config(cfg_dir, "fleet4"), "--dialect", "ardupilot", "--check")
    assert run.proc.returncode == 0, run.proc.stdout
    check_completed_run(run, ARDUPILOT)
    check_tlog(run, ARDUPILOT)
    # ArduCopter's throw: THROW while docked and recovering, then GUIDED (THROW_NEXTMODE set by the agents)
    hb = [m for m in read_tlog(run.tlog, ["HEARTBEAT"]) if m.get_srcComponent() == 1]
    for k in range(1, N + 1):
        modes = [m.custom_mode for m in hb if m.get_srcSystem() == k]
        assert modes[0] == ARDUPILOT.custom_mode(Mode.THROW) and modes[-1] == ARDUPILOT.custom_mode(Mode.OFFBOARD)


@pytest.mark.timeout(200)
@pytest.mark.parametrize("dialect", [PX4, ARDUPILOT], ids=["px4", "ardupilot"])
def test_attitude_output_flies_the_formation(cfg_dir, tmp_path, dialect):
    """--output attitude: the position law runs on the companions, which send
    SET_ATTITUDE_TARGET (attitude + thrust normalised by the hover-thrust parameter)."""
    run = fly(tmp_path / "run", write_config(cfg_dir, "fleet4"), "--output", "attitude", "--dialect", dialect.name,
              "--check")
    assert run.proc.returncode == 0, run.proc.stdout
    check_completed_run(run, dialect)
    att = [m for m in read_tlog(run.tlog, ["SET_ATTITUDE_TARGET"]) if m.get_srcComponent() == COMPANION_COMPID]
    assert {m.get_srcSystem() for m in att} == set(range(1, N + 1))
    thrust = np.array([m.thrust for m in att])
    q = np.array([m.q for m in att])
    assert ((thrust > 0.05) & (thrust < 0.95)).all(), (thrust.min(), thrust.max())
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
    # Holding station (second half), thrust = weight: the hover-thrust parameter the agents read
    name = dialect.hover_thrust_param
    param = [m.param_value for m in read_tlog(run.tlog, ["PARAM_VALUE"]) if m.param_id == name]
    assert param, f"no agent read {name}"
    assert np.median(thrust[len(thrust) // 2:]) == pytest.approx(param[0], abs=0.03)


@pytest.mark.timeout(200)
def test_vehicles_with_different_ekf_origins_still_assemble(cfg_dir, tmp_path):
    """First GNSS fixes up to 10 s apart while the vehicles ride the 5 m/s carrier (or fly):
    every vehicle has its own EKF origin, metres from the others; the agents convert and
    the formation still ends on its slots."""
    run = fly(tmp_path / "run", write_config(cfg_dir, "fleet4"), "--fix-delay-max", "10", "--check")
    origins: dict[int, set] = {}
    for m in read_tlog(run.tlog, ["GPS_GLOBAL_ORIGIN"]):
        if m.get_srcComponent() == 1:
            origins.setdefault(m.get_srcSystem(), set()).add((m.latitude, m.longitude, m.altitude))
    assert sorted(origins) == list(range(1, N + 1))
    assert all(len(v) == 1 for v in origins.values()), origins  # an EKF origin does not wander
    home = yaml.safe_load((cfg_dir / "fleet4.yaml").read_text())["mission"]["origin"]
    ned = np.array([geodetic_to_ned(lat * 1e-7, lon * 1e-7, alt * 1e-3, home["lat_deg"], home["lon_deg"],
                                    home["alt_amsl_m"]) for (lat, lon, alt) in (next(iter(v)) for v in origins.values())])
    spread = max(np.linalg.norm(a - b) for a, b in itertools.combinations(ned, 2))
    closest = min(np.linalg.norm(a - b) for a, b in itertools.combinations(ned, 2))
    assert spread > 5.0 and closest > 0.1, ned  # metres apart: a frame error would show in the formation
    assert run.proc.returncode == 0, run.proc.stdout
    check_completed_run(run, PX4)


@pytest.mark.timeout(200)
def test_killed_agent_autopilot_does_what_px4_does_and_the_swarm_goes_on(cfg_dir, tmp_path):
    """The killed agent's vehicle: PX4 flies its last setpoint for COM_OF_LOSS_T, then does
    what COM_OBL_RC_ACT says, as the value the tlog shows (the agents set or verify it at
    set-up): 5 Hold for ever (it never lands by itself), 4 Land; the stock 0 without RC the
    no-RC descent with no horizontal control."""
    config = write_config(cfg_dir, "fleet4_kill", KILL_WAYPOINTS)
    run = fly(tmp_path / "run", config, "--kill-agent", f"{KILLED}@{KILL_AT_S:g}")
    fl = run.metrics["fleet"]
    assert fl["dead_agents"] == {str(KILLED): -9} and fl["killed_agents"] == [KILLED]
    sysid = KILLED + 1
    msgs = read_tlog(run.tlog, ["HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED", "PARAM_VALUE"])
    t = lambda m: m._timestamp - EPOCH_UNIX_S  # noqa: E731  simulation time of a tlog record
    params = {m.param_id: m.param_value for m in msgs if m.get_type() == "PARAM_VALUE" and m.get_srcSystem() == sysid
              and m.param_id in PX4.loss_params}
    action = struct.unpack("<i", struct.pack("<f", params["COM_OBL_RC_ACT"]))[0]  # (PX4 integers travel bytewise)
    loss = PX4.loss_behaviour({**params, "COM_OBL_RC_ACT": action})
    assert loss.timeout_s == COM_OF_LOSS_T
    sps = [m for m in msgs if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and m.get_srcSystem() == sysid]
    t_last = t(sps[-1])
    assert t_last >= KILL_AT_S - 0.05, "the agent stopped sending before it was killed"
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == sysid
          and m.get_srcComponent() == 1 and t(m) >= t_last]
    after = PX4.custom_mode(loss.mode)
    first = next(m for m in hb if m.custom_mode == after)
    assert all(m.custom_mode == PX4.custom_mode(Mode.OFFBOARD) for m in hb if t(m) < t(first))
    # The failsafe at COM_OF_LOSS_T shows in PX4's next 1 Hz HEARTBEAT: on one of this vehicle's
    # slots of simulation time, within a period of the failsafe (not at once, as on ArduPilot).
    dt = t(first) - t_last
    assert COM_OF_LOSS_T - 1e-6 <= dt <= COM_OF_LOSS_T + HEARTBEAT_PERIOD_S + 2 * AUTOPILOT_PERIOD_S + 1e-6, dt
    phase = (t(first) - KILLED * HEARTBEAT_PHASE_STEP_S) % HEARTBEAT_PERIOD_S
    assert phase < AUTOPILOT_PERIOD_S + 1e-4, phase
    assert first.system_status == 5  # CRITICAL: in failsafe
    assert_path_inside_ghost(run, config, loss, t_last, KILLED)
    tel = run.tel
    i_after = int(np.searchsorted(tel["t_s"], t(first) + 3.0))
    if loss.then == AfterLoss.HOLD:  # for ever: no other mode, still in the air
        assert all(m.custom_mode == after for m in hb if t(m) >= t(first))
        if i_after < len(tel["t_s"]):  # the vehicle really brakes and stays: 3 s into Hold it is almost at rest
            assert np.linalg.norm(tel["vel_ned_mps"][i_after, KILLED]) < 0.3
            assert tel["pos_ned_m"][-1, KILLED, 2] < -1.0
    elif loss.then == AfterLoss.DESCEND and i_after < len(tel["t_s"]):  # no horizontal control: descending
        assert tel["vel_ned_mps"][i_after, KILLED, 2] == pytest.approx(loss.descent_speed_mps, abs=0.15)
    # the others fly on to HOVER and onto their slots
    others = [k for k in range(N) if k != KILLED]
    assert (tel["phase"][-1, others] == Phase.HOVER).all(), tel["phase"][-1]
    assert (run.final_slot_error_m()[others] < 0.05).all(), run.final_slot_error_m()
    assert run.metrics["mission"]["completed"]
    # nobody came within 1 m of anyone, the silent vehicle included
    d_min, pair, t_min = run.min_separation_m()
    assert d_min >= 1.0, f"vehicles {pair} {d_min:.2f} m apart at t={t_min:.2f} s"
    # no process of the run is left
    assert run.leftovers == [], run.leftovers
    try:
        import psutil
    except ImportError:
        return
    kids = []
    for p in psutil.Process().children(recursive=True):
        try:
            if str(run.out) in " ".join(p.cmdline()) and p.status() != psutil.STATUS_ZOMBIE:
                kids.append(p.pid)
        except psutil.Error:  # ended meanwhile
            pass
    assert kids == []


@pytest.mark.timeout(200)
def test_killed_agent_ardupilot_flies_on_for_guid_timeout_then_holds_in_guided_inside_its_ghost(cfg_dir, tmp_path):
    """ArduPilot on companion loss: the last velocity and acceleration for GUID_TIMEOUT, then
    a stop and a hold in GUIDED for ever (no mode change, no landing); the path lies inside
    the swarm's ghost of it and nobody comes within 1 m."""
    config = write_config(cfg_dir, "fleet4_kill", KILL_WAYPOINTS)
    run = fly(tmp_path / "run", config, "--dialect", "ardupilot", "--kill-agent", f"{KILLED}@{KILL_AT_S:g}")
    assert run.metrics["fleet"]["killed_agents"] == [KILLED]
    sysid = KILLED + 1
    loss = ARDUPILOT.loss_behaviour(loss_params_from_tlog(run, ARDUPILOT, sysid))
    assert loss.then == AfterLoss.HOLD and loss.mode == Mode.OFFBOARD
    msgs = read_tlog(run.tlog, ["HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED"])
    t = lambda m: m._timestamp - EPOCH_UNIX_S  # noqa: E731
    t_last = t([m for m in msgs if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and m.get_srcSystem() == sysid][-1])
    guided = ARDUPILOT.custom_mode(Mode.OFFBOARD)
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == sysid and m.get_srcComponent() == 1
          and t(m) >= t_last]
    assert hb and all(m.custom_mode == guided and m.base_mode & 128 for m in hb)  # GUIDED and armed to the end
    assert_path_inside_ghost(run, config, loss, t_last, KILLED)
    tel = run.tel
    # It may carry an acceleration feed-forward for the whole GUID_TIMEOUT (here up to 9 m/s
    # from assembly), then brakes at WPNAV_ACCEL (2.5 m/s^2): at rest well within 8 s.
    i_held = int(np.searchsorted(tel["t_s"], t_last + loss.timeout_s + 8.0))
    if i_held < len(tel["t_s"]):  # stopped after GUID_TIMEOUT, and still in the air
        assert np.linalg.norm(tel["vel_ned_mps"][i_held:, KILLED], axis=1).max() < 0.3
        assert tel["pos_ned_m"][-1, KILLED, 2] < -1.0
    others = [k for k in range(N) if k != KILLED]
    assert (tel["phase"][-1, others] == Phase.HOVER).all(), tel["phase"][-1]
    d_min, pair, t_min = run.min_separation_m()
    assert d_min >= 1.0, f"vehicles {pair} {d_min:.2f} m apart at t={t_min:.2f} s"
    assert run.leftovers == [], run.leftovers


@pytest.mark.timeout(200)
def test_lossy_link_converges_without_collision(cfg_dir, tmp_path):
    cfg = write_config(cfg_dir, "fleet4_lossy", link={"kind": "lossy", "loss": 0.2, "delay_s": 0.1})
    run = fly(tmp_path / "run", cfg, "--check")
    assert run.proc.returncode == 0, run.proc.stdout
    check_completed_run(run, PX4)
    link = run.metrics["link"]
    assert link["kind"] == "lossy" and link["copies_sent"] > 1000
    assert 0.15 <= link["copies_lost"] / link["copies_sent"] <= 0.25, link
    age = link["age_at_delivery_s"]
    assert 0.1 - 1e-6 <= age["p50"] <= 0.15, age  # the 100 ms delay (+ waiting for the receiver's next tick)


@pytest.mark.timeout(200)
def test_a_rotor_failure_in_the_sitl_brings_one_down_and_the_others_finish(cfg_dir, tmp_path):
    """The scenario's `faults` reach the SITL; the failed vehicle's agent declares it over
    MAVLink attitude, and the other three finish without it (docs/scenario.md)."""
    cfg = write_config(cfg_dir, "fleet4_rotor", faults={"rotor_failures": [{"vehicle": 2, "time_s": 16.0, "rotor": 3}]})
    run = fly(tmp_path / "run", cfg, "--check")
    assert run.proc.returncode == 0, run.proc.stdout
    (f,) = run.metrics["rotor_failures"]
    assert f["vehicle"] == 2 and f["failed_at_s"] == pytest.approx(16.0, abs=0.021)
    assert 0.3 <= f["detection_latency_s"] <= 1.5 and f["final_height_m"] == pytest.approx(0.0, abs=0.05)
    assert run.metrics["mission"]["completed"] and run.metrics["separation"]["collisions"] == 0
    assert run.metrics["checks"]["rotor_failures_detected"]


def assert_bit_identical(one: Run, two: Run) -> None:
    """Two runs' recordings byte for byte, and their metrics but the wall-clock figures."""
    assert sorted(two.tel) == sorted(one.tel)
    for key, a in one.tel.items():
        b = two.tel[key]
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), key
    skip = {"performance", "fleet"}  # wall-clock figures
    for key in sorted(set(one.metrics) | set(two.metrics)):
        if key not in skip:
            assert json.dumps(one.metrics.get(key)) == json.dumps(two.metrics.get(key)), key


@pytest.mark.timeout(200)
def test_lockstep_runs_are_bit_identical(px4_run, tmp_path):
    again = fly(tmp_path / "run", Path(px4_run.proc.args[4]), "--check")  # the same config file
    assert again.proc.returncode == 0, again.proc.stdout
    assert_bit_identical(px4_run, again)


@pytest.mark.timeout(200)
def test_ground_launch_lockstep_runs_are_bit_identical(tmp_path):
    """A ground launch sends its commands (mode, arm, take-off) with the lockstep ticks and
    takes their answers at a tick's end (VehicleLink.tick_aligned): sent between ticks, a
    vehicle's take-off came a tick late in about one run in seven."""
    path = ROOT / "configs" / "ground_4.yaml"
    one = fly(tmp_path / "one", path, "--dialect", "ardupilot", "--no-console")
    two = fly(tmp_path / "two", path, "--dialect", "ardupilot", "--no-console")
    assert one.proc.returncode == 0 and two.proc.returncode == 0, one.proc.stdout + two.proc.stdout
    assert_bit_identical(one, two)


@pytest.mark.timeout(200)
def test_signed_fleet_flies_the_same_run(px4_run, tmp_path):
    """`swarmdrop run --signing`: every link signed (required) with a fresh owner-only key;
    in lockstep the flight is bit-identical to the unsigned run, and nothing was dropped."""
    signed = fly(tmp_path / "run", Path(px4_run.proc.args[4]), "--check", "--signing")
    assert signed.proc.returncode == 0, signed.proc.stdout + signed.proc.stderr
    key = tmp_path / "run" / "signing.key"
    assert key.stat().st_mode & 0o077 == 0
    for name in ("pos_ned_m", "att_q_wxyz", "acc_cmd_ned_mps2"):
        assert px4_run.tel[name].tobytes() == signed.tel[name].tobytes(), name
    sg = signed.metrics["fleet"]["signing"]
    assert set(sg) == {"autopilot", "swarm"}
    for link in sg.values():
        assert link["unsigned"] == link["bad_signature"] == link["replayed"] == 0, sg
    # what went over the wire was signed: every frame in the SITL's tlog carries a signature
    frames = read_tlog(signed.out / "sitl.tlog", ["HEARTBEAT", "COMMAND_LONG", "SET_POSITION_TARGET_LOCAL_NED"])
    assert frames and all(m.get_header().incompat_flags & 1 for m in frames)


def _sim_s_reached(out: Path, sim_s: float) -> bool:
    """The SITL's last STATUS line (sitl.log) shows at least sim_s of simulated time."""
    try:
        lines = [ln for ln in (out / "sitl.log").read_text().splitlines() if ln.startswith("STATUS ")]
    except OSError:
        return False
    return bool(lines) and json.loads(lines[-1][7:]).get("sim_s", 0.0) >= sim_s


def _interrupt_fleet(cfg_dir: Path, out: Path, ready) -> tuple[subprocess.Popen, str, str]:
    """Start `swarmdrop run`, wait (deadline 60 s) until ready(out), then Ctrl-C it as a terminal would."""
    import signal

    cmd = [sys.executable, "-m", "swarmdrop.cli", "run", str(write_config(cfg_dir, "fleet4_int")), "--out", str(out),
           "--quiet", "--no-figures"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own group, as a shell's foreground job
    try:
        deadline = time.monotonic() + 60.0
        while not ready(out):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)  # polling a condition with a deadline
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc, stdout, stderr


@pytest.mark.timeout(120)
def test_ctrl_c_stops_every_process_and_reports_a_partial_run(cfg_dir, tmp_path):
    """Ctrl-C in a terminal sends SIGINT to the foreground process group: the harness stops
    the SITL and the agents, writes what it has, exits 130 and reports no agent as dead."""
    out = tmp_path / "run"
    proc, stdout, stderr = _interrupt_fleet(cfg_dir, out, lambda o: _sim_s_reached(o, 1.0))
    assert proc.returncode == 130, stderr[-2000:]
    assert "INTERRUPTED at" in stdout and "exited with code" not in stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["fleet"]["interrupted"] is True and metrics["fleet"]["dead_agents"] == {}
    assert metrics["stabilisation"]["per_vehicle"], "a partial run is still scored"
    left = wait_gone(out)
    assert left == [], left


@pytest.mark.timeout(120)
def test_ctrl_c_before_the_mission_starts_exits_130_without_a_traceback(cfg_dir, tmp_path):
    """Regression: Ctrl-C before the SITL's first recorded sample made the SITL raise while
    saving an empty recording, and the harness exit 2 ("the SITL wrote no recording")."""
    out = tmp_path / "run"

    def sitl_ready(o: Path) -> bool:
        try:
            return "SITL READY" in (o / "sitl.log").read_text()
        except OSError:
            return False

    proc, stdout, stderr = _interrupt_fleet(cfg_dir, out, sitl_ready)
    assert proc.returncode == 130, stderr[-2000:]
    assert "nothing to score" in stdout, stdout
    assert "Traceback" not in (out / "sitl.log").read_text()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["recorded"] is False and metrics["fleet"]["interrupted"] is True
    left = wait_gone(out)
    assert left == [], left


# ---------------------------------------------------------------------------- a landing that passes
@pytest.fixture(scope="module")
def landing_run(tmp_path_factory) -> Run:
    d = tmp_path_factory.mktemp("fleet_land")
    cfg = write_config(d, "fleet4_land")
    data = yaml.safe_load(cfg.read_text())
    data["mission"]["phases"] = {"land_after_hover_s": 3.0}
    # 3 s of hover do not bring the formation within 5 cm with the autopilots' own position loops
    # (issue 18): this run is about the landing, so the formation is judged at 0.3 m
    data["completion_tol_m"] = 0.3
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    return fly(d / "out", cfg, "--check")


def test_a_mission_that_lands_completes_when_every_vehicle_is_down_and_passes_its_check(landing_run):
    """Issue 16: with land_after_hover_s the mission completes once every vehicle has landed
    and disarmed; the formation is judged at the end of the hover, the landing apart."""
    r = landing_run
    m = r.metrics
    assert r.proc.returncode == 0, r.proc.stdout  # --check: every check passed
    assert m["checks"]["mission_completed"] and m["checks"]["landing_all_down"]
    assert m["checks"]["final_formation_deviation_below_tol"] and m["checks"]["landing_separation_ok"]
    land = m["landing"]
    assert land["vehicles_down"] == land["vehicles_judged"] == N
    # completion is the moment the last vehicle was down (the log sees it within a sample), after the landing began
    assert land["land_start_s"] < m["mission"]["completion_time_s"]
    assert abs(land["all_down_s"] - m["mission"]["completion_time_s"]) <= 1.0 / 50.0 + 1e-6
    # every vehicle rests on the ground (NED z = 0) at the end, in its own slot's column
    z = r.tel["pos_ned_m"][-1, :, 2].astype(float)
    assert np.all(np.abs(z) < 0.05), z
    horiz = np.linalg.norm(r.tel["pos_ned_m"][-1, :, :2].astype(float) - r.tel["slot_ned_m"][-1, :, :2], axis=1)
    # (the agents land on a velocity setpoint: PX4's velocity loop comes back with what its
    # integrator kept from the throw recovery and pushes each vehicle some decimetres aside)
    assert np.all(horiz < 1.0), horiz
    assert land["min_pair_distance_descending_m"] >= 1.0
    # the SITL's autopilots disarmed them: the tlog's last HEARTBEAT of each vehicle says so
    mlog = mavutil.mavlink_connection(str(r.tlog), dialect="common")
    armed = {}
    while (msg := mlog.recv_match(type="HEARTBEAT")) is not None:
        if msg.get_srcComponent() == 1 and 1 <= msg.get_srcSystem() <= N:
            armed[msg.get_srcSystem()] = bool(msg.base_mode & 128)
    assert armed == {k: False for k in range(1, N + 1)}
    assert not r.leftovers


def test_agents_that_give_up_on_a_stopped_sitl_after_completion_do_not_abort_the_run(tmp_path):
    """After MISSION COMPLETE the SITL writes its recording with its autopilots silent (seconds
    on a loaded machine); agents that exit on LINK_LOST meanwhile have done their job: the run
    is not aborted as "every agent has exited", and no agent is reported dead. Before
    completion the same exits are a dead fleet."""
    from sim_bridge.runs.fleet import Fleet, FleetOptions
    from sim_bridge.scenario import load_scenario
    from sim_bridge.sitl.status import SitlStatus

    path = ROOT / "configs" / "ground_4.yaml"
    fleet = Fleet(path, load_scenario(path, runner="fleet"), FleetOptions(out_dir=tmp_path, progress=False, figures=False))
    (tmp_path / "agents").mkdir()
    fleet.agents = [subprocess.Popen([sys.executable, "-c", "raise SystemExit(6)"]) for _ in range(fleet.n)]
    for p in fleet.agents:
        assert p.wait(timeout=30) == 6
    fleet.status = SitlStatus(sim_s=40.0, rtf=1.0, attached=fleet.n, complete=True)
    fleet._watch_agents(40.0)
    assert fleet.dead == {} and fleet._hopeless() == ""
    fleet.status = SitlStatus(sim_s=30.0, rtf=1.0, attached=fleet.n, complete=False)
    fleet._watch_agents(30.0)
    assert sorted(fleet.dead) == list(range(fleet.n))
    assert fleet._hopeless().startswith("every agent has exited")
