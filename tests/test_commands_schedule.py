"""The scenario's `commands:` schedule (companion/commands/schedule.py): validated at load
with errors that name the entry, in time order, and dry-run through a CommandSource (the
commands it would refuse)."""
from __future__ import annotations

import dataclasses
import math

import pytest

from companion.commands import CommandEntry, CommandSource, check_schedule, schedule_problems
from companion.config import ConfigError, validate
from companion.control.shapes import FormationSpec
from companion.mission import Mission
from sim_bridge.scenario import ScenarioConfig


def _scenario(commands, n=6):
    return {"mission": {"n_vehicles": n, "waypoints_ned_m": [[30.0, 0.0, -10.0], [60.0, 0.0, -10.0]],
                        "formation": {"radius_m": 8.0}},
            "commands": commands}


def test_schedule_loads_and_runs_through_a_command_source():
    cmds = [{"t_s": 30.0, "kind": "hold"}, {"t_s": 35.0, "kind": "formation", "shape": "wedge", "spacing_m": 4.0,
                                             "rotation_deg": 90.0},
            {"t_s": 40.0, "kind": "resume"}, {"t_s": 45.0, "kind": "exclude", "vehicles": [2], "land": False},
            {"t_s": 50.0, "kind": "rejoin", "vehicles": [2]}, {"t_s": 55.0, "kind": "goto",
                                                                 "waypoints_ned_m": [[0.0, 0.0, -12.0]], "speed_mps": 2.0},
            {"t_s": 60.0, "kind": "land", "vehicles": [1, 6]}, {"t_s": 70.0, "kind": "rtl"},
            {"t_s": 90.0, "kind": "land"}, {"t_s": 95.0, "kind": "abort"}]
    cfg = validate(ScenarioConfig, _scenario(cmds))
    assert len(cfg.commands) == len(cmds)
    src = CommandSource(Mission(cfg.mission))
    plans = [src.apply(c) for c in cfg.commands]
    assert [p.kind for p in plans] == [c["kind"] for c in cmds]
    assert plans[1].formation.shape == "wedge" and plans[1].formation.rotation_rad == pytest.approx(math.pi / 2)
    assert plans[3].excluded == {1} and not plans[3].landing  # (parked: it can rejoin; a descent cannot)
    assert plans[6].landing == {0, 5}
    assert plans[-1].abort


@pytest.mark.parametrize("entry,path,words", [
    ({"t_s": 1.0, "kind": "goto"}, "commands.0", "goto needs waypoints_ned_m"),
    ({"t_s": 1.0, "kind": "hold", "speed_mps": 2.0}, "commands.0", "hold does not take speed_mps"),
    ({"t_s": 1.0, "kind": "exclude"}, "commands.0", "exclude needs vehicles"),
    ({"t_s": 1.0, "kind": "formation"}, "commands.0", "at least one of shape"),
    ({"t_s": 1.0, "kind": "formation", "shape": "hexagon"}, "commands.0.shape", ""),
    ({"t_s": 1.0, "kind": "land", "vehicles": [0]}, "commands.0.vehicles.0", ""),
    ({"t_s": 1.0, "kind": "land", "vehicles": [7]}, "commands.0.vehicles", "not in the mission"),
    ({"t_s": 1.0, "kind": "teleport"}, "commands.0.kind", ""),
    ({"t_s": -1.0, "kind": "hold"}, "commands.0.t_s", ""),
    ({"t_s": 1.0, "kind": "goto", "waypoints_ned_m": [[1.0, 2.0]]}, "commands.0.waypoints_ned_m.0", "three numbers"),
    ({"t_s": 1.0, "kind": "exclude", "vehicles": [1], "land": 1}, "commands.0.land", "true or false"),
])
def test_schedule_errors_name_the_path(entry, path, words):
    with pytest.raises(ConfigError) as err:
        validate(ScenarioConfig, _scenario([entry]), "s.yaml")
    text = str(err.value)
    assert path in text and words in text, text


def test_schedule_must_be_within_the_run():
    entries = (CommandEntry(t_s=50.0, kind="hold"), CommandEntry(t_s=500.0, kind="resume"))
    check_schedule(entries, 6)
    with pytest.raises(ValueError, match=r"commands\.1\.t_s: 500 s is not before the end of the run \(duration_s 400 s\)"):
        check_schedule(entries, 6, 400.0)


def test_schedule_must_be_in_time_order():
    with pytest.raises(ConfigError, match=r"commands\.1\.t_s: .* time order"):
        validate(ScenarioConfig, _scenario([{"t_s": 5.0, "kind": "hold"}, {"t_s": 2.0, "kind": "resume"}]))


def test_no_schedule_by_default():
    assert validate(ScenarioConfig, _scenario([])).commands == ()
    assert ScenarioConfig().commands == ()


def test_entry_formation_spec_keeps_what_is_not_given():
    cur = FormationSpec("circle", radius_m=20.0, spacing_m=3.0, rotation_rad=0.5, slot_order="interleaved")
    e = CommandEntry(t_s=1.0, kind="formation", radius_m=10.0)
    assert e.formation_spec(cur) == dataclasses.replace(cur, radius_m=10.0)


def test_a_dry_run_of_a_schedule_names_the_commands_it_would_refuse():
    cfg = validate(ScenarioConfig, _scenario([{"t_s": 1.0, "kind": "resume"},
                                              {"t_s": 2.0, "kind": "formation", "shape": "shell", "radius_m": 20.0},
                                              {"t_s": 3.0, "kind": "abort"}, {"t_s": 4.0, "kind": "hold"}]))
    problems = schedule_problems(cfg.commands, Mission(cfg.mission))
    assert [p.split(":")[0] for p in problems] == ["commands.0", "commands.1", "commands.3"]
    assert "not held" in problems[0] and "below the ground" in problems[1] and "aborted" in problems[2]
