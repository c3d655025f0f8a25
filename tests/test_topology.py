"""Topology builders and Laplacians (companion/control/topology.py)."""
import numpy as np
import pytest

from companion.control import topology as T

BUILDERS = {
    "chain": T.chain,
    "ring": T.ring,
    "complete": T.complete,
    "k_nearest": lambda n, w=1.0: T.k_nearest(np.random.default_rng(1).normal(size=(n, 3)) * 10, 3, w),
}


@pytest.mark.parametrize("name", BUILDERS)
@pytest.mark.parametrize("n", [1, 2, 3, 7, 40])
def test_builders_shape_zero_diagonal_row_sums(name, n):
    W = BUILDERS[name](n, 0.5)
    assert W.shape == (n, n)
    assert np.all(np.diag(W) == 0)
    assert np.all(W >= 0)
    L = T.laplacian(W)
    np.testing.assert_allclose(L.sum(axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.diag(L), W.sum(axis=1))


def test_chain_structure_and_neighbours():
    W = T.chain(6, 2.0)
    assert W[0].sum() == 0  # vehicle 0 hears nobody
    for i in range(1, 6):
        assert W[i, i - 1] == 2.0 and W[i].sum() == 2.0
        np.testing.assert_array_equal(T.neighbours(W, i), [i - 1])
    assert T.neighbours(W, 0).size == 0


def test_ring_small_cases():
    np.testing.assert_array_equal(T.ring(1), [[0.0]])
    np.testing.assert_array_equal(T.ring(2), [[0, 1], [1, 0]])  # single link, not doubled
    W = T.ring(5)
    assert np.array_equal(W, W.T)
    np.testing.assert_array_equal(T.neighbours(W, 0), [1, 4])


def test_chain_eigenvalues_exact():
    lam = T.laplacian_spectrum(T.laplacian(T.chain(40, 1.5)))
    assert lam[0] == 0 and np.all(lam[1:] == 1.5) and np.all(lam.imag == 0)


def test_complete_eigenvalues():
    n = 9
    lam = np.sort(T.laplacian_spectrum(T.laplacian(T.complete(n, 0.5))).real)
    np.testing.assert_allclose(lam, [0.0] + [0.5 * n] * (n - 1), atol=1e-12)


def test_ring_eigenvalues():
    n = 10
    lam = np.sort(T.laplacian_spectrum(T.laplacian(T.ring(n))).real)
    np.testing.assert_allclose(lam, np.sort(2 - 2 * np.cos(2 * np.pi * np.arange(n) / n)), atol=1e-12)


def test_spectrum_of_weighted_tree_is_its_diagonal():
    # A random directed tree (each vehicle hears one lower-index vehicle), shuffled.
    rng = np.random.default_rng(3)
    n = 30
    W = np.zeros((n, n))
    for i in range(1, n):
        W[i, rng.integers(0, i)] = rng.uniform(0.5, 2.0)
    perm = rng.permutation(n)
    W = W[np.ix_(perm, perm)]
    L = T.laplacian(W)
    np.testing.assert_array_equal(np.sort(T.laplacian_spectrum(L).real), np.sort(np.diag(L)))


def test_spectrum_of_directed_cycle_is_complex():
    n = 6
    W = np.roll(np.eye(n), 1, axis=1)  # i hears i+1 mod n
    lam = T.laplacian_spectrum(T.laplacian(W))
    expect = 1 - np.exp(2j * np.pi * np.arange(n) / n)
    for z in expect:
        assert np.min(np.abs(lam - z)) < 1e-9


def test_k_nearest_on_a_line():
    p = np.zeros((6, 3))
    p[:, 0] = [0, 1, 3, 6, 10, 15]
    Wd = T.k_nearest(p, 1, symmetric=False)
    np.testing.assert_array_equal(Wd.argmax(axis=1), [1, 0, 1, 2, 3, 4])
    assert np.all(Wd.sum(axis=1) == 1)
    Ws = T.k_nearest(p, 1)
    assert np.array_equal(Ws, np.maximum(Wd, Wd.T))


def test_k_nearest_ties_and_clamp():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0]])
    Wd = T.k_nearest(p, 1, symmetric=False)
    assert Wd[0, 1] == 1 and Wd[0].sum() == 1  # equidistant: lowest index wins
    np.testing.assert_array_equal(T.k_nearest(p, 10), T.complete(4))
    np.testing.assert_array_equal(T.k_nearest(p[:1], 1), [[0.0]])


def test_input_validation():
    with pytest.raises(ValueError):
        T.chain(0)
    with pytest.raises(ValueError):
        T.ring(3, weight=-1)
    with pytest.raises(ValueError):
        T.laplacian(np.ones((2, 3)))
    with pytest.raises(ValueError):
        T.laplacian(np.array([[0, np.nan], [1, 0]]))
    with pytest.raises(ValueError):
        T.k_nearest(np.zeros((4, 2)), 1)
    with pytest.raises(IndexError):
        T.neighbours(T.chain(3), 3)


def test_describe():
    assert T.describe(T.chain(40)) == "chain(40)"
    assert T.describe(T.ring(7, 0.5)) == "ring(7, weight=0.5)"
    assert T.describe(T.complete(4)) == "complete(4)"
    assert T.describe(T.k_nearest(np.random.default_rng(0).normal(size=(8, 3)), 2)).startswith("graph(N=8")
