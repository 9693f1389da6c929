"""Ground-truth checks of gctr_cli.metrics: what counts as a similarity, and the errors against one."""

from __future__ import annotations

import numpy as np

from gctr_cli.geometry import random_rotation, to_matrix
from gctr_cli.metrics import (
    GT_ORTHOGONALITY_TOL,
    is_similarity,
    nearest_similarity,
    orthogonality_deviation,
    transform_errors,
)


def test_a_ground_truth_rounded_to_three_decimals_is_a_similarity_and_measures_errors_closely():
    """A matrix typed or printed with three decimals (a viewer's display, a paper's table) is accepted as
    ground truth, and the errors it gives differ from the exact matrix's by a small fraction of the limits
    (5 deg, 5% scale); the engine's own outputs are still held to the strict default."""
    rng = np.random.default_rng(1)
    exact = to_matrix(0.5, random_rotation(rng), [0.3, -1.2, 2.0])
    rounded = np.round(exact, 3)
    assert is_similarity(exact) == (True, "")
    assert is_similarity(rounded, orthogonality_tol=GT_ORTHOGONALITY_TOL) == (True, "")
    strict_ok, strict_reason = is_similarity(rounded)
    assert not strict_ok and "allowed 0.001" in strict_reason
    errors = transform_errors(exact, rounded, target_diagonal=1.0)
    assert errors.rot_err_deg < 0.3 and errors.scale_err < 3e-3


def test_a_shear_is_refused_with_how_far_it_is_from_a_rotation():
    shear = np.eye(4)
    shear[0, 1] = 0.05
    ok, reason = is_similarity(shear, orthogonality_tol=GT_ORTHOGONALITY_TOL)
    assert not ok
    assert reason.startswith("3x3 block is not a scaled rotation (not orthogonal up to scale: R·Rᵀ differs from "
                             "the identity by up to 0.05")
    assert reason.endswith("allowed 0.01)")


def test_the_nearest_similarity_of_a_rounded_or_stretched_matrix_is_a_similarity_close_to_it():
    """Polar decomposition: a rounded matrix goes back to within rounding of the exact one; a stretch
    (0.4%, which passes the ground-truth tolerance) becomes a similarity of the mean scale."""
    rng = np.random.default_rng(1)
    exact = to_matrix(0.5, random_rotation(rng), [0.3, -1.2, 2.0])
    near = nearest_similarity(np.round(exact, 3))
    assert orthogonality_deviation(near) < 1e-12 and is_similarity(near) == (True, "")
    assert transform_errors(exact, near, target_diagonal=1.0).rot_err_deg < 0.1
    np.testing.assert_allclose(nearest_similarity(exact), exact, atol=1e-12)
    stretched = np.diag([1.0, 1.004, 1.0, 1.0])
    assert is_similarity(stretched, orthogonality_tol=GT_ORTHOGONALITY_TOL)[0]
    np.testing.assert_allclose(nearest_similarity(stretched), np.diag([1.004 / 3 + 2 / 3] * 3 + [1.0]), atol=1e-12)
