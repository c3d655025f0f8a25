"""Runs flown side by side (headless.run_batch) give each run's result to the last bit,
and the pieces that make batching cheap keep their contracts."""
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.control.formation import consensus_rows
from companion.control.geometric import N_SP, pack_setpoint
from companion.params import InnerLoopConfig, VehicleParams
from companion.state import FleetSetpoint
from sim_bridge.runs.headless import run_batch, run_scenario
from sim_bridge.runs.sweep import plan_batches
from sim_bridge.scenario import load_scenario
from sim_bridge.world.physics import Physics, hover_state
from sim_bridge.world.transport import AgeHistogram

ROOT = Path(__file__).resolve().parents[1]

DISTURBED = """
vehicle: {drag_coeff_n_per_mps: 0.0065}
physics:
  wind: {steady_ned_mps: [0.0, 1.0, 0.0], gust_std_mps: 2.0, gust_tau_s: 2.0}
estimator: {pos_noise_std_m: 0.3, pos_noise_std_vertical_m: 0.5, pos_noise_tau_s: 2.0, latency_s: 0.05}
link: {kind: lossy, loss: 0.1, delay_s: 0.1, jitter_s: 0.02}
faults: {random_rotor_failures: 1, random_window_s: [15.0, 25.0]}
"""


@pytest.fixture(scope="module")
def disturbed_small(tmp_path_factory) -> Path:
    """small_6 in a disturbed world: gusts through drag, GPS error and latency, a lossy
    jittery link and one random rotor failure, so that every per-run stream is exercised."""
    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["completion_tol_m"] = 3.0
    extra = yaml.safe_load(DISTURBED)
    extra["estimator"] = {**data.get("estimator", {}), **extra["estimator"]}  # the shipped bias stays
    data.update(extra)
    path = tmp_path_factory.mktemp("cfg") / "small_6_disturbed.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _same(a, b) -> None:
    assert a.log.keys() == b.log.keys()
    for k in a.log:
        np.testing.assert_array_equal(a.log[k], b.log[k], err_msg=k)
    np.testing.assert_array_equal(a.phase_entry_s, b.phase_entry_s)
    np.testing.assert_array_equal(a.failed_at_s, b.failed_at_s)
    assert (a.t_complete_s, a.t_go_s, a.sim_s, a.vehicle_steps) == (b.t_complete_s, b.t_go_s, b.sim_s, b.vehicle_steps)
    assert a.safety.to_json() == b.safety.to_json()
    assert a.link == b.link


def test_each_run_of_a_batch_is_the_run_alone(disturbed_small):
    seeds = (11, 12, 13)
    batch = run_batch([load_scenario(disturbed_small, s) for s in seeds])
    alone = [run_scenario(load_scenario(disturbed_small, s), progress=False) for s in seeds]
    for b, a in zip(batch, alone):
        _same(b, a)
    assert not np.isnan(batch[0].failed_at_s).all()  # the fault did fire
    assert batch[0].link.copies_delivered != batch[1].link.copies_delivered  # and the seeds differ


def test_a_batch_refuses_scenarios_that_differ_beyond_the_seed():
    cfg = load_scenario(ROOT / "configs" / "small_6.yaml")
    other = dataclasses.replace(cfg, seed=8, completion_tol_m=0.5)
    with pytest.raises(ValueError, match="seed only"):
        run_batch([cfg, other])
    with pytest.raises(ValueError, match="at least one"):
        run_batch([])


@pytest.mark.parametrize("n_seeds,workers,max_batch", [(100, 2, 10), (101, 2, 10), (7, 2, 10), (3, 4, 10),
                                                       (25, 3, 4), (1, 1, 10)])
def test_batches_cover_the_seeds_in_order_and_share_out_evenly(n_seeds, workers, max_batch):
    seeds = list(range(50, 50 + n_seeds))
    batches = plan_batches(seeds, workers, max_batch)
    assert [s for b in batches for s in b] == seeds
    sizes = [len(b) for b in batches]
    assert max(sizes) <= max_batch and max(sizes) - min(sizes) <= 1 and min(sizes) >= 1
    if n_seeds >= workers:
        assert len(batches) % workers == 0
    with pytest.raises(ValueError):
        plan_batches(seeds, 0)


def test_consensus_rows_poisons_only_the_row_that_read_a_bad_value():
    n = 4
    rng = np.random.default_rng(3)
    pos, vel = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    W = np.ones((n, n)) - np.eye(n)
    nbr = np.array([[j for j in range(n) if j != i] for i in range(n)])
    h = rng.normal(size=(2, n, 3))
    ids = np.arange(n)
    nb_pos = np.broadcast_to(pos, (n, n, 3)).copy()
    nb_pos[2, 0] = np.inf  # row 2 heard a hostile state of vehicle 0
    usable = np.ones((n, n), bool)
    sel = np.array([0, 1, 1, 0])  # rows fly two references
    k = np.array([-1.0, -2.0, -0.5, -0.5, 0.3, 0.3])
    out = np.empty((n, 3))
    bad = consensus_rows(pos, vel, ids, nb_pos, np.broadcast_to(vel, (n, n, 3)), usable, h, h * 0.1, h * 0.01, sel,
                         W, nbr, k, math.inf, out, np.empty((n, 3)))
    assert bad == 0 and np.isnan(out[2]).all() and np.isfinite(np.delete(out, 2, axis=0)).all()
    for r in (0, 1, 3):  # each good row is what it is computed alone, on its own reference
        one = np.empty((1, 3))
        g = sel[r]
        consensus_rows(pos[r:r + 1], vel[r:r + 1], ids[r:r + 1], nb_pos[r:r + 1], np.broadcast_to(vel, (1, n, 3)),
                       usable[r:r + 1], h[g:g + 1], h[g:g + 1] * 0.1, h[g:g + 1] * 0.01, np.zeros(1, np.int64), W, nbr,
                       k, math.inf, one, np.empty((1, 3)))
        np.testing.assert_array_equal(one[0], out[r])


def test_physics_takes_a_packed_setpoint_as_the_same_setpoint():
    vp = VehicleParams()
    sp = FleetSetpoint.empty(3)
    sp.pos_ned_m[:] = [[1.0, 0.0, -1.0], [0.0, 2.0, 0.0], [0.5, 0.5, 0.5]]
    sp.yaw_rad[:] = 0.3
    assert pack_setpoint(sp).shape == (3, N_SP)
    a, b = hover_state(3, vp), hover_state(3, vp)
    Physics(vp, InnerLoopConfig()).step(a, sp, 50)
    Physics(vp, InnerLoopConfig()).step(b, pack_setpoint(sp)[[0, 1, 2]], 50)  # a copy, not the block itself
    np.testing.assert_array_equal(a.pos_ned_m, b.pos_ned_m)
    np.testing.assert_array_equal(a.rot_body_to_ned, b.rot_body_to_ned)
    with pytest.raises(ValueError, match="packed setpoint"):
        Physics(vp, InnerLoopConfig()).step(b, np.zeros((2, N_SP)), 1)


def test_age_histogram_small_path_bins_as_the_vector_path():
    rng = np.random.default_rng(5)
    small, big = AgeHistogram(), AgeHistogram()
    ages = np.concatenate([rng.uniform(-0.5, 12.0, 300), rng.integers(0, 500, 200) * 0.02, [9.9999999, 10.0, 0.0]])
    for chunk in np.array_split(ages, 60):  # <= 64 each: the Python loop
        small.add(chunk, 3)
    big.add(np.tile(ages, 3))  # one call over 64: ufunc.at
    np.testing.assert_array_equal(small.counts, big.counts)
    a, b = small.summary(), big.summary()
    assert (a.count, a.p50, a.p90, a.p99, a.max) == (b.count, b.p50, b.p90, b.p99, b.max)
