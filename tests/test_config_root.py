"""One config root (issue 17): the scenario schema is read whole by the SITL, one YAML
reader, one origin type, and a `version:` that gives an old or newer file a clear message."""
from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest
import yaml

from companion.config import CONFIG_VERSION, ConfigError
from companion.mission import GeodeticOrigin
from companion.node.config import load_mission_file
from sim_bridge.scenario import load_scenario
from sim_bridge.sitl.cli import add_arguments, config_from_args
from sim_bridge.sitl.config import DEFAULT_HOME, load_config

ROOT = Path(__file__).resolve().parents[1]
SMALL6 = ROOT / "configs" / "small_6.yaml"


def _write(tmp: Path, name: str, data) -> Path:
    p = tmp / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_the_sitl_reads_the_scenario_whole_nothing_copied(tmp_path):
    args = argparse.ArgumentParser()
    add_arguments(args)
    cfg = config_from_args(args.parse_args(["--scenario", str(SMALL6), "--dialect", "ardupilot"]))
    sc = load_scenario(SMALL6, runner=None)
    assert cfg.scenario == sc  # the section is the scenario itself
    assert (cfg.vehicles, cfg.seed, cfg.launch) == (sc.mission.n_vehicles, sc.seed, sc.mission.launch)
    assert cfg.home == sc.mission.origin and isinstance(cfg.home, GeodeticOrigin)
    assert (cfg.vehicle, cfg.inner_loop, cfg.carrier, cfg.estimator, cfg.faults, cfg.link) == (
        sc.vehicle, sc.inner_loop, sc.carrier, sc.estimator, sc.faults, sc.link)
    assert cfg.swarm_rate_hz == sc.mission.swarm.rate_hz and cfg.wind == sc.physics.wind
    over = config_from_args(args.parse_args(["--scenario", str(SMALL6), "--vehicles", "3", "--seed", "9"]))
    assert (over.vehicles, over.seed) == (3, 9)
    assert load_config(None).home == DEFAULT_HOME  # no mission origin: PX4 SITL's home


def test_a_version_1_sitl_config_says_where_its_keys_moved(tmp_path):
    old = _write(tmp_path, "old.yaml", {"vehicles": 4, "seed": 2, "home": {"lat_deg": 1.0, "lon_deg": 2.0},
                                        "dialect": "px4"})
    with pytest.raises(ConfigError, match=r"version-1 SITL config.*vehicles, seed, home.*scenario.mission.n_vehicles"):
        load_config(old)
    new = _write(tmp_path, "new.yaml", {"version": CONFIG_VERSION, "dialect": "px4",
                                        "scenario": {"seed": 2, "mission": {"n_vehicles": 4}}})
    assert load_config(new).vehicles == 4
    too_many = _write(tmp_path, "many.yaml", {"scenario": {"mission": {"n_vehicles": 300}}})
    with pytest.raises(ConfigError, match="at most 250"):
        load_config(too_many)


@pytest.mark.parametrize("version, match", [
    (CONFIG_VERSION + 1, "newer swarmdrop"), (0, "whole number from 1"), (True, "whole number"), ("2", "whole number"),
])
def test_every_reader_checks_the_version(tmp_path, version, match):
    data = yaml.safe_load(SMALL6.read_text())
    data["version"] = version
    p = _write(tmp_path, "v.yaml", data)
    with pytest.raises(ConfigError, match=match):
        load_scenario(p, runner=None)
    with pytest.raises(ConfigError, match=match):
        load_mission_file(p)
    with pytest.raises(ConfigError, match=match):
        load_config(_write(tmp_path, "s.yaml", {"version": version}))


def test_shipped_configs_say_their_version():
    for p in sorted((ROOT / "configs").glob("*.yaml")):
        assert yaml.safe_load(p.read_text())["version"] == CONFIG_VERSION, p.name


def test_one_yaml_reader_and_one_origin_type():
    """Only companion.config parses YAML; no module defines a second geodetic-origin type."""
    readers, origins = [], []
    for pkg in ("companion", "sim_bridge", "swarmdrop"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "yaml" \
                        and node.attr in ("safe_load", "load", "full_load", "unsafe_load"):
                    readers.append(str(path.relative_to(ROOT)))
                if isinstance(node, ast.ClassDef):
                    fields = {t.target.id for t in node.body if isinstance(t, ast.AnnAssign)
                              and isinstance(t.target, ast.Name)}
                    if {"lat_deg", "lon_deg"} <= fields:
                        origins.append(f"{path.relative_to(ROOT)}:{node.name}")
    assert readers == ["companion/config.py"]
    assert origins == ["companion/mission.py:GeodeticOrigin"]
