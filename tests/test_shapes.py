"""Formation shapes (companion/control/shapes.py): geometry, units, rotation, and the circle
that flies today reproduced bit for bit."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control.shapes import (
    SHAPES,
    WEDGE_HALF_ANGLE_DEG,
    FormationSpec,
    min_separation_m,
    offsets_for,
    spec_from_config,
)
from companion.mission import FormationConfig, MissionConfig, formation_offsets_ned_m


@pytest.mark.parametrize("order", ["sequential", "interleaved"])
@pytest.mark.parametrize("n", [1, 2, 3, 5, 6, 7, 39, 40, 41, 250])
def test_circle_reproduces_the_mission_offsets_bit_for_bit(order, n):
    for radius in (40.0, 12.345, 3.0):
        cfg = FormationConfig(radius_m=radius, slot_order=order)
        assert np.array_equal(offsets_for(spec_from_config(cfg), n), formation_offsets_ned_m(cfg, n))


def test_spec_from_the_default_mission_config():
    spec = spec_from_config(MissionConfig().formation)
    assert spec == FormationSpec("circle", radius_m=40.0, rotation_rad=0.0, slot_order="interleaved")


def _turned(p: np.ndarray, rot: float) -> np.ndarray:
    c, s = math.cos(rot), math.sin(rot)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return p @ r.T


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("order", ["sequential", "interleaved"])
def test_rotation_turns_every_shape_about_the_vertical(shape, order):
    for n in (1, 4, 9, 17):
        base = FormationSpec(shape, radius_m=10.0, spacing_m=3.0, slot_order=order if shape == "circle" else "sequential")
        for rot in (0.3, -2.0, math.pi / 2):
            turned = offsets_for(FormationSpec(shape, 10.0, 3.0, rot, base.slot_order), n)
            np.testing.assert_allclose(turned, _turned(offsets_for(base, n), rot), atol=1e-12)


def test_rotation_is_a_bearing_clockwise_from_north():
    """rotation pi/2: the forward axis points east, so a line (across) runs north-south."""
    line = offsets_for(FormationSpec("line", spacing_m=2.0, rotation_rad=math.pi / 2), 3)
    np.testing.assert_allclose(line, [[2.0, 0, 0], [0, 0, 0], [-2.0, 0, 0]], atol=1e-12)
    wedge = offsets_for(FormationSpec("wedge", spacing_m=2.0, rotation_rad=math.pi / 2), 3)
    assert np.argmax(wedge[:, 1]) == 0  # the apex is the most easterly slot


def test_line_runs_across_the_direction_of_travel_centred():
    p = offsets_for(FormationSpec("line", spacing_m=2.5), 5)
    np.testing.assert_allclose(p[:, 0], 0.0)
    np.testing.assert_allclose(p[:, 1], [-5.0, -2.5, 0.0, 2.5, 5.0])
    np.testing.assert_allclose(p[:, 2], 0.0)


@pytest.mark.parametrize("n", range(1, 31))
def test_grid_is_square_centred_and_spaced(n):
    s = 4.0
    p = offsets_for(FormationSpec("grid", spacing_m=s), n)
    cols = math.ceil(math.sqrt(n))
    np.testing.assert_allclose(p.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(p[:, 2], 0.0)
    assert len(np.unique(np.round(p[:, 1], 9))) <= cols + (cols - 1)  # full rows and a centred partial row
    assert len(np.unique(np.round(p[:, 0], 9))) == math.ceil(n / cols)
    if n > 1:
        assert min_separation_m(p) == pytest.approx(s)
    # rows are front to back: slot 0 is in the front row
    assert p[0, 0] == pytest.approx(p[:, 0].max())


def test_grid_of_nine_is_three_by_three():
    p = offsets_for(FormationSpec("grid", spacing_m=1.0), 9)
    np.testing.assert_allclose(sorted(set(np.round(p[:, 0], 12))), [-1.0, 0.0, 1.0])
    np.testing.assert_allclose(sorted(set(np.round(p[:, 1], 12))), [-1.0, 0.0, 1.0])


@pytest.mark.parametrize("n", [1, 2, 3, 8, 9, 40])
def test_wedge_has_its_apex_forward_and_spaced_arms(n):
    s = 3.0
    p = offsets_for(FormationSpec("wedge", spacing_m=s), n)
    np.testing.assert_allclose(p.mean(axis=0), 0.0, atol=1e-12)
    assert np.argmax(p[:, 0]) == 0  # apex forward (north at rotation 0)
    d = p - p[0]
    half = math.radians(WEDGE_HALF_ANGLE_DEG)
    for k in range(1, n):
        j = (k + 1) // 2
        assert np.linalg.norm(d[k]) == pytest.approx(j * s)  # spacing along the arm
        assert math.atan2(abs(d[k, 1]), -d[k, 0]) == pytest.approx(half)  # arm angle off the backward axis
        assert np.sign(d[k, 1]) == (-1 if k % 2 else 1)  # odd slots left (west), even right
    if n > 1:
        assert min_separation_m(p) == pytest.approx(s)


@pytest.mark.parametrize("n", [1, 2, 12, 40, 100])
def test_shell_spreads_points_evenly_on_a_sphere(n):
    r = 10.0
    p = offsets_for(FormationSpec("shell", radius_m=r), n)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), r)
    if n >= 12:
        # Fibonacci lattice: nearest neighbours at about sqrt(4 pi / n) r (the area per point)
        ideal = r * math.sqrt(4 * math.pi / n)
        assert min_separation_m(p) > 0.7 * ideal
        np.testing.assert_allclose(p.mean(axis=0), 0.0, atol=0.05 * r)
        assert p[0, 2] == p[:, 2].min()  # slot 0 at the top (most negative z: up)
        assert np.all(np.diff(p[:, 2]) > 0)  # heights go down with k


def test_circle_spacing():
    p = offsets_for(FormationSpec("circle", radius_m=40.0), 40)
    assert min_separation_m(p) == pytest.approx(2 * 40.0 * math.sin(math.pi / 40))
    np.testing.assert_allclose(np.hypot(p[:, 0], p[:, 1]), 40.0)


def test_zero_slots_and_bad_specs():
    assert offsets_for(FormationSpec("grid"), 0).shape == (0, 3)
    with pytest.raises(ValueError):
        offsets_for(FormationSpec(), -1)
    for bad in (dict(shape="hexagon"), dict(radius_m=0.0), dict(spacing_m=-1.0), dict(radius_m=math.nan),
                dict(rotation_rad=math.inf), dict(slot_order="random")):
        with pytest.raises(ValueError):
            FormationSpec(**bad)  # type: ignore[arg-type]


def test_size_is_the_dimension_the_shape_uses():
    assert FormationSpec("shell", radius_m=7.0, spacing_m=2.0).size_m == 7.0
    assert FormationSpec("wedge", radius_m=7.0, spacing_m=2.0).size_m == 2.0


# ----------------------------------------------------------------------------- shapes in the mission
@pytest.mark.parametrize("shape", SHAPES)
def test_the_mission_flies_the_configured_shape(shape):
    """mission.formation.shape is honoured (before: every formation was a circle): vehicle i
    takes slot i of offsets_for; the default circle is unchanged bit for bit."""
    from companion.mission import Mission

    cfg = FormationConfig(shape=shape, radius_m=12.0, spacing_m=3.0, rotation_deg=30.0)
    m = Mission(MissionConfig(n_vehicles=9, formation=cfg, waypoints_ned_m=((0.0, 0.0, -30.0),)))
    want = offsets_for(FormationSpec(shape, 12.0, 3.0, math.radians(30.0),
                                     "interleaved" if shape == "circle" else "sequential"), 9)
    np.testing.assert_array_equal(m.offsets_ned_m, want)
    plain = Mission(MissionConfig())
    assert np.array_equal(plain.offsets_ned_m, formation_offsets_ned_m(FormationConfig(), 40))


def test_feasibility_checks_the_shape():
    """companion.feasibility on shapes: slots closer than the separation (named by the size
    that sets them), a shell whose bottom is underground, slots outside the geofence."""
    from companion.feasibility import check_mission
    from companion.mission import GeofenceConfig

    def errors(**formation):
        mc = MissionConfig(n_vehicles=16, formation=FormationConfig(**formation), waypoints_ned_m=((0.0, 0.0, -10.0),),
                           geofence=GeofenceConfig(min_ned_m=(-30.0, -30.0, -60.0), max_ned_m=(30.0, 30.0, 0.0)))
        return [str(f) for f in check_mission(mc) if f.error]

    assert errors(shape="grid", spacing_m=3.0) == []
    assert any("mission.formation.spacing_m" in e and "0.8 m apart" in e for e in errors(shape="wedge", spacing_m=0.8))
    assert any("lowest slot would be 1.25 m below the ground" in e  # (Fibonacci: its bottom is r (1 - 1/n) down)
               for e in errors(shape="shell", radius_m=12.0))
    assert errors(shape="shell", radius_m=8.0) == []
    assert any("outside mission.geofence" in e for e in errors(shape="line", spacing_m=5.0))  # 75 m wide
