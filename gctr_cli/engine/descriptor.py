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

from gctr_cli.geometry import cross, row_norms


def _edges(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, ...]:
    """Edge vectors a->b, b->c, c->a of each triangle (a, b, c) and their lengths."""
    p = points[triangles]  # (M, 3, 3)
    ab, bc, ca = p[:, 1] - p[:, 0], p[:, 2] - p[:, 1], p[:, 0] - p[:, 2]
    return ab, bc, ca, row_norms(ab), row_norms(bc), row_norms(ca)


def _cosines(ab: np.ndarray, bc: np.ndarray, ca: np.ndarray, l_ab: np.ndarray, l_bc: np.ndarray,
             l_ca: np.ndarray) -> np.ndarray:
    """Cosines of the inner angles at a, b, c from the edges (each angle between its two edges,
    both pointing away from the vertex)."""
    def cos(e1: np.ndarray, e2: np.ndarray, n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", e1, e2) / np.maximum(n1 * n2, 1e-300)

    return np.stack([cos(ab, -ca, l_ab, l_ca), cos(bc, -ab, l_bc, l_ab), cos(ca, -bc, l_ca, l_bc)], axis=1)


def inner_angle_cosines(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(M, 3) cosines of the inner angles at each vertex of each triangle, in vertex order."""
    return _cosines(*_edges(points, triangles))


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
    return described_with_permutations(points, None, triangles, margin=margin)[0]


def _tilts(points: np.ndarray, normals: np.ndarray, triangles: np.ndarray, ab: np.ndarray | None = None,
           ca: np.ndarray | None = None) -> np.ndarray:
    """|cos| of the angle between each vertex normal and the triangle's plane normal."""
    if ab is None or ca is None:
        p = points[triangles]
        ab, ca = p[:, 1] - p[:, 0], p[:, 0] - p[:, 2]
    n_tri = cross(ab, -ca)
    n_tri /= np.maximum(row_norms(n_tri), 1e-300)[:, None]
    return np.abs(np.einsum("mvi,mi->mv", normals[triangles], n_tri))


def triangle_descriptors(points: np.ndarray, normals: np.ndarray | None, triangles: np.ndarray,
                         normal_weight: float = 0.0) -> np.ndarray:
    """(M, 3) inner-angle cosines, or (M, 6) with the weighted vertex-normal terms appended."""
    return described_with_permutations(points, normals, triangles, normal_weight, permute=False)[1]


#: vertex orders added by :func:`described_with_permutations`: (permutation, which swap it needs, and its
#: edges v -> v+1 as indices into the original's edges ab, bc, ca — so its perimeter is summed in its own order)
_PERMUTATIONS = (((1, 0, 2), "01", (0, 2, 1)), ((0, 2, 1), "12", (2, 1, 0)), ((1, 2, 0), "both", (1, 2, 0)),
                 ((2, 0, 1), "both", (2, 0, 1)), ((2, 1, 0), "both", (1, 0, 2)))


def described_with_permutations(points: np.ndarray, normals: np.ndarray | None, triangles: np.ndarray,
                                normal_weight: float = 0.0, margin: float = 0.08, permute: bool = True
                                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles (with the ambiguous variants of :func:`with_ambiguous_permutations` when ``permute``),
    their descriptors (as :func:`triangle_descriptors`) and perimeters, from one pass over the edges.

    A variant's cosines are its triangle's, reordered (an angle does not depend on the order of its
    two edges); its normal terms are computed from its own vertex order, like any triangle's.
    """
    ab, bc, ca, l_ab, l_bc, l_ca = _edges(points, triangles)
    cos = _cosines(ab, bc, ca, l_ab, l_bc, l_ca)
    perimeter = l_ab + l_bc + l_ca
    tri_parts, cos_parts, per_parts = [triangles], [cos], [perimeter]
    if permute and len(triangles):
        swap = {"01": cos[:, 1] - cos[:, 0] < margin, "12": cos[:, 2] - cos[:, 1] < margin}
        swap["both"] = swap["01"] & swap["12"]
        lengths = (l_ab, l_bc, l_ca)
        for perm, need, edges in _PERMUTATIONS:
            rows = swap[need]
            tri_parts.append(triangles[rows][:, list(perm)])
            cos_parts.append(cos[rows][:, list(perm)])
            per_parts.append(lengths[edges[0]][rows] + lengths[edges[1]][rows] + lengths[edges[2]][rows])
    tri, cos_all, per = np.concatenate(tri_parts), np.concatenate(cos_parts), np.concatenate(per_parts)
    if normal_weight <= 0 or normals is None or len(tri) == 0:
        return tri, cos_all, per
    n0 = len(triangles)
    tilt = np.concatenate([_tilts(points, normals, triangles, ab, ca), _tilts(points, normals, tri[n0:])])
    return tri, np.hstack([cos_all, normal_weight * tilt]), per
