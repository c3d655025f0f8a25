"""What a new user got wrong, and what swarmdrop now says: each mistake is refused before
anything flies (exit 2, the option, path or value named, no traceback, nothing lost), or
handled as the user would expect (a TCP autopilot that comes up late, Ctrl-C, a stats file
that can no longer be written in flight).

Everything here runs on 127.0.0.1 with fixed seeds; a process a test starts is stopped by
its PID; waits poll with deadlines."""
from __future__ import annotations

import argparse
import json
import math
import os
import select
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.config import ConfigError, read_yaml, validate
from sim_bridge.runs.rundir import MARKER, RunDirError, prepare_run_dir
from sim_bridge.sitl.testing import free_udp_base_port

ROOT = Path(__file__).resolve().parents[1]
SMALL6 = ROOT / "configs" / "small_6.yaml"


def swarmdrop(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "swarmdrop.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def agent_args(*extra: str) -> list[str]:
    return ["agent", "--vehicle-id", "0", "--mission", str(SMALL6), *extra]


def udp_autopilot() -> str:
    return f"udpin://127.0.0.1:{free_udp_base_port(1)}"


def tiny_config(tmp_path: Path, n: int = 2, **top) -> Path:
    """small_6 cut to n vehicles, one short leg, no obstacles, figures or launch study."""
    data = yaml.safe_load(SMALL6.read_text())
    data["mission"].update(n_vehicles=n, obstacles=[], waypoints_ned_m=[[20.0, 0.0, -10.0], [24.0, 2.0, -10.0]])
    data["duration_s"] = 40.0
    data["output"] = {"snapshot_times_s": [5.0], "attitude_vehicles": [1], "avoidance_vehicles": [1, n],
                      "figures": False}
    data.update(top)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def no_traceback(proc: subprocess.CompletedProcess) -> None:
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout, proc.stderr


# ============================================================================ 1. --stats / --log-file
@pytest.mark.timeout(60)
@pytest.mark.parametrize("option", ["--stats", "--log-file"])
def test_agent_refuses_a_stats_or_log_file_it_cannot_write_before_anything_flies(option, tmp_path):
    """The agent used to arm, take off and die mid-flight at its first statistics write."""
    where = tmp_path / "no_such_dir" / "agent.out"
    r = swarmdrop(*agent_args("--autopilot", udp_autopilot(), "--setup-timeout", "30", option, str(where)))
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert f"{option} {where}" in r.stderr and "cannot write there" in r.stderr, r.stderr
    assert "HEARTBEAT" not in r.stderr  # refused at start: it never waited for an autopilot
    no_traceback(r)


@pytest.mark.timeout(60)
def test_a_stats_write_that_fails_in_flight_is_logged_and_the_agent_flies_on(tmp_path, caplog):
    from companion.node.config import NodeConfig, check_node, load_mission_file
    from companion.node.runner import AgentNode

    out = tmp_path / "stats"
    out.mkdir()
    cfg = check_node(NodeConfig(vehicle_id=0, autopilot_url=udp_autopilot(), mission=load_mission_file(SMALL6),
                                swarm_bind=("127.0.0.1", 0), stats_path=out / "agent.json"))
    node = AgentNode(cfg)
    try:
        node.write_stats()
        assert json.loads((out / "agent.json").read_text())["vehicle_id"] == 0
        (out / "agent.json").unlink()
        out.rmdir()  # the directory goes away in flight
        with caplog.at_level("INFO", logger="swarmdrop.agent"):
            node.write_stats()  # no exception: the supervision loop (and the flight) goes on
            node.write_stats()
            errors = [r for r in caplog.records if r.levelname == "ERROR"]
            assert len(errors) == 1 and "cannot write the statistics" in errors[0].getMessage()
            assert str(out / "agent.json") in errors[0].getMessage()
            out.mkdir()
            node.write_stats()
            assert "again" in caplog.records[-1].getMessage()
        assert json.loads((out / "agent.json").read_text())["vehicle_id"] == 0
    finally:
        node.ap_ep.close()
        node.sw_ep.close()


# ============================================================================ 2. --overwrite and the run directory
def test_overwrite_never_deletes_what_a_user_added_to_a_run_directory(tmp_path):
    out = prepare_run_dir(tmp_path / "run")
    assert (out / MARKER).is_file()
    for name in ("metrics.json", "telemetry.npz", "fig5_trajectories_3d.png", "signing.key.timestamp-3"):
        (out / name).write_text("a run's")
    (out / "agents").mkdir()
    (out / "agents" / "agent_00.log").write_text("a run's")
    (out / "my_notes.txt").write_text("precious")
    (out / "analysis").mkdir()
    (out / "analysis" / "plot.py").write_text("precious")
    with pytest.raises(RunDirError) as e:
        prepare_run_dir(out, overwrite=True)
    msg = str(e.value)
    assert "my_notes.txt" in msg and "analysis/" in msg and "2 entries that no run writes" in msg, msg
    assert "metrics.json" not in msg.split("(", 1)[1]  # only what is not a run's is named
    assert (out / "my_notes.txt").read_text() == "precious"  # nothing deleted: not even the run's files
    assert (out / "analysis" / "plot.py").read_text() == "precious" and (out / "metrics.json").exists()
    (out / "my_notes.txt").unlink()
    (out / "analysis" / "plot.py").unlink()
    (out / "analysis").rmdir()
    prepare_run_dir(out, overwrite=True)  # now only a run's files: cleared (signed fleet runs too)
    assert sorted(p.name for p in out.iterdir()) == [MARKER]


@pytest.mark.parametrize("which", ["temp", "home", "cwd", "parent of cwd"])
def test_a_system_directory_is_never_a_run_directory_even_empty(which, tmp_path, monkeypatch):
    """An empty /tmp used to be accepted (and marked), then cleared by a later --overwrite.
    (Each case points the system directory at an empty directory of the test's own.)"""
    place = tmp_path / "place"
    place.mkdir()
    if which == "temp":
        monkeypatch.setattr(tempfile, "gettempdir", lambda: str(place))
        target = place
    elif which == "home":
        monkeypatch.setenv("HOME", str(place))
        target = place
    elif which == "cwd":
        monkeypatch.chdir(place)
        target = place
    else:
        (place / "sub").mkdir()
        monkeypatch.chdir(place / "sub")
        target = place
    for overwrite in (False, True):
        with pytest.raises(RunDirError, match="cannot be a run directory"):
            prepare_run_dir(target, overwrite=overwrite)
    assert not (target / MARKER).exists()


def test_tmp_and_var_tmp_and_the_root_are_refused_by_name():
    for path in ("/tmp", "/var/tmp", "/", tempfile.gettempdir()):  # (never with --overwrite: refused first anyway)
        with pytest.raises(RunDirError, match="cannot be a run directory"):
            prepare_run_dir(path)


def test_simulate_refuses_tmp_as_its_run_directory():
    r = swarmdrop("simulate", str(SMALL6), "--out", tempfile.gettempdir(), "--quiet", "--no-figures")
    assert r.returncode == 2 and "temporary directory" in r.stderr and "--out" in r.stderr, r.stderr
    no_traceback(r)


# ============================================================================ 3. a scenario without a mission
@pytest.mark.parametrize("content, phrase", [
    ("", "the file is empty"),
    ("# only a comment\n", "the file is empty"),
    ("seed: 3\nduration_s: 20.0\n", "no `mission:` section"),
    ("seed: 3\nmission:\n", "`mission:` is empty"),
    ("mission: [1, 2]\n", "`mission:` is a list, not a mapping"),
])
def test_a_scenario_or_mission_file_without_a_mission_is_refused(content, phrase, tmp_path):
    from companion.node.config import load_mission_file
    from sim_bridge.scenario import load_scenario

    f = tmp_path / "empty.yaml"
    f.write_text(content)
    for load in (load_scenario, load_mission_file):
        with pytest.raises(ConfigError) as e:
            load(f)
        assert str(e.value).startswith(f"{f}: ") and phrase in str(e.value) and "hidden default" in str(e.value)


def test_simulate_of_an_empty_file_exits_2_and_flies_nothing(tmp_path):
    f = tmp_path / "empty.yaml"
    f.write_text("")
    out = tmp_path / "out"
    r = swarmdrop("simulate", str(f), "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 2 and "mission:" in r.stderr and not out.exists(), (r.stdout, r.stderr)
    no_traceback(r)


@pytest.mark.parametrize("config", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.name)
def test_the_shipped_configs_still_load(config):
    from companion.node.config import load_mission_file
    from sim_bridge.scenario import load_scenario

    assert load_scenario(config, runner=None).mission.n_vehicles >= 1
    assert load_mission_file(config).mission.n_vehicles >= 1


# ============================================================================ 4. duplicate YAML keys
def test_a_key_given_twice_is_refused_naming_the_key_and_the_lines(tmp_path):
    f = tmp_path / "dup.yaml"
    f.write_text("version: 2\nmission:\n  n_vehicles: 6\n  formation: {radius_m: 10.0}\n  n_vehicles: 3\n")
    with pytest.raises(ConfigError) as e:
        read_yaml(f)
    msg = str(e.value)
    assert msg.startswith(f"{f}: line 5: duplicate key 'n_vehicles'") and "line 3" in msg, msg
    from companion.node.config import load_mission_file
    from sim_bridge.scenario import load_scenario

    for load in (load_scenario, load_mission_file):
        with pytest.raises(ConfigError, match="duplicate key 'n_vehicles'"):
            load(f)


def test_duplicates_in_flow_mappings_and_top_level_are_refused_merges_are_not(tmp_path):
    f = tmp_path / "a.yaml"
    f.write_text("a: {x: 1, x: 2}\n")
    with pytest.raises(ConfigError, match="line 1: duplicate key 'x'"):
        read_yaml(f)
    f.write_text("seed: 1\nname: x\nseed: 2\n")
    with pytest.raises(ConfigError, match="line 3: duplicate key 'seed' \\(already given on line 1"):
        read_yaml(f)
    f.write_text("base: &b {x: 1, y: 2}\nover:\n  <<: *b\n  x: 5\n")  # a merge key's value may be overridden
    assert read_yaml(f) == {"base": {"x": 1, "y": 2}, "over": {"x": 5, "y": 2}}


def test_simulate_refuses_a_duplicate_key_before_flying(tmp_path):
    text = SMALL6.read_text().replace("  n_vehicles: 6\n", "  n_vehicles: 6\n  n_vehicles: 3\n")
    f = tmp_path / "dup.yaml"
    f.write_text(text)
    r = swarmdrop("simulate", str(f), "--out", str(tmp_path / "out"), "--quiet", "--no-figures")
    assert r.returncode == 2 and "duplicate key 'n_vehicles'" in r.stderr and not (tmp_path / "out").exists()
    no_traceback(r)


# ============================================================================ 5. agent numbers and --signing-key
def _node(**kw):
    from companion.node.config import NodeConfig, load_mission_file

    return NodeConfig(vehicle_id=0, autopilot_url="udpin://127.0.0.1:14540", mission=load_mission_file(SMALL6), **kw)


@pytest.mark.parametrize("field, value, option", [
    ("setup_timeout_s", math.nan, "--setup-timeout"), ("setup_timeout_s", -1.0, "--setup-timeout"),
    ("setup_timeout_s", 0.0, "--setup-timeout"), ("setup_timeout_s", math.inf, "--setup-timeout"),
    ("rate_hz", math.nan, "--rate"), ("rate_hz", 0.0, "--rate"), ("rate_hz", 1e9, "--rate"),
    ("takeoff_alt_m", math.inf, "--takeoff-alt"), ("takeoff_alt_m", -3.0, "--takeoff-alt"),
    ("plan_every", 0, "--plan-every"),
])
def test_agent_numbers_must_be_finite_and_in_range(field, value, option):
    from companion.node.config import check_node

    with pytest.raises(ConfigError) as e:
        check_node(_node(**{field: value}))
    assert f"\n  {option}: " in str(e.value), str(e.value)


def test_agent_signing_key_without_signing_is_refused(tmp_path):
    from companion.node.config import check_node

    with pytest.raises(ConfigError, match="--signing-key .* needs --signing optional\\|require"):
        check_node(_node(signing_key_file=tmp_path / "k"))
    check_node(_node(signing="require", signing_key_file=tmp_path / "k"))  # (the key itself is read later)


@pytest.mark.timeout(60)
def test_agent_cli_refuses_setup_timeout_nan_and_a_key_without_signing(tmp_path):
    r = swarmdrop(*agent_args("--autopilot", udp_autopilot(), "--setup-timeout", "nan"))
    assert r.returncode == 2 and "--setup-timeout: must be a finite number" in r.stderr, r.stderr
    r = swarmdrop(*agent_args("--autopilot", udp_autopilot(), "--signing-key", str(tmp_path / "k")))
    assert r.returncode == 2 and "--signing-key" in r.stderr and "needs --signing optional|require" in r.stderr
    no_traceback(r)


def _sitl_args(*argv: str) -> argparse.Namespace:
    from sim_bridge.sitl.cli import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    return p.parse_args(list(argv))


def test_sitl_signing_key_without_signing_is_refused(tmp_path):
    from sim_bridge.sitl.cli import config_from_args

    with pytest.raises(ConfigError, match="--signing-key .* needs --signing optional\\|require"):
        config_from_args(_sitl_args("--signing-key", str(tmp_path / "k")))
    cfg = config_from_args(_sitl_args("--signing", "optional", "--signing-key", str(tmp_path / "k")))
    assert cfg.signing.mode == "optional"


# ============================================================================ 6. ports past 65535
def test_fleet_base_port_range_must_end_within_65535(tmp_path):
    from sim_bridge.runs.fleet import FleetOptions, run_fleet
    from sim_bridge.runs.procs import check_base_port, choose_ports

    with pytest.raises(ConfigError, match=r"--base-port 65530: .* 19 consecutive UDP ports, 65530\.\.65548.*65517"):
        check_base_port(6, 65530)
    with pytest.raises(ConfigError, match="--base-port 65530"):
        choose_ports(6, 65530)
    check_base_port(6, 65517)  # the last one that fits
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match="--base-port 65530"):
        run_fleet(SMALL6, FleetOptions(out_dir=out, base_port=65530, progress=False, figures=False))
    assert not out.exists()  # refused before anything was made


def test_a_console_port_in_use_is_refused_before_anything_starts(tmp_path):
    # (an explicit --console-port that was taken used to warn and run on without the console)
    import socket

    from sim_bridge.runs.fleet import FleetOptions, run_fleet

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = tmp_path / "out"
        with pytest.raises(ConfigError, match=rf"--console-port {port}: cannot listen there .*or 0 for any free one"):
            run_fleet(SMALL6, FleetOptions(out_dir=out, console=True, console_port=port, progress=False, figures=False))
        assert not out.exists()


def test_run_cli_base_port_past_65535_exits_2_without_a_traceback(tmp_path):
    r = swarmdrop("run", str(SMALL6), "--base-port", "65530", "--out", str(tmp_path / "o"), "--quiet")
    assert r.returncode == 2 and "--base-port 65530" in r.stderr and not (tmp_path / "o").exists(), r.stderr
    no_traceback(r)


def test_sitl_ports_must_fit_the_vehicle_count():
    from sim_bridge.sitl.cli import config_from_args
    from sim_bridge.sitl.config import EndpointConfig, MediumConfig, sitl_config

    with pytest.raises(ConfigError, match="endpoints.remote_base_port 65534 .*port 65537, past 65535"):
        config_from_args(_sitl_args("--vehicles", "4", "--remote-base-port", "65534"))
    with pytest.raises(ConfigError, match="endpoints.local_base_port 65534 .*past 65535"):
        config_from_args(_sitl_args("--vehicles", "4", "--local-base-port", "65534"))
    with pytest.raises(ConfigError, match="medium.agent_base_port"):
        sitl_config(vehicles=4, medium=MediumConfig(enabled=True, agent_base_port=65533))
    # the GCS step-over: vehicles from 65530 step over a GCS port of 65532, so 5 vehicles end at 65535 ...
    gcs = {"remote_base_port": 65530, "gcs_remote_port": 65532}
    assert sitl_config(vehicles=5, endpoints=EndpointConfig(**gcs)).endpoints.vehicle_remote_port(4) == 65535
    with pytest.raises(ConfigError, match="port 65536 \\(stepping over endpoints.gcs_remote_port\\)"):
        sitl_config(vehicles=6, endpoints=EndpointConfig(**gcs))  # ... and a sixth would need 65536
    assert sitl_config(vehicles=4, endpoints=EndpointConfig(local_base_port=0)).vehicles == 4  # ephemeral: any count


@pytest.mark.timeout(60)
def test_sitl_cli_remote_port_past_65535_exits_2():
    r = swarmdrop("sitl", "--vehicles", "4", "--remote-base-port", "65534")
    assert r.returncode == 2 and "65537" in r.stderr and "--remote-base-port" in r.stderr and "READY" not in r.stdout
    no_traceback(r)


# ============================================================================ 7. fleet options, kill times, sitl --duration
@pytest.mark.parametrize("kw, phrase", [
    ({"rate_hz": 0.0}, "--rate 0"), ({"rate_hz": math.nan}, "--rate nan"), ({"rate_hz": 1e9}, "--rate 1e+09"),
    ({"fix_delay_max_s": -1.0}, "--fix-delay-max -1"), ({"fix_delay_max_s": math.inf}, "--fix-delay-max inf"),
    ({"agent_nice": 20}, "--agent-nice 20"), ({"agent_nice": -1}, "--agent-nice -1"),
])
def test_fleet_refuses_agent_options_the_agents_would_refuse_before_anything_starts(kw, phrase, tmp_path):
    from sim_bridge.runs.fleet import FleetOptions, run_fleet

    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=phrase.replace("+", "\\+")):
        run_fleet(SMALL6, FleetOptions(out_dir=out, progress=False, figures=False, **kw))
    assert not out.exists()


def test_fleet_refuses_a_kill_after_the_runs_duration(tmp_path):
    from sim_bridge.runs.fleet import FleetOptions, run_fleet

    out = tmp_path / "out"
    with pytest.raises(ConfigError, match="--kill-agent 1@1e\\+09: .*after the run's duration_s \\(150 s"):
        run_fleet(SMALL6, FleetOptions(out_dir=out, kill={1: 1e9}, progress=False, figures=False))
    assert not out.exists()


def test_run_cli_kill_agent_with_a_negative_id_names_the_id(tmp_path, capsys):
    from swarmdrop.cli import main

    for form in (["--kill-agent", "-1@5"], ["--kill-agent=-1@5"]):
        assert main(["run", str(SMALL6), "--out", str(tmp_path / "o"), "--quiet", *form]) == 2
        err = capsys.readouterr().err
        assert "vehicle id -1 is not a vehicle" in err and "expected one argument" not in err, err
    assert not (tmp_path / "o").exists()


def test_run_cli_rate_zero_exits_2_naming_rate(tmp_path):
    r = swarmdrop("run", str(SMALL6), "--rate", "0", "--out", str(tmp_path / "o"), "--quiet")
    assert r.returncode == 2 and "--rate 0" in r.stderr and "agent 0" not in r.stderr and not (tmp_path / "o").exists()
    no_traceback(r)


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf"])
def test_sitl_duration_must_be_above_zero(value):
    from sim_bridge.sitl.cli import config_from_args

    with pytest.raises(ConfigError, match="--duration"):
        config_from_args(_sitl_args("--duration", value))


# ============================================================================ 8. Ctrl-C
def main_or_fail(argv: list[str]) -> int:
    """swarmdrop.cli.main(argv); a KeyboardInterrupt that escapes it fails the test (instead of
    stopping the whole pytest session, as an escaped one does)."""
    from swarmdrop.cli import main

    try:
        return main(argv)
    except KeyboardInterrupt:
        pytest.fail("KeyboardInterrupt escaped swarmdrop.cli.main (a traceback for the user)")


def test_ctrl_c_before_the_run_has_flown_writes_nothing_and_says_so(tmp_path, monkeypatch, capsys):
    import sim_bridge.runs.simulate as sim
    from swarmdrop.cli import EXIT_INTERRUPTED

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "run_scenario", interrupted)
    out = tmp_path / "out"
    assert main_or_fail(["simulate", str(tiny_config(tmp_path)), "--out", str(out), "--quiet"]) == EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert f"nothing was written to {out}" in err and "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == [MARKER]


def test_ctrl_c_while_the_results_are_written_says_the_run_is_incomplete(tmp_path, monkeypatch, capsys):
    """The interrupt used to be reported as "nothing was written" beside config.json and telemetry.npz."""
    import sim_bridge.runs.simulate as sim
    from swarmdrop.cli import EXIT_INTERRUPTED

    monkeypatch.setattr(sim, "run_scenario", lambda cfg, progress=True: object())
    monkeypatch.setattr(sim, "compute_metrics", lambda result, study, so3: object())

    def save_log_then_ctrl_c(result, out_dir: Path) -> None:
        (out_dir / "telemetry.npz").write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "save_log", save_log_then_ctrl_c)
    out = tmp_path / "out"
    assert main_or_fail(["simulate", str(tiny_config(tmp_path)), "--out", str(out), "--quiet"]) == EXIT_INTERRUPTED
    err = capsys.readouterr().err.strip()
    assert "nothing was written" not in err
    assert f"{out} holds an incomplete run (config.json, telemetry.npz)" in err and "--overwrite" in err, err
    assert len(err.splitlines()) == 1 and not (out / "metrics.json").exists()


def test_ctrl_c_during_start_up_imports_is_one_line_and_exit_130(monkeypatch, capsys):
    import swarmdrop.cli as cli

    def importing(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", importing)
    assert main_or_fail(["simulate", str(SMALL6)]) == cli.EXIT_INTERRUPTED
    err = capsys.readouterr().err.strip()
    assert err == "swarmdrop: interrupted"


def test_a_sweep_of_a_billion_seeds_is_refused_before_anything_is_built(tmp_path, capsys):
    # (it used to build the list of seeds first: 24 GB, then the kernel's OOM killer, no message)
    out = tmp_path / "sw"
    assert main_or_fail(["sweep", str(SMALL6), "--seeds", "1000000000", "--workers", "1", "--quiet",
                         "--out", str(out)]) == 2
    assert "--seeds 1000000000: at most 100,000 in one sweep" in capsys.readouterr().err
    assert not out.exists()


def test_ctrl_c_during_a_sweep_says_what_was_written(tmp_path, monkeypatch, capsys):
    import sim_bridge.runs.sweep as sweep
    from swarmdrop.cli import EXIT_INTERRUPTED

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(sweep, "run_sweep", interrupted)
    out = tmp_path / "sw"
    assert main_or_fail(["sweep", str(SMALL6), "--seeds", "2", "--workers", "1", "--quiet", "--out", str(out)]) == \
        EXIT_INTERRUPTED
    assert f"nothing was written to {out}" in capsys.readouterr().err


# ============================================================================ 9. an agent started before its TCP server
def _read_until(proc: subprocess.Popen, text: str, timeout_s: float) -> str:
    """proc's stderr up to the line holding text (select with a deadline)."""
    got = ""
    deadline = time.monotonic() + timeout_s
    fd = proc.stderr.fileno()
    while text not in got:
        left = deadline - time.monotonic()
        assert left > 0 and proc.poll() is None, f"{text!r} not logged; got:\n{got}"
        if select.select([fd], [], [], min(left, 0.2))[0]:
            chunk = os.read(fd, 65536).decode(errors="replace")
            assert chunk, f"stderr closed; got:\n{got}"
            got += chunk
    return got


@pytest.mark.timeout(60)
def test_agent_waits_for_a_tcp_server_that_comes_up_later():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))  # bound, not listening yet: connections are refused
    port = server.getsockname()[1]
    url = f"tcp://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "swarmdrop.cli", *agent_args("--autopilot", url,
                                                                                 "--setup-timeout", "30")],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    conn = None
    try:
        _read_until(proc, f"waiting for TCP server on {url}", 30.0)
        server.listen(1)  # the autopilot comes up
        server.settimeout(30.0)
        conn, _ = server.accept()
        _read_until(proc, f"connected to the TCP server on {url}", 30.0)
        assert proc.poll() is None  # now it waits for a HEARTBEAT, as on UDP
    finally:
        if proc.poll() is None:
            proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stderr.close()
        if conn is not None:
            conn.close()
        server.close()


@pytest.mark.timeout(60)
def test_agent_with_no_tcp_server_exits_3_after_the_setup_timeout():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))  # never listens
    try:
        url = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        t0 = time.monotonic()
        r = swarmdrop(*agent_args("--autopilot", url, "--setup-timeout", "1"))
        wall = time.monotonic() - t0
    finally:
        server.close()
    assert r.returncode == 3, (r.stdout, r.stderr)  # as UDP with no autopilot: NO_AUTOPILOT, not CONFIG
    assert f"waiting for TCP server on {url}" in r.stderr and "within --setup-timeout 1 s" in r.stderr
    assert wall >= 1.0
    no_traceback(r)


# ============================================================================ 10. a hover too short to settle
# (tests/test_feasibility.py, with the other feasibility checks: test_a_landing_hover_shorter_than_the_settling_time*)


# ============================================================================ 11. smaller things
def test_a_serial_port_that_cannot_be_opened_names_the_device_and_baud_apart(tmp_path):
    from companion.link.endpoints import open_link

    dev = tmp_path / "ttyNOPE"
    with pytest.raises(OSError) as e:
        open_link(f"serial://{dev}:921600")
    msg = str(e.value)
    assert f"serial device {dev} (at 921600 baud)" in msg and f"{dev}:921600" not in msg, msg
    with pytest.raises(OSError, match="not a serial port"):  # a file that is no terminal: an OSError too
        open_link("/dev/null:57600")


def test_a_bad_seed_override_is_blamed_on_the_option_not_the_file():
    from sim_bridge.scenario import load_scenario

    with pytest.raises(ConfigError) as e:
        load_scenario(SMALL6, seed=-1)
    assert str(e.value).startswith("--seed: ") and str(SMALL6) not in str(e.value)
    with pytest.raises(ConfigError, match="^--first-seed: "):
        load_scenario(SMALL6, seed=-1, seed_option="--first-seed")


def test_a_waypoint_with_two_numbers_says_it_needs_three():
    from sim_bridge.scenario import ScenarioConfig

    data = yaml.safe_load(SMALL6.read_text())
    data["mission"]["waypoints_ned_m"][0] = [20.0, 0.0]
    with pytest.raises(ConfigError) as e:
        validate(ScenarioConfig, data, "x.yaml")
    assert "mission.waypoints_ned_m.0: a waypoint needs three numbers x, y, z (NED, m), got 2" in str(e.value)
    assert "Field required" not in str(e.value)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """One tiny headless run, in-process (2 vehicles, a short leg; seed 7 from small_6)."""
    from sim_bridge.reports.metrics import compute_metrics
    from sim_bridge.runs.headless import run_scenario
    from sim_bridge.scenario import load_scenario

    cfg = load_scenario(tiny_config(tmp_path_factory.mktemp("tiny")))
    result = run_scenario(cfg, progress=False)
    return cfg, result, compute_metrics(result, None)


def test_run_json_is_strict_json_and_reads_back(tiny_run, tmp_path):
    from sim_bridge.reports.record import load_run, save_run

    cfg, result, _ = tiny_run
    assert math.isinf(result.safety.min_clearance_m) and math.isnan(result.safety.min_clearance_time_s)  # no obstacle
    save_run(result, tmp_path)

    def refuse(name: str):
        raise AssertionError(f"bare {name} in run.json")

    info = json.loads((tmp_path / "run.json").read_text(), parse_constant=refuse)
    assert info["safety"]["min_clearance_m"] is None and info["safety"]["min_clearance_time_s"] is None
    back = load_run(tmp_path, cfg)
    assert math.isinf(back.safety.min_clearance_m) and math.isnan(back.safety.min_clearance_time_s)
    for name in ("t_go_s", "t_all_assembled_s", "t_complete_s", "t_land_start_s", "sim_s"):
        a, b = getattr(result, name), getattr(back, name)
        assert (math.isnan(a) and math.isnan(b)) or a == b, name
    assert back.safety.min_pair_dist_m == result.safety.min_pair_dist_m
    np.testing.assert_array_equal(back.failed_at_s, result.failed_at_s)


def test_the_summary_has_a_space_after_every_label(tiny_run, tmp_path):
    from sim_bridge.reports.summary import summary_lines

    _, _, metrics = tiny_run
    [line] = [ln for ln in summary_lines(metrics, tmp_path) if "min obstacle clearance" in ln]
    assert line.startswith("  min obstacle clearance: "), line


def test_run_prints_its_run_directory_absolute(tmp_path, monkeypatch, capsys):
    import sim_bridge.runs.fleet as fleet
    import sim_bridge.runs.fleet_report as report
    from swarmdrop.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(fleet, "run_fleet", lambda config, opts, warn=None: (object(), 0))
    monkeypatch.setattr(report, "summary_lines", lambda rep, out: [f"run directory: {out}"])
    assert main(["run", str(SMALL6), "--out", "rel/run", "--quiet"]) == 0
    assert capsys.readouterr().out.strip() == f"run directory: {(tmp_path / 'rel' / 'run').resolve()}"


@pytest.mark.timeout(60)
def test_the_agent_logs_the_swarm_port_it_bound():
    r = swarmdrop(*agent_args("--autopilot", udp_autopilot(), "--swarm-bind", "127.0.0.1:0", "--setup-timeout",
                              "0.5"))
    assert r.returncode == 3, r.stderr
    line = next(ln for ln in r.stderr.splitlines() if "swarm link on" in ln)
    port = int(line.rsplit("swarm link on 127.0.0.1:", 1)[1].split()[0])
    assert port > 0, line


# ============================================================================ 12. help shows every default
def _optional_actions(parser: argparse.ArgumentParser):
    return [a for a in parser._actions if a.option_strings and a.help != argparse.SUPPRESS
            and not isinstance(a, (argparse._HelpAction, argparse._VersionAction))]


def test_agent_help_shows_every_default():
    from companion.node.cli import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    missing = [a.option_strings[0] for a in _optional_actions(p) if "default" not in a.help and "required" not in a.help]
    assert missing == []
    text = p.format_help().replace("\n", " ")
    text = " ".join(text.split())
    for shown in ("default 120", "default acceleration", "default off", "default INFO",
                  "default: the mission's mission.takeoff_alt_m"):
        assert shown in text, shown


def test_sweep_help_has_a_description_and_shows_every_default():
    from swarmdrop.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    sweep = sub.choices["sweep"]
    assert sweep.description and "seed" in sweep.description
    missing = [a.option_strings[0] for a in _optional_actions(sweep) if "default" not in a.help]
    assert missing == []
    seeds = next(a for a in sweep._actions if "--seeds" in a.option_strings)
    assert "default 10" in seeds.help
