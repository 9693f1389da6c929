"""Stage 3: random wide-baseline triplets (triangles) on the salient points.

A triangle qualifies when all three edges are at least ``min_edge`` long (the paper: 50% of the
diameter of the overlapping region) and no inner angle is below ``min_angle_deg`` (near-degenerate
triangles have unstable angle descriptors). Triangles are returned as index triples with their
vertices in canonical order (see :mod:`gctr_cli.engine.descriptor`) and without duplicates.
"""

from __future__ import annotations

import numpy as np

#: up to this many points, already drawn vertex sets are marked in a table of m^3 booleans
_SEEN_TABLE_MAX_POINTS = 256
#: enumerate all admissible triangles (instead of drawing) when there are at most this many times n
_ENUMERATE_FACTOR = 2.0


def _canonical(tri: np.ndarray, sq: np.ndarray, max_cos: float) -> np.ndarray:
    """The triangles (index triples) with no inner angle below the limit, vertices in canonical order
    (ascending cosine: largest angle first; equal cosines in the given vertex order)."""
    i, j, k = tri[:, 0], tri[:, 1], tri[:, 2]
    a2, b2, c2 = sq[j, k], sq[k, i], sq[i, j]  # squared edges opposite vertices i, j, k
    c0, c1, c2 = ((b2 + c2 - a2) / (2 * np.sqrt(b2 * c2)), (a2 + c2 - b2) / (2 * np.sqrt(a2 * c2)),
                  (a2 + b2 - c2) / (2 * np.sqrt(a2 * b2)))
    ok = (c0 <= max_cos) & (c1 <= max_cos) & (c2 <= max_cos)  # NaN (a repeated vertex) fails
    tri, c0, c1, c2 = tri[ok], c0[ok], c1[ok], c2[ok]
    # A stable argsort of the three columns by comparisons (np.argsort along a length-3 axis sorts every
    # row separately, several times slower): each vertex's place is the number of vertices before it.
    place0 = (c1 < c0).astype(np.int64) + (c2 < c0)
    place1 = (c0 <= c1).astype(np.int64) + (c2 < c1)
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    return np.stack([np.where(place0 == p, v0, np.where(place1 == p, v1, v2)) for p in range(3)], axis=1)


def _sorted_rows(tri: np.ndarray) -> np.ndarray:
    """Each row of the (M, 3) integer array sorted ascending (``np.sort(tri, axis=1)``, by a sorting network)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    mid = np.maximum(lo, c)
    return np.stack([np.minimum(lo, c), np.minimum(hi, mid), np.maximum(hi, mid)], axis=1)


def _first_draws(key: np.ndarray) -> np.ndarray:
    """Ascending indices of the first occurrence of each distinct value of the non-negative integer ``key``
    (``np.sort(np.unique(key, return_index=True)[1])``): one plain sort of ``key * len + index`` (distinct
    values) instead of a stable sort of the keys."""
    n = len(key)
    if n == 0:
        return np.empty(0, dtype=np.int64)
    if int(key.max()) >= np.iinfo(np.int64).max // n:  # the packed values would overflow
        return np.sort(np.unique(key, return_index=True)[1])
    packed = np.sort(key.astype(np.int64) * n + np.arange(n))
    sorted_key = packed // n
    head = np.empty(n, dtype=bool)
    head[0] = True
    head[1:] = sorted_key[1:] != sorted_key[:-1]
    return np.sort(packed[head] % n)


def _enumerate_triangles(near: np.ndarray, sq: np.ndarray, max_cos: float) -> np.ndarray:
    """Every triangle whose three edges are admissible (``near``) and whose angles are wide enough,
    canonical vertex order, sorted by vertex set (deterministic)."""
    i, j = np.nonzero(np.triu(near, 1))  # edges i < j, in row-major order
    common = near[i] & near[j]  # (edges, m): the third vertices admissible from both ends
    common &= np.arange(near.shape[0])[None, :] > j[:, None]  # k > j: each vertex set once
    e, k = np.nonzero(common)
    if len(e) == 0:
        return np.empty((0, 3), dtype=np.int64)
    return _canonical(np.stack([i[e], j[e], k], axis=1).astype(np.int64), sq, max_cos)


def sample_triangles(points: np.ndarray, n: int, min_edge: float, rng: np.random.Generator,
                     min_angle_deg: float = 10.0, max_rounds: int = 8, max_edge: float = np.inf) -> np.ndarray:
    """Up to ``n`` distinct wide-baseline triangles, (M, 3) int, vertices in canonical order.

    With a finite ``max_edge`` the triangles are *local*: the second and third vertex are drawn
    among the points within ``max_edge`` of the first, so that when only a part of the cloud
    overlaps the other, a useful share of the triangles lies entirely inside that part.
    """
    m = len(points)
    if m < 3 or n <= 0:
        return np.empty((0, 3), dtype=np.int64)
    max_cos = np.cos(np.radians(min_angle_deg))
    # Squared pairwise distances of the (few hundred) salient points: edge tests and the law of
    # cosines become table lookups.
    sq = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=-1)
    min_sq, max_sq = min_edge * min_edge, max_edge * max_edge
    # Draw the first vertex, then the other two among its admissible partners (edge within
    # [min_edge, max_edge]): wide-baseline triangles are rare among uniform triples, so drawing
    # partners directly accepts most draws; with a finite ``max_edge`` the triangles are local.
    near = (sq <= max_sq) & (sq >= min_sq) & (sq > 0)
    # When the admissible triangles (three admissible edges: the triangles of the graph ``near``) are
    # few — local triangles of a small overlap region — drawing would spend all ``max_rounds``
    # re-finding the same ones: enumerate them instead (trace(A^3) / 6 counts them).
    adj = near.astype(np.float64)
    n_admissible = float(np.einsum("ij,ji->", adj @ adj, adj)) / 6.0
    if n_admissible <= _ENUMERATE_FACTOR * n:
        tri = _enumerate_triangles(near, sq, max_cos)
        if len(tri) > n:
            tri = tri[np.sort(rng.choice(len(tri), n, replace=False))]
        return tri
    n_near = near.sum(axis=1)
    near_first = np.argsort(~near, axis=1, kind="stable")  # row i: the admissible partners of i first
    anchors = np.flatnonzero(n_near >= 2)
    # Each draw is kept only the first time its vertex set comes up (seeded, deterministic); a
    # table over all vertex triples (m^3 booleans, allocated lazily) marks what is already kept.
    seen = np.zeros(m * m * m, dtype=bool) if m <= _SEEN_TABLE_MAX_POINTS else None
    kept_keys: list[np.ndarray] = []
    found: list[np.ndarray] = []
    have = 0
    batch = max(2 * n, 1000)
    for _ in range(max_rounds):
        i = anchors[rng.integers(0, len(anchors), size=batch)]
        j = near_first[i, (rng.random(batch) * n_near[i]).astype(np.int64)]
        k = near_first[i, (rng.random(batch) * n_near[i]).astype(np.int64)]
        a2 = sq[j, k]
        ok = (a2 >= min_sq) & (a2 <= max_sq) & (a2 > 0)  # i-j and i-k are admissible by construction
        tri = _canonical(np.stack([i[ok], j[ok], k[ok]], axis=1), sq, max_cos)
        srt = _sorted_rows(tri).astype(np.int64)
        key = (srt[:, 0] * m + srt[:, 1]) * m + srt[:, 2]
        first = _first_draws(key)  # first draw of each vertex set within this round, in draw order
        tri, key = tri[first], key[first]
        if seen is not None:
            new = ~seen[key]
            seen[key[new]] = True
        else:
            new = ~np.isin(key, np.concatenate(kept_keys)) if kept_keys else np.ones(len(key), dtype=bool)
            kept_keys.append(key[new])
        found.append(tri[new])
        have += int(new.sum())
        if have >= n:
            break  # the first n distinct draws are final: more rounds would not change them
    if not found:
        return np.empty((0, 3), dtype=np.int64)
    return np.concatenate(found)[:n].astype(np.int64)
