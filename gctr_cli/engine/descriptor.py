"""Stage 3: the triplet descriptor — cosines of the three inner angles (scale invariant).

The descriptor of a triangle (a, b, c) is ``(cos A, cos B, cos C)`` in vertex order. As an
extension (``tensor.normal_weight > 0``) it is followed by ``w * |n_v . n_tri|`` for each vertex v:
the angle between the salient point's (supervoxel) normal and the triangle's plane — also
invariant to scale, rotation and translation, and much more discriminative on noisy, non-repeatable
salient points (weight 0 gives the paper's pure angle descriptor). Vertices are
put in *canonical order* — largest inner angle first (ascending cosine) — so that a descriptor
match between a source and a target triangle also fixes which vertex corresponds to which.
Where two angles are nearly equal that order is unstable, so the target side also carries the
swapped variants (:func:`with_ambiguous_permutations`).
"""

from __future__ import annotations

import numpy as np


def inner_angle_cosines(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(M, 3) cosines of the inner angles at each vertex of each triangle, in vertex order."""
    p = points[triangles]  # (M, 3, 3)
    a, b, c = p[:, 0], p[:, 1], p[:, 2]

    def cos_at(v: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
        e1, e2 = u - v, w - v
        den = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
        return np.einsum("ij,ij->i", e1, e2) / np.maximum(den, 1e-300)

    return np.stack([cos_at(a, b, c), cos_at(b, c, a), cos_at(c, a, b)], axis=1)


def canonical_order(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Reorder each triangle's vertices by ascending cosine (largest angle first)."""
    if len(triangles) == 0:
        return triangles
    order = np.argsort(inner_angle_cosines(points, triangles), axis=1, kind="stable")
    return np.take_along_axis(triangles, order, axis=1)


def with_ambiguous_permutations(points: np.ndarray, triangles: np.ndarray,
                                margin: float = 0.08) -> np.ndarray:
    """Add, for canonical triangles whose neighbouring angles are within ``margin`` in cosine,
    the variants with those two vertices swapped (and both swaps for near-equilateral ones)."""
    if len(triangles) == 0:
        return triangles
    cos = inner_angle_cosines(points, triangles)
    extra = [triangles]
    swap01 = cos[:, 1] - cos[:, 0] < margin
    swap12 = cos[:, 2] - cos[:, 1] < margin
    extra.append(triangles[swap01][:, [1, 0, 2]])
    extra.append(triangles[swap12][:, [0, 2, 1]])
    both = swap01 & swap12
    for perm in ([1, 2, 0], [2, 0, 1], [2, 1, 0]):
        extra.append(triangles[both][:, perm])
    return np.concatenate(extra)


def triangle_descriptors(points: np.ndarray, normals: np.ndarray | None, triangles: np.ndarray,
                         normal_weight: float = 0.0) -> np.ndarray:
    """(M, 3) inner-angle cosines, or (M, 6) with the weighted vertex-normal terms appended."""
    cos = inner_angle_cosines(points, triangles)
    if normal_weight <= 0 or normals is None or len(triangles) == 0:
        return cos
    p = points[triangles]
    n_tri = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n_tri /= np.maximum(np.linalg.norm(n_tri, axis=1, keepdims=True), 1e-300)
    tilt = np.abs(np.einsum("mvi,mi->mv", normals[triangles], n_tri))
    return np.hstack([cos, normal_weight * tilt])
