"""A run directory tells the truth, and a run that cannot fly stops (issue 16).

- `--out` must be new or empty, or cleared with `--overwrite` (which deletes only a run's
  files, and refuses a directory holding anything else); it is checked as writable before
  anything flies, and a system directory (/tmp, home, ...) is never one.
- An interrupted fleet run never reports a completed mission nor draws figures from
  files it did not write.
- `swarmdrop run` stops, naming the agents and their exit codes, as soon as no agent is
  left that can attach (it used to wait for ever on a SITL clock held at 0).
"""
from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from sim_bridge.runs.fleet import EXIT_AGENTS_FAILED, FleetOptions, parse_kill, run_fleet
from sim_bridge.runs.rundir import MARKER, RunDirError, prepare_run_dir

ROOT = Path(__file__).resolve().parents[1]
SMALL6 = ROOT / "configs" / "small_6.yaml"


def cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "swarmdrop.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def quick_config(tmp_path: Path, n: int = 3) -> Path:
    """small_6 cut to n vehicles and a short leg, without figures or launch study."""
    data = yaml.safe_load(SMALL6.read_text())
    data["mission"]["n_vehicles"] = n
    data["mission"]["obstacles"] = []
    data["mission"]["waypoints_ned_m"] = [[20.0, 0.0, -10.0], [26.0, 4.0, -11.0]]
    data["duration_s"] = 90.0  # (it completes near 61 s: the autopilot's own loops, issue 18)
    data["output"] = {"snapshot_times_s": [5.0], "attitude_vehicles": [1], "avoidance_vehicles": [1, n],
                      "figures": False}
    path = tmp_path / "quick.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# ---------------------------------------------------------------------------- the run directory
def test_a_non_empty_out_is_refused_and_kept_unless_overwrite_clears_it(tmp_path):
    out = tmp_path / "run"
    prepare_run_dir(out)
    assert (out / MARKER).is_file()
    (out / "metrics.json").write_text("{}")
    (out / "fig5_trajectories_3d.png").write_bytes(b"old")
    with pytest.raises(RunDirError, match="not empty.*--overwrite"):
        prepare_run_dir(out)
    assert (out / "metrics.json").read_text() == "{}"  # refused: nothing touched
    prepare_run_dir(out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == [MARKER]


def test_a_run_that_wrote_nothing_leaves_a_directory_the_same_command_takes_again(tmp_path):
    """A run refused at start (a port in use) or interrupted before writing leaves only the
    marker, and says it wrote nothing: the same command then goes ahead without --overwrite."""
    out = prepare_run_dir(tmp_path / "run")
    assert sorted(p.name for p in out.iterdir()) == [MARKER]
    assert prepare_run_dir(out) == out
    (out / "metrics.json").write_text("{}")  # but one file more is a previous run's
    with pytest.raises(RunDirError, match="not empty"):
        prepare_run_dir(out)


def test_overwrite_clears_only_run_directories(tmp_path):
    junk = tmp_path / "notes"
    junk.mkdir()
    (junk / "thesis.tex").write_text("precious")
    with pytest.raises(RunDirError, match=r"1 entry that no run writes \(thesis.tex\)"):
        prepare_run_dir(junk, overwrite=True)
    assert (junk / "thesis.tex").read_text() == "precious"
    (junk / MARKER).write_text("")  # the marker no longer licenses deleting someone's files
    with pytest.raises(RunDirError, match=r"thesis.tex"):
        prepare_run_dir(junk, overwrite=True)
    assert (junk / "thesis.tex").read_text() == "precious"
    src = tmp_path / "src"
    src.mkdir()
    (src / "pyproject.toml").write_text("")
    (src / "metrics.json").write_text("{}")
    with pytest.raises(RunDirError, match="source tree"):
        prepare_run_dir(src, overwrite=True)
    old = tmp_path / "old_run"  # a run directory written before the marker existed
    (old / "agents").mkdir(parents=True)
    for name in ("metrics.json", "telemetry.npz", "fig8_formation_deviation.png", "sitl.tlog"):
        (old / name).write_bytes(b"x")
    prepare_run_dir(old, overwrite=True)
    assert sorted(p.name for p in old.iterdir()) == [MARKER]


def test_an_out_that_cannot_be_written_is_refused_before_anything_flies(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(RunDirError, match="cannot write there"):
        prepare_run_dir(blocker / "run")
    with pytest.raises(RunDirError, match="not a directory"):
        prepare_run_dir(blocker)
    if os.geteuid() != 0:  # (root writes through permissions)
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
        with pytest.raises(RunDirError, match="cannot write there"):
            prepare_run_dir(ro / "run")


def test_simulate_into_a_used_directory_is_refused_and_overwrite_leaves_no_stale_figures(tmp_path):
    cfg = quick_config(tmp_path)
    out = tmp_path / "out"
    first = cli("simulate", str(cfg), "--out", str(out), "--quiet")
    assert first.returncode == 0, first.stderr
    (out / "fig5_trajectories_3d.png").write_bytes(b"an old run's figure")
    again = cli("simulate", str(cfg), "--out", str(out), "--quiet", "--no-figures")
    assert again.returncode == 2 and "not empty" in again.stderr and "--overwrite" in again.stderr
    assert "Traceback" not in again.stderr
    redo = cli("simulate", str(cfg), "--out", str(out), "--quiet", "--no-figures", "--overwrite")
    assert redo.returncode == 0, redo.stderr
    assert not list(out.glob("*.png"))  # nothing from the old run beside the new metrics
    unwritable = cli("simulate", str(cfg), "--out", str(cfg / "sub"), "--quiet")
    assert unwritable.returncode == 2 and "cannot write there" in unwritable.stderr


# ---------------------------------------------------------------------------- the fleet harness
def test_kill_agent_must_name_a_vehicle_of_the_mission(tmp_path):
    r = cli("run", str(SMALL6), "--out", str(tmp_path / "o"), "--kill-agent", "9@5", "--quiet")
    assert r.returncode == 2 and "--kill-agent 9" in r.stderr and "0..5" in r.stderr
    assert not (tmp_path / "o").exists()  # refused before anything was made
    for bad in ("2@-1", "2@nan", "x@3", "2@5 2@9"):
        with pytest.raises(ValueError, match="--kill-agent"):
            parse_kill(bad.split())


def test_version():
    r = cli("--version")
    assert r.returncode == 0 and r.stdout.startswith("swarmdrop ")


def test_run_stops_with_the_agents_exit_codes_when_none_can_attach(tmp_path):
    """The agents all die at start (here: a stand-in interpreter that fails every agent):
    the SITL's clock waits for them, so the harness must stop everything and say why."""
    fake = tmp_path / "python"
    fake.write_text(f"#!/bin/sh\ncase \"$*\" in *' agent '*) echo 'agent: refused' >&2; exit 4;; esac\n"
                    f"exec {sys.executable} \"$@\"\n")
    fake.chmod(0o755)
    cfg = quick_config(tmp_path)
    t0 = time.monotonic()
    report, code = run_fleet(cfg, FleetOptions(out_dir=tmp_path / "out", progress=False, figures=False,
                                               python=str(fake)))
    assert code == EXIT_AGENTS_FAILED
    assert time.monotonic() - t0 < 60.0  # it used to wait for ever
    fl = report.fleet
    assert fl.dead_agents == {"0": 4, "1": 4, "2": 4}
    assert "exited before every vehicle had attached" in fl.aborted and "agent 0 (exit code 4)" in fl.aborted
    assert report.metrics is None  # nothing flew: nothing scored
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["recorded"] is False and m["fleet"]["aborted"] == fl.aborted


def test_agent_python_runs_the_agents_and_nothing_else(tmp_path):
    """--agent-python (FleetOptions.agent_python): the agents run on that interpreter (here one
    that refuses to run anything), the SITL on the harness's own; so the agents die with its
    exit code while the SITL starts and waits for them."""
    fake = tmp_path / "onboard-python"
    fake.write_text("#!/bin/sh\necho 'onboard: refused' >&2\nexit 5\n")
    fake.chmod(0o755)
    report, code = run_fleet(quick_config(tmp_path), FleetOptions(out_dir=tmp_path / "out", progress=False,
                                                                  figures=False, agent_python=str(fake)))
    assert code == EXIT_AGENTS_FAILED
    assert report.fleet.dead_agents == {"0": 5, "1": 5, "2": 5}
    assert "exited before every vehicle had attached" in report.fleet.aborted
    r = cli("run", str(quick_config(tmp_path)), "--out", str(tmp_path / "o2"), "--agent-python",
            str(tmp_path / "no-such-python"), "--quiet")
    assert r.returncode == 2 and "--agent-python" in r.stderr and "no executable file" in r.stderr
    assert not (tmp_path / "o2").exists()  # refused before anything was made


def test_an_interrupted_run_never_reports_a_completed_mission(tmp_path):
    """The case seen by a user: Ctrl-C at t = 0 into a directory that held a finished
    run printed "mission complete" and [PASS] from the old files."""
    cfg = quick_config(tmp_path)
    out = tmp_path / "out"
    done = cli("simulate", str(cfg), "--out", str(out), "--quiet")  # a finished run in the way
    assert done.returncode == 0 and json.loads((out / "metrics.json").read_text())["mission"]["completed"]
    refused = cli("run", str(cfg), "--out", str(out), "--quiet")
    assert refused.returncode == 2 and "not empty" in refused.stderr
    proc = subprocess.Popen([sys.executable, "-m", "swarmdrop.cli", "run", str(cfg), "--out", str(out), "--quiet",
                             "--overwrite"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60.0
        while not (out / "ports.json").exists():  # the harness has started its processes
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)  # polling for a file with a deadline
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr
    assert "mission complete at:   n/a" in stdout or "nothing to score" in stdout, stdout
    assert "[PASS] mission_completed" not in stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["fleet"]["interrupted"] is True
    assert m.get("recorded") is False or (m["mission"]["completed"] is False
                                          and m["mission"]["ended_early"] == "interrupted")
    assert not list(out.glob("*.png"))  # the old run's figures went with --overwrite; none drawn from them


def test_a_headless_mission_that_lands_completes_when_every_vehicle_is_down(tmp_path):
    """land_after_hover_s: headless, the autopilot model detects the landing and disarms
    (sim_bridge.world.autopilot_model, as the SITL's autopilot); the mission completes then, the
    formation is judged at the end of the hover, and --check passes."""
    cfg = quick_config(tmp_path)
    data = yaml.safe_load(cfg.read_text())
    data["mission"]["phases"] = {"land_after_hover_s": 3.0}
    # 3 s of hover do not bring the formation within 5 cm with the autopilot's own velocity loop
    # (the bias its integrator kept from the throw recovery is still being unlearnt): this test is
    # about the landing, so the formation is judged at 0.3 m
    data["completion_tol_m"] = 0.3
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "out"
    r = cli("simulate", str(cfg), "--out", str(out), "--quiet", "--check")
    assert r.returncode == 0, r.stdout + r.stderr
    m = json.loads((out / "metrics.json").read_text())
    land = m["landing"]
    assert land["vehicles_down"] == land["vehicles_judged"] == 3
    assert land["land_start_s"] < m["mission"]["completion_time_s"]
    assert m["formation_deviation"]["final_max_m"] < data["completion_tol_m"]  # judged before the descent
    with np.load(out / "telemetry.npz") as z:
        assert z["down"][-1].all() and np.all(np.abs(z["pos_ned_m"][-1, :, 2]) < 0.05)


def test_a_mission_that_holds_station_ends_when_swarm_commands_have_landed_every_vehicle(tmp_path):
    """A station-keeping mission whose vehicles are all landed by swarm commands before it
    completes (here two LANDs, neither naming every vehicle: as an operator's LAND from the
    console, which the scenario was not written with) is over: the run ends once every vehicle
    is down and disarmed, says so, and does not call the mission complete. (It used to fly on
    to duration_s and report only "mission complete at: n/a".) A LAND naming every vehicle is
    a mission that ends landed, as a LAND without vehicles."""
    from sim_bridge.scenario import ends_landed, load_scenario

    cfg = quick_config(tmp_path)
    data = yaml.safe_load(cfg.read_text())
    data["duration_s"] = 150.0
    data["commands"] = [{"t_s": 30.0, "kind": "land", "vehicles": [1]}, {"t_s": 32.0, "kind": "land", "vehicles": [2, 3]}]
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    assert not ends_landed(load_scenario(cfg))
    out = tmp_path / "out"
    r = cli("simulate", str(cfg), "--out", str(out), "--quiet", "--check")
    assert r.returncode == 1, r.stdout + r.stderr  # not completed: --check fails
    m = json.loads((out / "metrics.json").read_text())
    landed = m["mission"]["landed_early_s"]
    assert m["mission"]["completed"] is False and landed is not None and 32.0 < landed < 90.0
    assert f"every vehicle landed and disarmed at {landed:.1f} s" in r.stdout
    with np.load(out / "telemetry.npz") as z:  # the run ended completion_hold_s after the last was down
        assert z["t_s"][-1] <= landed + data.get("completion_hold_s", 5.0) + 0.5
        assert np.all(np.abs(z["pos_ned_m"][-1, :, 2]) < 0.05)
    data["commands"] = [{"t_s": 30.0, "kind": "land", "vehicles": [3, 1, 2]}]
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    assert ends_landed(load_scenario(cfg))
