"""Communication topologies of the swarm as weight matrices (paper eq. 27-28).

Convention used everywhere in companion.control: W is a dense (N, N) float array
and W[i, j] >= 0 is the weight w_ij with which vehicle i *hears* vehicle j (row i
lists what vehicle i receives). The diagonal is zero. The graph Laplacian is
L = D - W with D = diag(row sums of W), so every row of L sums to zero and
L @ 1 = 0. Directed graphs (chain) give non-symmetric W and L.

Dense matrices are deliberate: the fleets flown are tens to a few thousand
vehicles, and dense W keeps the consensus law one matrix product.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "chain",
    "ring",
    "complete",
    "k_nearest",
    "laplacian",
    "laplacian_spectrum",
    "neighbours",
    "describe",
    "check_weights",
]

_KNN_CHUNK_ROWS = 256  # rows of the pairwise-distance matrix held at once in k_nearest


def _check_n_weight(n: int, weight: float) -> None:
    if int(n) != n or n < 1:
        raise ValueError(f"vehicle count n must be an integer >= 1, got {n!r}")
    if not np.isfinite(weight) or weight <= 0:
        raise ValueError(f"weight must be finite and > 0, got {weight!r}")


def check_weights(W: np.ndarray) -> np.ndarray:
    """Validate a weight matrix and return it as a float array.

    Args:
        W: (N, N) weights, W[i, j] = weight with which i hears j.

    Raises:
        ValueError: W is not square, not finite, or has negative entries.
    """
    W = np.asarray(W, dtype=float)
    if W.ndim != 2 or W.shape[0] != W.shape[1]:
        raise ValueError(f"weight matrix must be square (N, N), got shape {W.shape}")
    if not np.all(np.isfinite(W)):
        raise ValueError("weight matrix has non-finite entries")
    if np.any(W < 0):
        raise ValueError("weight matrix has negative entries (antagonistic links are not supported)")
    return W


def chain(n: int, weight: float = 1.0) -> np.ndarray:
    """Directed chain of the paper's simulation (section 4.1, Fig. 4).

    Vehicle i hears vehicle i-1 only; vehicle 0 hears nobody (it tracks its slot
    h_0 alone through K2).

    Args:
        n: vehicle count N >= 1.
        weight: w_{i,i-1} > 0.

    Returns:
        W: (N, N), W[i, i-1] = weight for i >= 1, zeros elsewhere.

    Raises:
        ValueError: n < 1 or weight not finite and positive.
    """
    _check_n_weight(n, weight)
    W = np.zeros((n, n))
    i = np.arange(1, n)
    W[i, i - 1] = weight
    return W


def ring(n: int, weight: float = 1.0) -> np.ndarray:
    """Undirected ring: vehicle i hears i-1 and i+1 (mod n).

    For n == 2 the two neighbours coincide and the single link has `weight`
    (not 2*weight); for n == 1 there are no links.

    Returns:
        W: (N, N), symmetric.

    Raises:
        ValueError: n < 1 or weight not finite and positive.
    """
    _check_n_weight(n, weight)
    W = np.zeros((n, n))
    if n > 1:
        i = np.arange(n)
        W[i, (i - 1) % n] = weight  # assignment, so n == 2 does not double the link
        W[i, (i + 1) % n] = weight
    return W


def complete(n: int, weight: float = 1.0) -> np.ndarray:
    """Every vehicle hears every other one.

    Returns:
        W: (N, N), weight off the diagonal, zero on it.

    Raises:
        ValueError: n < 1 or weight not finite and positive.
    """
    _check_n_weight(n, weight)
    return weight * (1.0 - np.eye(n))


def k_nearest(
    positions_ned_m: np.ndarray, k: int, weight: float = 1.0, symmetric: bool = True
) -> np.ndarray:
    """Vehicle i hears its k nearest vehicles by the given reference positions.

    Pass the formation offsets r_i (eq. 25), not live positions: the topology must
    be fixed for the stability check of eq. 28 to hold, and every agent must build
    the same W.

    Symmetrised by default (i hears j if j is among i's k nearest OR i among j's),
    because then L is symmetric positive semi-definite, its eigenvalues are real
    and >= 0, and any gains with Hurwitz leader block and K3 >= 0 are stable
    (docs/formation.md). With symmetric=False the graph is directed, L may have
    complex eigenvalues, and check_stability decides.

    Ties in distance are broken by the lower vehicle index (stable sort), so
    every agent gets the same graph. k >= N-1 gives the complete graph (so N == 1
    with k == 1 is allowed and gives no links).

    Args:
        positions_ned_m: (N, 3) reference positions, NED metres.
        k: neighbours per vehicle, >= 1.
        weight: weight of every link, > 0.
        symmetric: symmetrise the k-nearest relation (see above).

    Returns:
        W: (N, N).

    Cost: O(N^2) time, O(_KNN_CHUNK_ROWS * N) memory.

    Raises:
        ValueError: bad shape, non-finite positions, k < 1, bad weight.
    """
    p = np.asarray(positions_ned_m, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 1:
        raise ValueError(f"positions_ned_m must be (N, 3) with N >= 1, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("positions_ned_m has non-finite entries")
    if int(k) != k or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    n = p.shape[0]
    _check_n_weight(n, weight)
    k = min(int(k), n - 1)
    W = np.zeros((n, n))
    if k == 0:
        return W
    for start in range(0, n, _KNN_CHUNK_ROWS):
        rows = np.arange(start, min(start + _KNN_CHUNK_ROWS, n))
        d2 = np.sum((p[rows, None, :] - p[None, :, :]) ** 2, axis=-1)
        d2[np.arange(len(rows)), rows] = np.inf  # never pick yourself
        nearest = np.argsort(d2, axis=1, kind="stable")[:, :k]
        W[rows[:, None], nearest] = weight
    if symmetric:
        W = np.maximum(W, W.T)
    return W


def laplacian(W: np.ndarray) -> np.ndarray:
    """Graph Laplacian L = D - W, D = diag(row sums of W) (eq. 28).

    Args:
        W: (N, N) weights.

    Returns:
        L: (N, N); every row sums to zero.

    Raises:
        ValueError: see check_weights.
    """
    W = check_weights(W)
    deg = W.sum(axis=1) - np.diagonal(W)  # self-loops carry no information about differences
    L = 0.0 - W  # (0.0 - 0.0 is +0.0, unlike -W)
    np.fill_diagonal(L, deg)
    return L


def laplacian_spectrum(L: np.ndarray) -> np.ndarray:
    """Eigenvalues of a Laplacian, computed exactly where numerics would not be.

    * Acyclic "hears" graph (chain, any tree pointing at a leader): some vertex
      permutation makes L triangular, so its eigenvalues are exactly its diagonal
      (the in-degrees). The chain Laplacian has one Jordan block of size N-1 at
      eigenvalue w, whose eigenvalues a backward-stable solver may return
      scattered by ~eps**(1/(N-1)) (0.4 for N = 40). LAPACK's balancing happens
      to detect permuted-triangular input, but we do not rely on an
      implementation detail: the kron closed loop of eq. 28, which balancing
      cannot triangularise, does show that scatter (~0.26 for chain(40)).
    * Symmetric L: eigvalsh (real, well conditioned).
    * Otherwise: a general eigensolver (Schur form).

    Args:
        L: (N, N) Laplacian.

    Returns:
        (N,) complex eigenvalues. For the acyclic case in topological order
        (vehicles that hear nobody first), otherwise ascending real part.
    """
    L = np.asarray(L, dtype=float)
    n = L.shape[0]
    if np.array_equal(L, L.T):
        # Symmetric Laplacian: PSD with an exact 0 (L @ 1 = 0); pin both so that
        # round-off (e.g. -7e-16) cannot flip a marginal verdict or read oddly.
        lam = np.maximum(np.linalg.eigvalsh(L), 0.0)
        if n:
            lam[0] = 0.0
        return lam.astype(complex)
    order = _topological_order(L)
    if order is not None:
        return np.diag(L)[order].astype(complex)
    lam = np.linalg.eigvals(L)
    return lam[np.argsort(lam.real, kind="stable")] if n else lam


def _topological_order(L: np.ndarray) -> np.ndarray | None:
    """Order in which each vehicle comes after everyone it hears, or None if the
    'hears' graph has a cycle. Kahn's algorithm, one numpy step per layer."""
    n = L.shape[0]
    hears = (L != 0) & ~np.eye(n, dtype=bool)
    remaining = hears.sum(axis=1)  # unresolved sources per vehicle
    heard_by = [np.flatnonzero(hears[:, j]) for j in range(n)]
    frontier = np.flatnonzero(remaining == 0)
    done = np.zeros(n, dtype=bool)
    order = []
    while frontier.size:
        order.append(frontier)
        done[frontier] = True
        hit = np.concatenate([heard_by[j] for j in frontier]) if frontier.size else np.empty(0, int)
        np.subtract.at(remaining, hit, 1)
        cand = np.unique(hit)
        frontier = cand[(remaining[cand] == 0) & ~done[cand]]
    if not done.all():
        return None
    return np.concatenate(order)


def neighbours(W: np.ndarray, i: int) -> np.ndarray:
    """Indices j that vehicle i hears (W[i, j] != 0, j != i), ascending.

    Args:
        W: (N, N) weights.
        i: vehicle index, 0 <= i < N.

    Returns:
        (K,) int array.

    Raises:
        IndexError: i out of range.
    """
    W = np.asarray(W)
    n = W.shape[0]
    if not -n <= i < n:
        raise IndexError(f"vehicle index {i} out of range for N = {n}")
    i = i % n
    nz = np.flatnonzero(W[i])
    return nz[nz != i]


def describe(W: np.ndarray) -> str:
    """Short human name of a topology for error messages: 'chain(40)',
    'ring(12, weight=0.5)', 'complete(5)', else 'graph(N=40, 117 links)'."""
    W = np.asarray(W, dtype=float)
    n = W.shape[0]
    nz = W[W != 0]
    links = int(nz.size)
    if links and np.all(nz == nz[0]):
        w = float(nz[0])
        suffix = "" if w == 1.0 else f", weight={w:g}"
        for name, build in (("chain", chain), ("ring", ring), ("complete", complete)):
            if np.array_equal(W, build(n, w)):
                return f"{name}({n}{suffix})"
    return f"graph(N={n}, {links} links)"


def neighbour_table(W: np.ndarray) -> np.ndarray:
    """(N, K) int64 table of who each vehicle hears: row i lists the j != i with
    W[i, j] != 0 in increasing order, padded with -1; K = the largest in-degree (>= 1).
    """
    W = np.asarray(W)
    n = W.shape[0]
    lists = [[j for j in np.flatnonzero(W[i]) if j != i] for i in range(n)]
    k = max(1, max((len(x) for x in lists), default=0))
    out = np.full((n, k), -1, dtype=np.int64)
    for i, x in enumerate(lists):
        out[i, :len(x)] = x
    return out
