"""Stage 2: random wide-baseline triplets (triangles) on the salient points.

A triangle qualifies when all three edges are at least ``min_edge`` long (the paper: 50% of the
diameter of the overlapping region) and no inner angle is below ``min_angle_deg`` (near-degenerate
triangles have unstable angle descriptors). Triangles are returned as index triples with their
vertices in canonical order (see :mod:`gctr_cli.engine.descriptor`) and without duplicates.
"""

from __future__ import annotations

import numpy as np

from gctr_cli.engine.descriptor import canonical_order


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
    local = np.isfinite(max_edge)
    if local:
        near = (sq <= max_sq) & (sq >= min_sq)
        n_near = near.sum(axis=1)
        near_first = np.argsort(~near, axis=1, kind="stable")  # row i: the near points of i first
        anchors = np.flatnonzero(n_near >= 2)
        if len(anchors) == 0:
            return np.empty((0, 3), dtype=np.int64)
    found: list[np.ndarray] = []
    have = 0
    batch = max(4 * n, 1000)
    for _ in range(max_rounds):
        if local:
            i = anchors[rng.integers(0, len(anchors), size=batch)]
            j = near_first[i, (rng.random(batch) * n_near[i]).astype(np.int64)]
            k = near_first[i, (rng.random(batch) * n_near[i]).astype(np.int64)]
        else:
            i, j, k = rng.integers(0, m, size=(3, batch))
        a2, b2, c2 = sq[j, k], sq[k, i], sq[i, j]  # squared edges opposite vertices i, j, k
        ok = ((a2 >= min_sq) & (b2 >= min_sq) & (c2 >= min_sq) & (a2 > 0) & (b2 > 0) & (c2 > 0)
              & (a2 <= max_sq) & (b2 <= max_sq) & (c2 <= max_sq))
        i, j, k, a2, b2, c2 = i[ok], j[ok], k[ok], a2[ok], b2[ok], c2[ok]
        cos_i = (b2 + c2 - a2) / (2 * np.sqrt(b2 * c2))
        cos_j = (a2 + c2 - b2) / (2 * np.sqrt(a2 * c2))
        cos_k = (a2 + b2 - c2) / (2 * np.sqrt(a2 * b2))
        ok = (cos_i <= max_cos) & (cos_j <= max_cos) & (cos_k <= max_cos)
        tri = np.stack([i[ok], j[ok], k[ok]], axis=1)
        found.append(tri)
        have += len(tri)
        if have >= 2 * n:
            break
    tri = np.concatenate(found) if found else np.empty((0, 3), dtype=np.int64)
    if len(tri) == 0:
        return tri
    # Deduplicate on the unordered vertex set, keep the first draw (seeded, deterministic).
    srt = np.sort(tri, axis=1).astype(np.int64)
    key = (srt[:, 0] * m + srt[:, 1]) * m + srt[:, 2]
    _, first = np.unique(key, return_index=True)
    tri = tri[np.sort(first)][:n]
    return canonical_order(points, tri)
