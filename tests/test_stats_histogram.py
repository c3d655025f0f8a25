"""The agent's duration statistics: counted in a histogram as they come (O(1) per tick, O(bins)
per statistics write however long the flight), summarised conservatively, and pooled by the
fleet with the same rule."""
import numpy as np
import pytest

from companion.node.stats import FINE_BIN_US, FINE_BINS, LAT_BIN_US, LAT_BINS, DurationHistogram, histogram_percentiles
from sim_bridge.runs.fleet_report import pooled_percentiles


def _durations(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).gamma(2.0, 1e-4, n)  # s: a 0.2 ms mean, a long tail


def test_percentiles_are_the_upper_edge_of_the_bin_holding_the_exact_value():
    d = _durations(1, 50_000)
    h = DurationHistogram()
    for x in d.tolist():
        h.add(x)
    assert h.n == len(d) and h.max_s == d.max()
    exact_ms = np.percentile(d, (50, 90, 99), method="inverted_cdf") * 1e3
    got_ms = np.array(h.percentiles_ms((50, 90, 99)))
    assert np.all(got_ms >= exact_ms) and np.all(got_ms - exact_ms <= FINE_BIN_US / 1000.0 + 1e-12)
    # an upper bin edge, exactly
    np.testing.assert_allclose(got_ms / (FINE_BIN_US / 1000.0), np.round(got_ms / (FINE_BIN_US / 1000.0)), atol=1e-9)


def test_the_files_histogram_is_the_fine_one_summed_and_the_tail_lands_in_the_last_bin():
    d = np.concatenate([_durations(2, 20_000), [0.2, 1.5, -1e-6]])  # beyond 50 ms, and a clock step back
    h = DurationHistogram()
    for x in d.tolist():
        h.add(x)
    coarse = h.coarse(LAT_BIN_US, LAT_BINS)
    expect = np.bincount(np.clip((d * 1e6 / LAT_BIN_US).astype(int), 0, LAT_BINS - 1), minlength=LAT_BINS)
    assert coarse == tuple(expect.tolist()) and sum(coarse) == len(d)
    assert h.counts[FINE_BINS - 1] >= 2 and h.counts[0] >= 1


def test_the_fleet_pools_with_the_same_rule():
    hs = []
    for seed in (3, 4):
        h = DurationHistogram()
        for x in _durations(seed, 10_000).tolist():
            h.add(x)
        hs.append({"bin_us": LAT_BIN_US, "counts": list(h.coarse(LAT_BIN_US, LAT_BINS))})
    pooled = pooled_percentiles(hs + [None, {}], (50, 99, 99.9))
    both = np.concatenate([_durations(3, 10_000), _durations(4, 10_000)])
    for p in (50, 99, 99.9):
        exact = np.percentile(both, p, method="inverted_cdf") * 1e3
        assert exact <= pooled[f"p{p:g}"] <= exact + LAT_BIN_US / 1000.0 + 1e-12
    assert pooled_percentiles([None, {}], (50,)) == {}


def test_nothing_counted_has_no_percentiles():
    assert DurationHistogram().percentiles_ms((50, 99)) == []
    assert histogram_percentiles([0, 0, 0], 10, (50,)) == []
    assert histogram_percentiles([], 10, (50,)) == []
    with pytest.raises(ValueError):
        DurationHistogram().coarse(15, 10)  # not a multiple of the fine bin
    with pytest.raises(ValueError):
        DurationHistogram().coarse(50, 2000)  # past 50 ms


def test_no_percentile_above_the_largest_and_a_stall_past_the_bins_is_reported_as_it_was():
    h = DurationHistogram()
    h.add(0.2053e-3)  # one sample: every percentile is it, not its bin's upper edge
    assert h.percentiles_ms((50, 99)) == [pytest.approx(0.2053), pytest.approx(0.2053)]
    h = DurationHistogram()
    for _ in range(999):
        h.add(0.1e-3)
    h.add(1.5)  # a 1.5 s stall, past the last bin's lower edge (50 ms)
    p50, p99, p_top = h.percentiles_ms((50, 99, 99.95))
    assert p50 == pytest.approx(0.11) and p99 == pytest.approx(0.11)
    assert p_top == pytest.approx(1500.0)  # the stall itself, not the 50 ms edge
    with pytest.raises(ValueError):
        h.coarse(50, 0)
