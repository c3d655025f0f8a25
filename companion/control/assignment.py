"""Slot assignment: which vehicle takes which new formation slot (pure numpy, deterministic).

A formation change (a new shape, or vehicles leaving or rejoining) moves every vehicle from
its current slot to a slot of the new table. `assign_slots` chooses the permutation that
minimises the sum of SQUARED distances from old to new slots, solved exactly by
`linear_assignment` (the Hungarian method in its shortest-augmenting-path form, as in
Jonker-Volgenant: O(n^3) time, one numpy row operation per step; n = 250 takes 0.01-0.1 s).

Why squared distances (Turpin, Michael & Kumar, "CAPT: Concurrent assignment and planning
of trajectories for multiple robots", IJRR 2014): if every vehicle then flies the straight
line from its old slot to its new one with the SAME time profile (position
old + s(t) (new - old), one s(t) for all, as `companion.commands.morph_offsets_ned_m`
does), optimality gives (a_i - a_j) . (b_i - b_j) >= 0 for every pair (else swapping the
two would be cheaper), hence their distance at every instant obeys

    |x_i - x_j|^2 >= (1 - s)^2 |a_i - a_j|^2 + s^2 |b_i - b_j|^2 >= d_a^2 d_b^2 / (d_a^2 + d_b^2)

with d_a, d_b their old and new separations: never less than min(d_a, d_b) / sqrt(2).
Note what this does NOT say: two straight PATHS (as sets) may still cross, the vehicles
only pass the crossing point at different times (a shallow crossing of a long and a short
move; tests/test_assignment.py shows one). Minimising the sum of plain distances would
uncross the paths but gives no such bound on the distance in time.

Imports: numpy only.
"""
from __future__ import annotations

import numpy as np


def linear_assignment(cost: np.ndarray) -> np.ndarray:
    """The minimum-cost assignment of rows to distinct columns.

    Shortest augmenting paths with potentials (the Jonker-Volgenant / Crouse form of the
    Hungarian method): for a square problem, a column reduction first gives every column
    to its cheapest row where that row is still free; then each free row is matched along a
    shortest augmenting path (Dijkstra over the columns on reduced costs, one numpy row
    operation per step), and the potentials keep every reduced cost >= 0. O(n^2 m) at
    worst; n = 250 formation changes take about 0.01-0.1 s.

    Deterministic: equal inputs give equal outputs. Among equally close columns the search
    takes a free one first (ending the path: a vehicle keeps its slot when nothing is
    gained by moving it), else the lowest index.

    Args:
        cost: (n, m) finite costs, n <= m.
    Returns:
        (n,) int array: the column of each row (distinct).
    Raises:
        ValueError: not a 2-D array, more rows than columns, or a non-finite cost.
    """
    c = np.asarray(cost, dtype=float)
    if c.ndim != 2:
        raise ValueError(f"cost must be a 2-D array, got shape {c.shape}")
    n, m = c.shape
    if n > m:
        raise ValueError(f"{n} rows cannot take distinct columns of {m}")
    if not np.all(np.isfinite(c)):
        raise ValueError("cost has non-finite entries")
    col4row = np.full(n, -1, dtype=np.intp)
    row4col = np.full(m, -1, dtype=np.intp)
    u = np.zeros(n)
    v = np.zeros(m)
    if n == m and n:  # column reduction (rectangular: the column potentials must stay <= 0, so from 0)
        v = c.min(axis=0)
        cheapest = c.argmin(axis=0)
        for j in range(m):
            i = cheapest[j]
            if col4row[i] < 0:
                col4row[i], row4col[j] = j, i
        has = col4row >= 0
        u[has] = c[has, col4row[has]] - v[col4row[has]]  # = 0: each such row's cheapest reduced cost
    path = np.zeros(m, dtype=np.intp)  # path[j]: the row from which column j was reached
    key = np.empty(m)  # tentative distance of each column not yet scanned (inf once scanned)
    dist = np.empty(m)  # final distance of each scanned column
    r = np.empty(m)
    upd = np.empty(m, dtype=bool)
    unscanned = np.empty(m, dtype=bool)
    tie = np.empty(m, dtype=bool)
    for cur in range(n):
        if col4row[cur] >= 0:
            continue
        key.fill(np.inf)
        unscanned.fill(True)
        open_cols = row4col < 0
        rows: list[int] = []
        cols: list[int] = []
        reached = 0.0
        i = cur
        while True:
            rows.append(i)
            np.subtract(c[i], v, out=r)
            r += reached - u[i]
            np.less(r, key, out=upd)
            upd &= unscanned
            np.copyto(key, r, where=upd)
            np.copyto(path, i, where=upd)
            j = int(np.argmin(key))
            reached = float(key[j])
            if not open_cols[j]:  # prefer a free column at the same distance: the path ends there
                np.equal(key, reached, out=tie)
                tie &= open_cols
                k = int(np.argmax(tie))
                if tie[k]:
                    j = k
            dist[j] = reached
            key[j] = np.inf
            unscanned[j] = False
            cols.append(j)
            i = int(row4col[j])
            if i < 0:
                break
        u[cur] += reached
        if len(rows) > 1:
            rr = np.asarray(rows[1:], dtype=np.intp)
            u[rr] += reached - dist[col4row[rr]]
        cc = np.asarray(cols, dtype=np.intp)
        v[cc] -= reached - dist[cc]
        while True:  # augment: flip the path back to the free row
            i = int(path[j])
            row4col[j] = i
            col4row[i], j = j, int(col4row[i])
            if i == cur:
                break
    return col4row


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m) squared Euclidean distances between the rows of a (n, k) and b (m, k)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    d = a[:, None, :] - b[None, :, :]
    return np.einsum("ijk,ijk->ij", d, d)


def assign_slots(old_ned_m: np.ndarray, new_ned_m: np.ndarray) -> np.ndarray:
    """The new slot of each vehicle: minimises the sum of squared distances old -> new.

    Args:
        old_ned_m: (n, 3) each vehicle's current slot offset (or position), NED m.
        new_ned_m: (m, 3) the new slot offsets, m >= n.
    Returns:
        (n,) int array: new_ned_m row taken by each vehicle (distinct).
    Raises:
        ValueError: shapes, more vehicles than slots, or non-finite input.
    """
    old = np.asarray(old_ned_m, dtype=float).reshape(-1, 3)
    new = np.asarray(new_ned_m, dtype=float).reshape(-1, 3)
    return linear_assignment(squared_distances(old, new))


def assignment_cost(cost: np.ndarray, col_of_row: np.ndarray) -> float:
    """Total cost of an assignment (row i takes column col_of_row[i])."""
    c = np.asarray(cost, dtype=float)
    return float(c[np.arange(len(col_of_row)), col_of_row].sum())
