"""Config validation: errors name the dotted path and the reason; the simulate CLI."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from companion.config import ConfigError, load_yaml
from sim_bridge.scenario import ScenarioConfig

ROOT = Path(__file__).resolve().parents[1]


def test_paper_40_loads():
    cfg = load_yaml(ScenarioConfig, ROOT / "configs" / "paper_40.yaml")
    assert cfg.mission.n_vehicles == 40
    assert cfg.carrier.vel_ned_mps == (5.0, 0.0, 0.0)
    assert cfg.mission.obstacles[0].radius_m == 15.0


def test_unknown_key_named_with_path(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("mission:\n  formation:\n    radius_m: 40\n    raduis_m: 3\n")
    with pytest.raises(ConfigError) as e:
        load_yaml(ScenarioConfig, f)
    assert "mission.formation.raduis_m: unknown key" in str(e.value)


def test_bad_value_named_with_reason(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("mission:\n  formation:\n    radius_m: -5\nphysics:\n  rate_hz: 100\n")
    with pytest.raises(ConfigError) as e:
        load_yaml(ScenarioConfig, f)
    msg = str(e.value)
    assert "mission.formation.radius_m" in msg and "greater than 0" in msg and "-5" in msg
    assert "physics.rate_hz" in msg and "500" in msg


def test_rates_must_divide(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("agent:\n  rate_hz: 30\n")
    with pytest.raises(ConfigError, match="whole multiple"):
        load_yaml(ScenarioConfig, f)


def test_missing_file():
    with pytest.raises(ConfigError, match="no such config file"):
        load_yaml(ScenarioConfig, "/nonexistent/x.yaml")


def test_cli_reports_config_error(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("carrier:\n  vel_ned_mps: [5, 0]\n")
    r = subprocess.run(
        [sys.executable, "-m", "swarmdrop.cli", "simulate", str(f), "--quiet"],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )
    assert r.returncode == 2
    assert "carrier.vel_ned_mps" in r.stderr


def test_cli_simulate_writes_run_directory_and_passes_checks(tmp_path):
    from swarmdrop.cli import main

    out = tmp_path / "run"
    assert main(["simulate", str(ROOT / "configs" / "small_6.yaml"), "--out", str(out), "--quiet",
                 "--no-figures", "--check", "--seed", "11"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["seed"] == 11 and all(m["checks"].values())
    assert (out / "telemetry.npz").stat().st_size > 0 and (out / "config.json").exists()
