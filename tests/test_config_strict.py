"""Issue 16: every bad config value is refused at load with its dotted path and a reason,
and a mission that cannot be flown is refused before anything flies: by `load_scenario`,
by `swarmdrop simulate` (exit 2, "error:", no traceback) and by `swarmdrop agent` (exit
code CONFIG). The shipped configs load with no errors and no warnings."""
from __future__ import annotations

import copy
import math
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable

import pytest
import yaml

from companion.config import ConfigError, validate
from companion.node.runner import ExitCode
from sim_bridge.scenario import ScenarioConfig, load_scenario, scenario_findings
from sim_bridge.sitl.testing import free_udp_base_port

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SMALL6 = CONFIGS / "small_6.yaml"
PAPER40 = CONFIGS / "paper_40.yaml"
SHIPPED = sorted(CONFIGS.glob("*.yaml"))


def _edited(base: Path, edit: Callable[[dict], Any]) -> dict:
    data = yaml.safe_load(base.read_text())
    data = copy.deepcopy(data)
    edit(data)
    return data


def _write(tmp: Path, name: str, data: dict) -> Path:
    p = tmp / f"{name}.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def _set(*keys_and_value):
    """An edit that sets data[k1][k2]...[kn] = value (list indices allowed)."""
    *keys, value = keys_and_value

    def edit(data: dict) -> None:
        node = data
        for k in keys[:-1]:
            node = node.setdefault(k, {}) if isinstance(k, str) else node[k]
        node[keys[-1]] = value

    return edit


# name: (base config, edit, dotted path, reason (a phrase of the message))
BAD = {
    # the reported user failures
    "waypoint with a NaN": (SMALL6, _set("mission", "waypoints_ned_m", 1, 1, math.nan),
                            "mission.waypoints_ned_m.1.1", "must be a finite number"),
    "duration_s: .inf": (SMALL6, _set("duration_s", math.inf), "duration_s", "must be a finite number"),
    "seed: -1": (SMALL6, _set("seed", -1), "seed", "greater than or equal to 0"),
    "n_vehicles: 10000": (SMALL6, _set("mission", "n_vehicles", 10000), "mission.n_vehicles",
                          "flies at most 1000"),
    "n_vehicles: true": (SMALL6, _set("mission", "n_vehicles", True), "mission.n_vehicles",
                         "must be a whole number"),
    "obstacle enclosing the formation": (PAPER40, _set("mission", "obstacles",
                                                       [{"centre_ned_m": [100.0, 0.0, -10.0], "radius_m": 45.0}]),
                                         "mission.obstacles.0", "encloses the whole formation at the assembly point"),
    "obstacle on the launch track": (SMALL6, _set("mission", "obstacles",
                                                  [{"centre_ned_m": [12.0, 0.5, -20.0], "radius_m": 2.0}]),
                                     "mission.obstacles.0", "launch track (0, 0, -20) -> (25, 0, -20) passes through"),
    "waypoint below ground": (SMALL6, _set("mission", "waypoints_ned_m", 1, 2, 5.0), "mission.waypoints_ned_m.1",
                              "5 m below the ground"),
    "waypoint 1e9 m away": (SMALL6, _set("mission", "waypoints_ned_m", 1, 0, 1.0e9), "mission.waypoints_ned_m.1",
                            "beyond 10000 m"),
    "transit speed 1e6 m/s": (SMALL6, _set("mission", "transit_speed_mps", 1.0e6), "mission.transit_speed_mps",
                              "beyond what the autopilot flies"),
    # strict integers and booleans, more non-finite numbers
    "n_vehicles: 2.0": (SMALL6, _set("mission", "n_vehicles", 2.0), "mission.n_vehicles", "must be a whole number"),
    "a boolean given as 1": (SMALL6, _set("launch_study", "enabled", 1), "launch_study.enabled",
                             "must be true or false"),
    "seed: 7.0": (SMALL6, _set("seed", 7.0), "seed", "must be a whole number"),
    "seed beyond 64 bits": (SMALL6, _set("seed", 2**63), "seed", "less than or equal to 9223372036854775807"),
    "a number written as a string": (SMALL6, _set("duration_s", "1e3"), "duration_s", "must be a number"),
    "carrier start -inf": (SMALL6, _set("carrier", "start_ned_m", [0.0, 0.0, -math.inf]), "carrier.start_ned_m.2",
                           "must be a finite number"),
    "NaN obstacle radius": (SMALL6, _set("mission", "obstacles", 0, "radius_m", math.nan),
                            "mission.obstacles.0.radius_m", "must be a finite number"),
    "duration over a day": (SMALL6, _set("duration_s", 86_401.0), "duration_s", "less than or equal to 86400"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_load_scenario_refuses_a_bad_value_naming_its_path_and_reason(case, tmp_path):
    base, edit, path, reason = BAD[case]
    f = _write(tmp_path, "bad", _edited(base, edit))
    with pytest.raises(ConfigError) as e:
        load_scenario(f)
    msg = str(e.value)
    assert msg.startswith(str(f)), msg
    lines = [ln.strip() for ln in msg.splitlines()]
    assert any(ln.startswith(f"{path}: ") and reason in ln for ln in lines), msg


def test_a_seed_override_is_validated_like_the_files_seed():
    with pytest.raises(ConfigError, match=r"seed: Input should be greater than or equal to 0 \(got -1\)"):
        load_scenario(SMALL6, seed=-1)
    assert load_scenario(SMALL6, seed=3).seed == 3


@pytest.mark.parametrize("value, reason", [(True, "must be a whole number"), (2.0, "must be a whole number"),
                                           ("3", "must be a whole number")])
def test_integers_are_strict(value, reason, tmp_path):
    """`true` and `2.0` are not integers: `n_vehicles: true` used to fly one vehicle."""
    data = _edited(SMALL6, _set("mission", "n_vehicles", value))
    with pytest.raises(ConfigError) as e:
        validate(ScenarioConfig, data, "x.yaml")
    assert f"mission.n_vehicles: {reason}" in str(e.value) and f"(got {value!r})" in str(e.value)


@pytest.mark.parametrize("value", [1, 0, "true", "yes"])
def test_booleans_are_strict(value):
    data = _edited(SMALL6, _set("output", "figures", value))
    with pytest.raises(ConfigError, match=r"output\.figures: must be true or false"):
        validate(ScenarioConfig, data, "x.yaml")


def test_a_bare_yaml_word_read_as_a_boolean_gets_a_hint(tmp_path):
    """YAML 1.1 reads `launch: off` (or yes, no, on) as a boolean: the error says to quote it."""
    f = tmp_path / "off.yaml"
    f.write_text("mission:\n  launch: off\n")
    with pytest.raises(ConfigError) as e:
        load_scenario(f)
    assert "mission.launch: Input should be 'carrier' or 'ground' (YAML reads a bare on, off, yes or no as true " \
           "or false: quote the word) (got False)" in str(e.value)


def test_an_integer_is_a_number_and_a_yaml_boolean_is_a_boolean():
    data = _edited(SMALL6, _set("duration_s", 150))  # 150 is a fine float
    data["output"]["figures"] = False
    cfg = validate(ScenarioConfig, data, "x.yaml")
    assert cfg.duration_s == 150.0 and cfg.output.figures is False


def test_every_bad_value_of_a_file_is_named_at_once(tmp_path):
    data = _edited(SMALL6, _set("seed", -1))
    data["duration_s"] = math.inf
    data["mission"]["n_vehicles"] = True
    with pytest.raises(ConfigError) as e:
        load_scenario(_write(tmp_path, "three", data))
    msg = str(e.value)
    assert "3 invalid setting(s)" in msg
    assert all(f"\n  {p}: " in msg for p in ("seed", "duration_s", "mission.n_vehicles")), msg


# ---------------------------------------------------------------------------- the simulate CLI
@pytest.mark.timeout(120)
@pytest.mark.parametrize("case", list(BAD))
def test_simulate_cli_exits_2_naming_the_path_before_flying(case, tmp_path):
    base, edit, path, reason = BAD[case]
    f = _write(tmp_path, "bad", _edited(base, edit))
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "simulate", str(f), "--out", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=90)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stderr.startswith("error: "), r.stderr
    assert f"{path}: " in r.stderr and reason in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert not out.exists(), "the run directory was created: the run started"
    assert "run directory" not in r.stdout


@pytest.mark.timeout(60)
def test_simulate_cli_refuses_a_negative_seed_option(tmp_path):
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "simulate", str(SMALL6), "--seed", "-1", "--out",
                        str(out)], cwd=ROOT, capture_output=True, text=True, timeout=50)
    assert r.returncode == 2 and "seed" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()


WARNING_ONLY = _set("mission", "transit_accel_mps2", 5.0)
"""small_6 with a transit acceleration above mission.consensus_accel_max_mps2 (3) but below what
a Crazyflie can do (g tan 50 deg = 11.7 m/s^2): a warning, no error."""


def test_the_warning_only_mission_gives_one_warning_and_no_error():
    cfg = validate(ScenarioConfig, _edited(SMALL6, WARNING_ONLY))
    found = scenario_findings(cfg)
    assert [(f.path, f.error) for f in found] == [("mission.transit_accel_mps2", False)], found


@pytest.mark.timeout(60)
def test_simulate_cli_strict_refuses_a_warning(tmp_path):
    """`swarmdrop simulate --strict` (swarmdrop/cli.py) makes warnings errors."""
    f = _write(tmp_path, "warn", _edited(SMALL6, WARNING_ONLY))
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "simulate", str(f), "--strict", "--out", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=50)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stderr.startswith("error: ") and "mission.transit_accel_mps2: " in r.stderr, r.stderr
    assert "--strict makes it an error" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


# ---------------------------------------------------------------------------- the shipped configs
@pytest.mark.parametrize("config", SHIPPED, ids=[p.name for p in SHIPPED])
def test_shipped_configs_load_with_no_errors_and_no_warnings(config):
    warnings: list[str] = []
    cfg = load_scenario(config, strict=True, warn=warnings.append, runner=None)
    assert warnings == []
    for runner in ("headless", "sitl", "fleet"):
        found = scenario_findings(cfg, runner)
        if runner == "headless" and cfg.mission.launch != "carrier":  # refused at load, and only for that
            assert [f.path for f in found] == ["mission.launch"], found
            continue
        assert found == [], f"{config.name} ({runner}): " + "; ".join(map(str, found))


def test_shipped_configs_are_all_checked():
    assert {p.name for p in SHIPPED} >= {"small_6.yaml", "paper_40.yaml", "paper_40_disturbed.yaml", "ground_4.yaml"}


# ---------------------------------------------------------------------------- the agent
def _agent(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """`swarmdrop agent ARGS` to its end (the swarm socket on 127.0.0.1, an ephemeral port)."""
    return subprocess.run([sys.executable, "-m", "swarmdrop.cli", "agent", "--swarm-bind", "127.0.0.1:0", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)


AGENT_BAD = {
    "obstacle enclosing the formation": (_set("mission", "obstacles",
                                              [{"centre_ned_m": [20.0, 0.0, -10.0], "radius_m": 12.0}]),
                                         "mission.obstacles.0", "encloses the whole formation"),
    "more vehicles than MAVLink sysids": (_set("mission", "n_vehicles", 251), "mission.n_vehicles",
                                          "at most 250"),
    "waypoint below ground": (_set("mission", "waypoints_ned_m", 1, 2, 5.0), "mission.waypoints_ned_m.1",
                              "below the ground"),
    "transit speed 1e6 m/s": (_set("mission", "transit_speed_mps", 1.0e6), "mission.transit_speed_mps",
                              "beyond what the autopilot flies"),
    "waypoint with a NaN": (_set("mission", "waypoints_ned_m", 0, 0, math.nan), "mission.waypoints_ned_m.0.0",
                            "must be a finite number"),
}


@pytest.mark.timeout(90)
@pytest.mark.parametrize("case", list(AGENT_BAD))
def test_agent_refuses_an_infeasible_mission_with_the_config_exit_code(case, tmp_path):
    edit, path, reason = AGENT_BAD[case]
    f = _write(tmp_path, "mission", _edited(SMALL6, edit))
    r = _agent("--vehicle-id", "0", "--mission", str(f), "--autopilot", f"udpin://127.0.0.1:{free_udp_base_port(1)}",
               "--setup-timeout", "1")
    assert r.returncode == int(ExitCode.CONFIG) == 2, (r.stdout, r.stderr)
    assert str(f) in r.stderr and f"{path}: " in r.stderr and reason in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and "HEARTBEAT" not in r.stderr  # refused before waiting for anything


@pytest.mark.timeout(90)
def test_agent_strict_refuses_a_warning_which_it_otherwise_logs(tmp_path):
    f = _write(tmp_path, "mission", _edited(SMALL6, WARNING_ONLY))
    url = f"udpin://127.0.0.1:{free_udp_base_port(1)}"
    strict = _agent("--vehicle-id", "0", "--mission", str(f), "--autopilot", url, "--strict")
    assert strict.returncode == int(ExitCode.CONFIG), (strict.stdout, strict.stderr)
    assert "mission.transit_accel_mps2: " in strict.stderr and "--strict makes it an error" in strict.stderr
    # without --strict the warning is logged and the agent goes on (to wait for an autopilot that
    # never comes: exit NO_AUTOPILOT after --setup-timeout)
    lax = _agent("--vehicle-id", "0", "--mission", str(f), "--autopilot", url, "--setup-timeout", "1")
    assert lax.returncode == int(ExitCode.NO_AUTOPILOT), (lax.stdout, lax.stderr)
    warned = [ln for ln in lax.stderr.splitlines() if " WARNING " in ln and "mission.transit_accel_mps2" in ln]
    assert len(warned) == 1 and str(f) in warned[0], lax.stderr


def test_agent_feasibility_check_is_pure_and_passes_the_shipped_missions():
    from companion.node.config import load_mission_file, mission_findings

    for config in SHIPPED:
        assert mission_findings(load_mission_file(config)) == [], config.name


def _file(tmp: Path, name: str, content: bytes | None) -> Path:
    p = tmp / name
    if content is not None:
        p.write_bytes(content)
    return p


@pytest.mark.parametrize("name, content, reason", [
    ("", None, "is a directory, not a config file"),
    ("bin.yaml", b"\xff\xfe\x00mission", "cannot be read"),
    ("list.yaml", b"- 1\n", "expected a mapping at the top level"),
    ("nope.yaml", None, "no such mission file"),
])
def test_an_unusable_mission_file_is_a_config_error(name, content, reason, tmp_path):
    """A directory or an undecodable file used to escape as IsADirectoryError (reported as a link
    that cannot be opened) or UnicodeDecodeError (a traceback, exit 1)."""
    from companion.node.config import load_mission_file

    with pytest.raises(ConfigError, match=reason):
        load_mission_file(_file(tmp_path, name, content))


@pytest.mark.timeout(60)
def test_agent_with_an_undecodable_mission_file_exits_2_without_a_traceback(tmp_path):
    f = tmp_path / "bin.yaml"
    f.write_bytes(b"\xff\xfe\x00mission")
    r = _agent("--vehicle-id", "0", "--mission", str(f), "--autopilot", f"udpin://127.0.0.1:{free_udp_base_port(1)}")
    assert r.returncode == int(ExitCode.CONFIG), (r.stdout, r.stderr)
    assert f"{f}: cannot be read" in r.stderr and "Traceback" not in r.stderr


def test_sweep_refuses_a_negative_first_seed_before_flying(tmp_path):
    r = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "sweep", str(ROOT / "configs" / "small_6.yaml"),
                        "--first-seed", "-1", "--seeds", "2", "--workers", "1", "--quiet", "--out",
                        str(tmp_path / "sw")], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "seed" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "sw" / "runs.csv").exists()
