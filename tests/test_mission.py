"""Mission model: formation slots and the formation-centre path c(t)."""
import numpy as np
import pytest

from companion.mission import CentrePath, FormationConfig, formation_offsets_ned_m


@pytest.mark.parametrize("order", ["sequential", "interleaved"])
@pytest.mark.parametrize("n", [1, 2, 6, 7, 40])
def test_circle_slots_on_radius_and_distinct(order, n):
    r = formation_offsets_ned_m(FormationConfig(radius_m=40.0, slot_order=order), n)
    assert r.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(r[:, :2], axis=1), 40.0)
    np.testing.assert_allclose(r[:, 2], 0.0)
    if n > 1:
        d = np.linalg.norm(r[:, None] - r[None], axis=2) + np.eye(n) * 1e9
        # evenly spaced on the circle (odd n interleaved: within a factor 2)
        chord = 2 * 40.0 * np.sin(np.pi / n)
        assert d.min() > 0.49 * chord


def test_interleaved_slots_run_south_to_north_alternating_sides():
    r = formation_offsets_ned_m(FormationConfig(radius_m=40.0, slot_order="interleaved"), 40)
    assert np.all(np.diff(r[0::2, 0]) > 0) and np.all(np.diff(r[1::2, 0]) > 0)
    assert np.all(r[0::2, 1] < 0) and np.all(r[1::2, 1] > 0)


def _path():
    wps = np.array([[100.0, 0, -10], [150, 150, -70], [250, 250, -170]])
    return CentrePath(wps, v_max_mps=3.0, a_max_mps2=0.5, dwell_s=2.0)


def test_path_limits_and_derivatives():
    p = _path()
    t = np.arange(-1.0, p.duration_s + 5.0, 0.01)
    c = np.array([p.at(x)[0] for x in t])
    v = np.array([p.at(x)[1] for x in t])
    a = np.array([p.at(x)[2] for x in t])
    assert np.linalg.norm(v, axis=1).max() <= 3.0 + 1e-9
    assert np.linalg.norm(a, axis=1).max() <= 0.5 + 1e-9
    # c' is the derivative of c and c'' of c' (central differences, away from kinks)
    np.testing.assert_allclose(np.gradient(c, t, axis=0)[1:-1], v[1:-1], atol=0.01)
    dv = np.gradient(v, t, axis=0)
    smooth = np.linalg.norm(a[2:] - a[:-2], axis=1) < 1e-12
    np.testing.assert_allclose(dv[1:-1][smooth], a[1:-1][smooth], atol=1e-6)
    np.testing.assert_allclose(c[0], [100, 0, -10])
    np.testing.assert_allclose(c[-1], [250, 250, -170], atol=1e-9)


def test_path_duration_closed_form():
    # leg 1: 169.12 m, leg 2: 173.2 m; v=3, a=0.5 -> t_acc = 6 s, cruise = (D - 18)/3
    p = _path()
    d1, d2 = np.linalg.norm([50, 150, 60]), np.linalg.norm([100, 100, 100])
    expected = sum(12.0 + (d - 18.0) / 3.0 + 2.0 for d in (d1, d2))
    assert p.duration_s == pytest.approx(expected)


def test_short_leg_is_triangular():
    p = CentrePath(np.array([[0.0, 0, 0], [2.0, 0, 0]]), 3.0, 0.5, 0.0)
    # v_peak = sqrt(D a) = 1 m/s < 3, duration = 2 * v_peak / a = 4 s
    assert p.duration_s == pytest.approx(4.0)
    assert p.at(2.0)[1][0] == pytest.approx(1.0)
