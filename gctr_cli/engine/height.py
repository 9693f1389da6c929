"""Height-map evidence for the verdict: how well an alignment matches the two clouds' relief over
the target's dominant plane.

On outdoor LiDAR windows the ground is most of both clouds and matches under any rotation about
its normal, while the structure that should decide (trees, poles, façades) is too noisy for PCA
normals, so the surface agreement hardly tells the right alignment from a wrong one. The height of
that structure above the ground survives the noise: a tree is as tall in both clouds wherever its
normals point. The target's dominant plane (the ground, a floor, or simply the flattest large part
of an object) is divided into square cells; in each cell the 90th percentile of the height above the
plane sums up the relief. An alignment is scored by the cells where the moved source and the target
both have points and at least one has relief: agreeing heights count for it, different heights
against it at a lower weight (even the right alignment of two noisy, partial windows leaves as many
cells differing as agreeing — edges of the overlap, sparse cells — while a wrong one agrees on few).
The result is floored at 0: relief is evidence *for* an alignment when it agrees more than it
differs, never against one (on an object without a ground, the "dominant plane" is just its flattest
part, and a right answer's heights over it need not agree).

The relief is coarse: it tells which alignment is right, not how precise it is. The verdict uses it
only as a second lead that can raise the confidence of the answer the surface agreement chose
(:func:`gctr_cli.engine.decide.relief_confidence`), never to choose the answer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: percentile of the heights in a cell that sums up its relief (the top of the structure, robust to
#: a stray point above it)
CELL_PERCENTILE = 0.9
#: a cell needs this many points of a cloud to have a height
MIN_CELL_POINTS = 2
#: at most this many points are tried as seeds of the dominant plane (evenly strided)
PLANE_SEEDS = 200
#: a target with fewer relief cells has too little relief to tell alignments apart (a handful of
#: agreeing cells would count as a large share): no height map
MIN_RELIEF_CELLS = 30
#: offset that keeps cell indices non-negative in the packed cell keys
_KEY_OFFSET = 1 << 20


@dataclass(frozen=True)
class HeightMap:
    """The target's relief over its dominant plane, ready to compare moved source points with."""

    normal: np.ndarray  # unit normal of the plane, towards most of the off-plane points
    offset: float  # plane: normal . x = offset
    basis: np.ndarray  # (2, 3) in-plane axes
    cell: float  # cell side (normalised target units)
    tolerance: float  # heights within this agree; relief is a height above twice this
    keys: np.ndarray  # sorted keys of the cells with a height
    heights: np.ndarray  # their heights
    relief_cells: int  # cells of the target with relief (the normaliser of the score)

    @classmethod
    def build(cls, points: np.ndarray, normals: np.ndarray, band: float, cell: float,
              tolerance: float) -> HeightMap | None:
        """Height map of ``points`` over their dominant plane (points within ``band`` of it with a
        normal within 30° of its normal); ``None`` when fewer than ``MIN_RELIEF_CELLS`` cells have
        relief."""
        normal, offset = dominant_plane(points, normals, band)
        a = np.eye(3)[int(np.argmin(np.abs(normal)))]
        u = np.cross(normal, a)
        u /= np.linalg.norm(u)
        basis = np.stack([u, np.cross(normal, u)])
        keys, heights = cell_heights(points, normal, offset, basis, cell)
        relief = int(np.count_nonzero(heights > 2 * tolerance))
        if relief < MIN_RELIEF_CELLS:
            return None
        return cls(normal, offset, basis, cell, tolerance, keys, heights, relief)

    def agreement(self, moved: np.ndarray, conflict_weight: float) -> float:
        """(Relief cells whose heights agree − ``conflict_weight`` × those whose heights differ) / the
        target's relief cells, for source points already moved into the target's frame, floored at 0;
        in [0, 1]."""
        keys, heights = cell_heights(moved, self.normal, self.offset, self.basis, self.cell)
        _, i, j = np.intersect1d(keys, self.keys, assume_unique=True, return_indices=True)
        a, b = heights[i], self.heights[j]
        relief = np.maximum(a, b) > 2 * self.tolerance
        agree = np.abs(a - b) < self.tolerance
        net = np.count_nonzero(relief & agree) - conflict_weight * np.count_nonzero(relief & ~agree)
        return float(np.clip(net / self.relief_cells, 0.0, 1.0))


def dominant_plane(points: np.ndarray, normals: np.ndarray, band: float) -> tuple[np.ndarray, float]:
    """The plane through most of ``points`` (within ``band``, normals within 30°), by one-point RANSAC
    over evenly strided seed points (deterministic), refitted by PCA of its points and turned towards
    the side where most of the other points lie."""
    seeds = np.arange(0, len(points), max(1, len(points) // PLANE_SEEDS))
    seed_normals = normals[seeds]
    best, best_count = 0, -1
    for start in range(0, len(seeds), 50):  # chunks keep the (seeds x points) matrices small
        n = seed_normals[start:start + 50]
        d = np.abs(points @ n.T - np.sum(points[seeds[start:start + 50]] * n, axis=1))
        aligned = np.abs(normals @ n.T) >= np.cos(np.radians(30.0))
        counts = np.count_nonzero((d < band) & aligned, axis=0)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best, best_count = start + k, int(counts[k])
    normal = seed_normals[best]
    on = np.abs((points - points[seeds[best]]) @ normal) < band
    if on.sum() >= 3:
        centred = points[on] - points[on].mean(axis=0)
        normal = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    offset = float(points[on].mean(axis=0) @ normal) if on.any() else float(points[seeds[best]] @ normal)
    signed = points @ normal - offset
    off = signed[np.abs(signed) > 3 * band]
    if np.count_nonzero(off < 0) > np.count_nonzero(off > 0):
        normal, offset = -normal, -offset
    return normal, offset


def cell_heights(points: np.ndarray, normal: np.ndarray, offset: float, basis: np.ndarray,
                 cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Sorted keys of the plane cells holding at least ``MIN_CELL_POINTS`` of ``points`` and the
    ``CELL_PERCENTILE`` height above the plane in each."""
    h = points @ normal - offset
    ij = np.clip(np.floor(points @ basis.T / cell), -_KEY_OFFSET + 1, _KEY_OFFSET - 1).astype(np.int64) + _KEY_OFFSET
    key = ij[:, 0] * (2 * _KEY_OFFSET) + ij[:, 1]
    order = np.lexsort((h, key))
    key, h = key[order], h[order]
    keys, start, count = np.unique(key, return_index=True, return_counts=True)
    top = h[start + np.floor(CELL_PERCENTILE * (count - 1)).astype(np.int64)]
    keep = count >= MIN_CELL_POINTS
    return keys[keep], top[keep]
