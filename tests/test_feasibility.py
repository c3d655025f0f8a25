"""Can it fly? companion.feasibility.check_mission and sim_bridge.scenario.scenario_findings
on closed-form geometry: each check, whether it is an error or a warning, and
check_findings' --strict (docs/scenario.md, "Can it fly?")."""
from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.config import ConfigError, validate
from companion.control.formation import ConsensusGains
from companion.feasibility import (
    MAVLINK_MAX_VEHICLES,
    MAX_RANGE_M,
    Finding,
    check_mission,
    errors_of,
    max_horizontal_accel_mps2,
    min_slot_distance_m,
    segment_gap_m,
    thrust_to_weight,
)
from companion.link.limits import SetpointLimits
from companion.mission import (
    ApfConfig,
    FormationConfig,
    GeofenceConfig,
    MissionConfig,
    Obstacle,
    PhaseConfig,
    formation_offsets_ned_m,
)
from companion.params import GRAVITY_MPS2, InnerLoopConfig, VehicleParams
from sim_bridge.scenario import HEADLESS_MAX_VEHICLES, ScenarioConfig, check_findings, scenario_findings

ROOT = Path(__file__).resolve().parents[1]
W0 = (0.0, 0.0, -10.0)
W1 = (100.0, 0.0, -10.0)
TRACK = (np.array([0.0, 0.0, -30.0]), np.array([50.0, 0.0, -30.0]))
"""A carrier track 20 m above the formation plane (no slot near it)."""


def mission(n: int = 4, radius_m: float = 10.0, waypoints=(W0, W1), **kw) -> MissionConfig:
    """n vehicles on a circle, slot_order sequential: with n = 4 and radius r, UAV 1..4 sit at
    (r, 0), (0, r), (-r, 0), (0, -r) around the centre (north, east, south, west); neighbours
    are r * sqrt(2) apart."""
    return MissionConfig(n_vehicles=n, formation=FormationConfig(radius_m=radius_m, slot_order="sequential"),
                         waypoints_ned_m=tuple(waypoints), **kw)


def only(findings: list[Finding]) -> Finding:
    assert len(findings) == 1, [str(f) for f in findings]
    return findings[0]


def test_the_reference_mission_has_no_findings():
    assert check_mission(mission()) == []
    assert check_mission(mission(), launch_track_ned_m=TRACK, obstacle_margin_m=1.0) == []


def test_slot_geometry_used_below():
    r = formation_offsets_ned_m(FormationConfig(radius_m=10.0, slot_order="sequential"), 4)
    np.testing.assert_allclose(r, [[10, 0, 0], [0, 10, 0], [-10, 0, 0], [0, -10, 0]], atol=1e-12)
    d, i, j = min_slot_distance_m(r)
    assert d == pytest.approx(10 * math.sqrt(2)) and (j - i) % 2 == 1  # (all four pairs of neighbours tie)
    assert min_slot_distance_m(r[:1])[0] == math.inf


# ---------------------------------------------------------------------------- obstacles
def test_an_obstacle_whose_sphere_holds_every_slot_encloses_the_formation():
    f = only(check_mission(mission(obstacles=(Obstacle(centre_ned_m=W0, radius_m=10.5),))))
    assert f.error and f.path == "mission.obstacles.0"
    assert f.reason == "encloses the whole formation at the assembly point (waypoint 0)"


def test_an_obstacle_enclosing_the_final_hover():
    f = only(check_mission(mission(obstacles=(Obstacle(centre_ned_m=W1, radius_m=10.5),))))
    assert f.error and "the last waypoint (the final hover) (waypoint 1)" in f.reason


def test_one_waypoint_is_both_the_assembly_point_and_the_final_hover():
    f = only(check_mission(mission(waypoints=(W0,), obstacles=(Obstacle(centre_ned_m=W0, radius_m=11.0),))))
    assert f.error and "the assembly point (also the final hover) (waypoint 0)" in f.reason


def test_the_obstacle_margin_moves_the_surface_out():
    """Slots 0.5 m outside a 9.5 m sphere: clear at margin 0 (but in its repulsion: a warning),
    enclosed at margin 1."""
    m = mission(obstacles=(Obstacle(centre_ned_m=W0, radius_m=9.5),))
    f = only(check_mission(m, obstacle_margin_m=0.0))
    assert not f.error and "the slot of UAV(s) 1, 2, 3, 4 at the assembly point" in f.reason
    assert "mission.apf.obstacle_influence_m 8 m" in f.reason
    f = only(check_mission(m, obstacle_margin_m=1.0))
    assert f.error and "encloses the whole formation" in f.reason


def test_an_obstacle_holding_one_slot():
    # UAV 1's slot at the assembly point is (10, 0, -10); the next slot is 14.1 m from the obstacle's
    # centre, 13.1 m from its surface: outside the 8 m repulsion
    m = mission(obstacles=(Obstacle(centre_ned_m=(10.0, 0.0, -10.0), radius_m=1.0),))
    f = only(check_mission(m))
    assert f.error and f.path == "mission.obstacles.0"
    assert f.reason.startswith("holds the slot of UAV(s) 1 at the assembly point (waypoint 0)")


def test_repulsion_without_gain_is_no_warning():
    m = mission(obstacles=(Obstacle(centre_ned_m=W0, radius_m=9.5),), apf=ApfConfig(obstacle_gain_mps2=0.0))
    assert check_mission(m) == []


def test_segment_gap_closed_form():
    a, b = TRACK
    assert segment_gap_m(a, b, np.array([25.0, 3.0, -30.0]), 2.0) == pytest.approx(1.0)  # beside the middle
    assert segment_gap_m(a, b, np.array([25.0, 1.0, -30.0]), 2.0) == pytest.approx(-1.0)  # through it
    assert segment_gap_m(a, b, np.array([60.0, 0.0, -30.0]), 5.0) == pytest.approx(5.0)  # past the end: to b
    assert segment_gap_m(a, a, np.array([3.0, 4.0, -30.0]), 1.0) == pytest.approx(4.0)  # a point


@pytest.mark.parametrize("centre, radius, margin, expected", [
    ((25.0, 1.0, -30.0), 2.0, 0.0, "passes through it"),
    ((25.0, 3.0, -30.0), 2.0, 1.5, "passes 1 m from its surface"),
    ((25.0, 3.0, -30.0), 2.0, 0.0, None),
    ((60.0, 0.0, -30.0), 5.0, 1.0, None),
])
def test_the_launch_track_through_or_near_an_obstacle(centre, radius, margin, expected):
    m = mission(obstacles=(Obstacle(centre_ned_m=centre, radius_m=radius),))
    found = check_mission(m, launch_track_ned_m=TRACK, obstacle_margin_m=margin)
    if expected is None:
        assert found == []
        return
    f = only(found)
    assert f.error and f.path == "mission.obstacles.0"
    assert f"the carrier's launch track (0, 0, -30) -> (50, 0, -30) {expected} (margin {margin:g} m)" in f.reason


# ---------------------------------------------------------------------------- ground
@pytest.mark.parametrize("z, error, phrase", [
    (5.0, True, "z = 5 m is 5 m below the ground"),
    (0.0, True, "z = 0 m is on the ground"),
    (-0.5, False, "would fly 0.5 m above the ground (under 1 m)"),
])
def test_a_waypoint_below_on_or_just_above_the_ground(z, error, phrase):
    f = only(check_mission(mission(waypoints=(W0, (100.0, 0.0, z)))))
    assert f.path == "mission.waypoints_ned_m.1" and f.error is error and phrase in f.reason


def test_one_metre_up_is_fine_and_no_ground_means_no_check():
    assert check_mission(mission(waypoints=(W0, (100.0, 0.0, -1.0)))) == []
    assert check_mission(mission(waypoints=(W0, (100.0, 0.0, 5.0)), ground_z_m=None)) == []


def test_the_ground_argument_overrides_the_missions():
    """Ground 20 m up (NED z -20): the assembly point 10 m up is 10 m under it."""
    found = check_mission(mission(), ground_z_m=-20.0)
    assert [(f.path, f.error) for f in found] == [("mission.waypoints_ned_m.0", True), ("mission.waypoints_ned_m.1", True)]
    assert "z = -10 m is 10 m below the ground (NED z -20 m" in found[0].reason


def test_a_release_point_underground():
    f = only(check_mission(mission(), launch_track_ned_m=(np.array([0.0, 0.0, 1.0]), TRACK[1])))
    assert f.error and f.path == "carrier" and "the first release point (0, 0, 1) is at or below the ground" in f.reason


# ---------------------------------------------------------------------------- range
def test_a_waypoint_a_million_kilometres_away():
    found = check_mission(mission(waypoints=(W0, (1.0e9, 0.0, -10.0))))
    f = found[0]
    assert f.error and f.path == "mission.waypoints_ned_m.1" and f.reason.startswith("1e+09 m from the mission origin")
    assert f"beyond {MAX_RANGE_M:.0f} m" in f.reason
    assert all(g.path != "mission.transit_speed_mps" for g in found)


def test_a_slot_beyond_the_range_although_its_waypoint_is_inside():
    """Waypoint 9995 m north, radius 10: UAV 1's slot is 10005 m out (9985 m north: 9995 m, inside)."""
    assert check_mission(mission(waypoints=(W0, (9985.0, 0.0, -10.0)))) == []
    f = only(check_mission(mission(waypoints=(W0, (9995.0, 0.0, -10.0)))))
    assert f.error and f.path == "mission.waypoints_ned_m.1"
    assert f.reason.startswith("the slot of UAV 1 (mission.formation.radius_m 10) is ")
    assert f.reason.endswith(" m from the mission origin, beyond 10000 m")


def test_an_absurd_formation_radius_is_out_of_range():
    """A radius of 1e300 m used to pass every check (the slot distances overflow to inf)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # overflow is a finding, not a RuntimeWarning ahead of the error
        found = check_mission(mission(radius_m=1.0e300))
    assert [f.path for f in found if f.error] == ["mission.waypoints_ned_m.0", "mission.waypoints_ned_m.1"]
    assert "radius_m 1e+300" in found[0].reason


def test_an_obstacle_or_a_release_point_out_of_range():
    far = (2.0e4, 0.0, -10.0)
    f = only(check_mission(mission(obstacles=(Obstacle(centre_ned_m=far, radius_m=1.0),))))
    assert f.error and f.path == "mission.obstacles.0.centre_ned_m" and "2e+04 m from the mission origin" in f.reason
    f = only(check_mission(mission(), launch_track_ned_m=(TRACK[0], np.array([2.0e4, 0.0, -30.0]))))
    assert f.error and f.path == "carrier" and "the last release point" in f.reason
    f = only(check_mission(mission(), launch_track_ned_m=(TRACK[0], np.array([math.inf, 0.0, -30.0]))))
    assert f.error and f.path == "carrier" and "inf m" in f.reason


# ---------------------------------------------------------------------------- geofence
def test_a_geofence_that_excludes_slots():
    fence = GeofenceConfig(min_ned_m=(-50.0, -50.0, -50.0), max_ned_m=(50.0, 50.0, 0.0))
    f = only(check_mission(mission(waypoints=(W0, (45.0, 0.0, -10.0)), geofence=fence)))
    assert f.error and f.path == "mission.waypoints_ned_m.1"
    assert f.reason == "1 formation slot(s) lie outside mission.geofence (e.g. UAV 1 at (55, 0, -10))"
    m = mission(waypoints=(W0, (40.0, 0.0, -10.0)), geofence=fence)  # UAV 1 at x = 50: on the face, inside
    assert check_mission(m, launch_track_ned_m=TRACK) == []  # the track ends at x = 50 too
    f = only(check_mission(m, launch_track_ned_m=(TRACK[0], np.array([60.0, 0.0, -30.0]))))
    assert f.error and f.path == "carrier"
    assert f.reason == "the last release point (60, 0, -30) lies outside mission.geofence"


# ---------------------------------------------------------------------------- spacing
@pytest.mark.parametrize("radius, separation, error", [(0.5, 1.0, True), (2.0, 1.0, False), (2.0, 3.0, True)])
def test_slots_closer_than_the_separation_or_inside_the_repulsion(radius, separation, error):
    f = only(check_mission(mission(radius_m=radius), separation_m=separation))
    assert f.path == "mission.formation.radius_m" and f.error is error
    assert re.search(rf"neighbouring slots \(UAVs \d and \d\) are {radius * math.sqrt(2):.3g} m apart", f.reason)
    assert ("closer than the separation" in f.reason) is error


def test_spacing_beyond_the_repulsion_or_without_gain_is_fine():
    assert check_mission(mission(radius_m=3.0)) == []  # 4.24 m apart, repulsion reaches 4 m
    assert check_mission(mission(radius_m=2.0, apf=ApfConfig(vehicle_gain_mps2=0.0))) == []
    assert check_mission(mission(n=1, radius_m=0.1)) == []


# ---------------------------------------------------------------------------- speeds and accelerations
def test_the_vehicles_limits_in_closed_form():
    vp = VehicleParams()
    tw = 4 * vp.thrust_coeff_n_per_radps2 * vp.rotor_speed_max_radps ** 2 / (vp.mass_kg * GRAVITY_MPS2)
    assert thrust_to_weight(vp) == pytest.approx(tw)
    # the Crazyflie's tilt limit (50 deg) binds before its thrust: g tan 50 deg = 11.7 m/s^2
    assert max_horizontal_accel_mps2(vp, InnerLoopConfig()) == pytest.approx(GRAVITY_MPS2 * math.tan(math.radians(50)))


def test_a_transit_of_a_million_metres_a_second():
    f = only(check_mission(mission(transit_speed_mps=1.0e6)))
    assert f.error and f.path == "mission.transit_speed_mps"
    assert f.reason == "1e+06 m/s is beyond what the autopilot flies (MPC_XY_VEL_MAX 12 m/s, MPC_Z_VEL_MAX_UP 3 m/s)"


@pytest.mark.parametrize("w0, w1, error", [
    ((0.0, 0.0, -10.0), (0.0, 0.0, -110.0), "the leg to waypoint 1 needs a climb speed of 5 m/s, beyond MPC_Z_VEL_MAX_UP 3 m/s"),
    ((0.0, 0.0, -10.0), (0.0, 0.0, -20.0), None),  # 10 m: the leg peaks at sqrt(10 * 0.5) = 2.24 m/s
    ((0.0, 0.0, -110.0), (0.0, 0.0, -100.0), "needs a descent speed of 2.24 m/s, beyond MPC_Z_VEL_MAX_DN 1.5 m/s"),
])
def test_a_leg_faster_than_the_autopilot_climbs_or_descends(w0, w1, error):
    found = check_mission(mission(waypoints=(w0, w1), transit_speed_mps=5.0, transit_accel_mps2=0.5))
    if error is None:
        assert found == []
    else:
        f = only(found)
        assert f.error and f.path == "mission.transit_speed_mps" and error in f.reason


def test_a_horizontal_leg_beyond_the_autopilots_horizontal_limit():
    lim = SetpointLimits(xy_vel_max_mps=2.0, z_vel_max_up_mps=5.0)
    found = check_mission(mission(transit_speed_mps=4.0), limits=lim)
    f = [g for g in found if g.path == "mission.transit_speed_mps"]
    assert only(f).error and "needs a horizontal speed of 4 m/s, beyond MPC_XY_VEL_MAX 2 m/s" in f[0].reason


@pytest.mark.parametrize("accel, error", [(12.0, True), (5.0, False), (3.0, None)])
def test_transit_acceleration_beyond_the_vehicle_or_the_consensus_limit(accel, error):
    found = check_mission(mission(transit_accel_mps2=accel))
    if error is None:
        assert found == []
        return
    f = only(found)
    assert f.path == "mission.transit_accel_mps2" and f.error is error
    assert ("beyond the vehicle's 11.7 m/s^2" in f.reason) is error


@pytest.mark.parametrize("kw, path", [
    ({"total_accel_max_mps2": 12.0}, "mission.total_accel_max_mps2"),
    ({"formation_error_max_m": 40.0}, "mission.formation_error_max_m"),  # 0.6 / 1.6 * 40 = 15 m/s
    ({"phases": PhaseConfig(land_after_hover_s=10.0, land_speed_mps=2.0)}, "mission.phases.land_speed_mps"),
])
def test_warnings_about_limits_the_autopilot_or_inner_loop_clamps(kw, path):
    f = only(check_mission(mission(**kw)))
    assert f.path == path and not f.error


def _slot_error_response(gains: ConsensusGains, t_end_s: float, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """e'' = k2_vel e' + k2_pos e from e = 1 m at rest, by RK4 (eq. 27 about the slot, one axis)."""
    def f(x):
        return np.array([x[1], gains.k2_vel_per_s * x[1] + gains.k2_pos_per_s2 * x[0]])

    n = int(round(t_end_s / dt))
    x, out = np.array([1.0, 0.0]), np.empty(n + 1)
    out[0] = 1.0
    for i in range(n):
        k1 = f(x)
        k2 = f(x + dt / 2 * k1)
        k3 = f(x + dt / 2 * k2)
        k4 = f(x + dt * k3)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out[i + 1] = x[0]
    return np.linspace(0.0, n * dt, n + 1), out


@pytest.mark.parametrize("gains", [ConsensusGains(), ConsensusGains(k2_pos_per_s2=-1.0, k2_vel_per_s=-2.0),
                                   ConsensusGains(k2_pos_per_s2=-2.0, k2_vel_per_s=-1.0)],
                         ids=["default (real poles)", "double pole", "complex poles"])
def test_the_settling_time_is_the_last_crossing_of_the_slot_loops_step_response(gains):
    from companion.feasibility import settling_time_s

    settle = settling_time_s(gains, 0.05)
    t, e = _slot_error_response(gains, settle + 10.0)
    last = t[np.flatnonzero(np.abs(e) >= 0.05)[-1]]
    assert settle == pytest.approx(last, abs=0.01)


def test_a_landing_hover_shorter_than_the_settling_time_is_a_warning_with_the_numbers():
    """Default gains: s^2 + 1.6 s + 0.6, poles -0.6 and -1 /s; from 1 m at rest the error is
    2.5 e^-0.6t - 1.5 e^-t, 0.05 m at 6.44 s (ln(2.5 x 20) / 0.6 = 6.5 s from the slow mode
    alone). small_6 with a 5 s hover ended 0.115 m off: the response says 0.114 m."""
    f = only(check_mission(mission(phases=PhaseConfig(land_after_hover_s=5.0))))
    assert f.path == "mission.phases.land_after_hover_s" and not f.error
    for text in ("5 s of hover", "about 6.4 s", "within 0.05 m", "s^2 + 1.6 s + 0.6", "k2_vel_per_s -1.6",
                 "k2_pos_per_s2 -0.6", "poles -0.6 and -1 /s", "hover at least 7 s"):
        assert text in f.reason, (text, f.reason)
    assert 2.5 * math.exp(-0.6 * 5.0) - 1.5 * math.exp(-5.0) == pytest.approx(0.114, abs=5e-4)
    assert check_mission(mission(phases=PhaseConfig(land_after_hover_s=10.0))) == []
    assert check_mission(mission(phases=PhaseConfig(land_after_hover_s=6.5))) == []
    assert check_mission(mission()) == []  # no landing, no hover check
    stiffer = ConsensusGains(k2_pos_per_s2=-2.4, k2_vel_per_s=-3.2)  # poles -1.2, -2: half the time
    assert check_mission(mission(phases=PhaseConfig(land_after_hover_s=5.0), consensus=stiffer)) == []


def test_a_vehicle_that_cannot_lift_itself():
    f = only(check_mission(mission(), VehicleParams(mass_kg=1.0)))
    assert f.error and f.path == "vehicle" and f.reason.startswith("thrust-to-weight 0.0586")


def test_unstable_consensus_gains():
    f = only(check_mission(mission(consensus=ConsensusGains(k2_pos_per_s2=0.6))))
    assert f.error and f.path == "mission.consensus" and "unstable" in f.reason


def test_errors_come_first():
    m = mission(radius_m=2.0, transit_speed_mps=1.0e6)  # a spacing warning, a speed error
    found = check_mission(m)
    assert [f.error for f in found] == [True, False]


# ---------------------------------------------------------------------------- vehicle count limits
def test_more_vehicles_than_mavlink_system_ids():
    assert MAVLINK_MAX_VEHICLES == 250
    f = only(check_mission(MissionConfig(n_vehicles=251), max_vehicles=MAVLINK_MAX_VEHICLES))
    assert f.error and f.path == "mission.n_vehicles" and "at most 250" in f.reason
    found = check_mission(MissionConfig(n_vehicles=250, formation=FormationConfig(radius_m=400.0)),
                          max_vehicles=MAVLINK_MAX_VEHICLES)
    assert all(f.path != "mission.n_vehicles" for f in found)


def scenario(**mission_kw) -> ScenarioConfig:
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["mission"].update(mission_kw)
    return validate(ScenarioConfig, data, "small_6")


@pytest.mark.parametrize("n, runner, command, limit", [
    (HEADLESS_MAX_VEHICLES + 1, "headless", "simulate", 1000),
    (MAVLINK_MAX_VEHICLES + 1, "sitl", "sitl", 250),
    (MAVLINK_MAX_VEHICLES + 1, "fleet", "run", 250),
])
def test_each_runner_refuses_more_vehicles_than_it_flies(n, runner, command, limit):
    f = only(scenario_findings(scenario(n_vehicles=n), runner))  # (nothing else is checked)
    assert f.error and f.path == "mission.n_vehicles"
    assert f.reason.startswith(f"{n} vehicles: `swarmdrop {command}` flies at most {limit}")


@pytest.mark.parametrize("n, runner", [(HEADLESS_MAX_VEHICLES, "headless"), (MAVLINK_MAX_VEHICLES, "sitl"),
                                       (MAVLINK_MAX_VEHICLES, "fleet"), (MAVLINK_MAX_VEHICLES + 1, "headless")])
def test_at_the_limit_the_count_is_not_refused(n, runner):
    found = scenario_findings(scenario(n_vehicles=n, formation={"radius_m": 400.0}), runner)
    assert all(f.path != "mission.n_vehicles" for f in found), found


# ---------------------------------------------------------------------------- scenario-only checks
def test_scenario_passes_its_ground_separation_margin_and_launch_track():
    """small_6's carrier flies (0, 0, -20) -> (25, 0, -20); safety.obstacle_margin_m is 1."""
    f = only(scenario_findings(scenario(obstacles=[{"centre_ned_m": [3.0, 3.0, -20.0], "radius_m": 2.5}])))
    assert f.error and f.path == "mission.obstacles.0" and "passes 0.5 m from its surface (margin 1 m)" in f.reason


def test_a_recording_too_large_for_memory():
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["duration_s"] = 86_400.0  # 4.32e6 samples x (6 x 150 + 1000) bytes = 8.2 GB
    found = scenario_findings(validate(ScenarioConfig, data))
    f = only([g for g in found if "GB of memory" in g.reason])
    assert f.error and f.path == "duration_s" and "need 8.21 GB of memory, more than 2 GB" in f.reason


def test_a_duration_too_short_for_the_mission():
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["duration_s"] = 20.0
    f = only(scenario_findings(validate(ScenarioConfig, data)))
    assert f.error and f.path == "duration_s" and f.reason.startswith("the mission cannot end within 20 s")


def test_landing_without_ground():
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["physics"] = {"ground_z_m": None}
    data["mission"]["phases"] = {"land_after_hover_s": 10.0}  # (long enough to settle: no hover warning)
    f = only(scenario_findings(validate(ScenarioConfig, data)))
    assert f.error and f.path == "mission.phases.land_after_hover_s" and "descend for ever" in f.reason


def test_a_radio_range_shorter_than_the_neighbour_distance():
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["link"] = {"range_m": 5.0}
    f = only(scenario_findings(validate(ScenarioConfig, data)))
    assert f.error and f.path == "link.range_m" and "would never hear it" in f.reason


def test_a_release_faster_than_the_autopilot_flies_is_a_warning():
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["carrier"]["vel_ned_mps"] = [13.0, 0.0, 0.0]
    f = only(scenario_findings(validate(ScenarioConfig, data)))
    assert not f.error and f.path == "carrier.vel_ned_mps" and "released at 13 m/s" in f.reason


# ---------------------------------------------------------------------------- check_findings, --strict
ERR = Finding("mission.n_vehicles", "too many")
WARN = Finding("mission.transit_accel_mps2", "a bit much", error=False)


def test_finding_text_and_errors_of():
    assert str(ERR) == "mission.n_vehicles: too many"
    assert errors_of([ERR, WARN]) == [ERR]
    assert errors_of([ERR, WARN], strict=True) == [ERR, WARN]


def test_check_findings_raises_on_errors_and_passes_warnings_on():
    warned: list[str] = []
    with pytest.raises(ConfigError) as e:
        check_findings([ERR, WARN], "m.yaml", warn=warned.append)
    assert str(e.value) == ("m.yaml: the mission cannot be flown as configured (1 problem(s)):\n"
                            "  mission.n_vehicles: too many")
    check_findings([WARN], "m.yaml", warn=warned.append)
    assert warned == ["m.yaml: mission.transit_accel_mps2: a bit much (a warning; --strict makes it an error)"]
    check_findings([WARN], "m.yaml")  # no warn: dropped
    check_findings([], "m.yaml", strict=True)


def test_strict_makes_warnings_errors():
    warned: list[str] = []
    with pytest.raises(ConfigError) as e:
        check_findings([WARN], "m.yaml", strict=True, warn=warned.append)
    assert str(e.value) == ("m.yaml: the mission cannot be flown as configured (1 problem(s)):\n"
                            "  mission.transit_accel_mps2: a bit much (a warning; --strict makes it an error)")
    assert warned == []
    with pytest.raises(ConfigError, match=r"\(2 problem\(s\)\)"):
        check_findings([ERR, WARN], "m.yaml", strict=True)


def test_strict_on_a_real_warning():
    found = check_mission(mission(transit_accel_mps2=5.0))
    check_findings(found, "m")
    with pytest.raises(ConfigError, match="mission.transit_accel_mps2: 5 m/s"):
        check_findings(found, "m", strict=True)


def test_the_fleet_needs_a_geodetic_origin_the_headless_runner_does_not():
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    del data["mission"]["origin"]
    cfg = validate(ScenarioConfig, data)
    assert scenario_findings(cfg, "headless") == []
    f = only(scenario_findings(cfg, "fleet"))
    assert f.error and f.path == "mission.origin"
