"""gctr_cli.geometry: compose, split, apply and invert similarities; uniform random rotations."""

from __future__ import annotations

import ast
import inspect

import numpy as np
import pytest

from gctr_cli import geometry
from gctr_cli.geometry import apply, cross, invert, random_rotation, row_norms, split, to_matrix

#: a rotation by 90 degrees about z, written out
RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def test_to_matrix_and_apply_with_numbers_worked_by_hand():
    T = to_matrix(2.0, RZ90, [1.0, -2.0, 3.0])
    np.testing.assert_array_equal(T, [[0, -2, 0, 1], [2, 0, 0, -2], [0, 0, 2, 3], [0, 0, 0, 1]])
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 2.0, 3.0]])
    # x' = 2 * Rz90 @ p + t: (1,0,0) -> (0,2,0) + t; (0,1,0) -> (-2,0,0) + t; (1,2,3) -> (-4,2,6) + t
    np.testing.assert_array_equal(apply(T, pts), [[1.0, 0.0, 3.0], [-1.0, -2.0, 3.0], [-3.0, 0.0, 9.0]])


def test_split_inverts_to_matrix():
    rng = np.random.default_rng(0)
    for _ in range(50):
        s, R, t = float(np.exp(rng.uniform(-3, 3))), random_rotation(rng), rng.normal(scale=1e3, size=3)
        s2, R2, t2 = split(to_matrix(s, R, t))
        assert s2 == pytest.approx(s, rel=1e-14)
        np.testing.assert_allclose(R2, R, rtol=0, atol=1e-14)
        np.testing.assert_array_equal(t2, t)
    assert split(to_matrix(0.5, RZ90, [0, 0, 7]))[0] == pytest.approx(0.5, rel=1e-15)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 8, 9, 150, 800, 2000, 6000, 44000])
def test_cross_and_row_norms_are_numpys_bit_for_bit(n):
    """The engine's faster cross products and row lengths give numpy's results to the last bit (answers do
    not change): rows of widely varying magnitude, C-ordered, strided, Fortran-ordered and column-permuted."""
    rng = np.random.default_rng(n)
    a = rng.normal(size=(n, 3)) * np.exp(rng.normal(size=(n, 3)) * 3)
    b = rng.normal(size=(n, 3)) * np.exp(rng.normal(size=(n, 1)) * 3)
    for x, y in ((a, b), (a[::2], b[::2]), (np.asfortranarray(a), b), (a[:, [2, 0, 1]], -b)):
        assert np.array_equal(cross(x, y), np.cross(x, y))
        assert np.array_equal(row_norms(x), np.linalg.norm(x, axis=1))
        assert np.array_equal(row_norms(x - y), np.linalg.norm(x - y, axis=1))


def test_split_rejects_a_singular_block():
    with pytest.raises(ValueError, match="singular"):
        split(np.diag([1.0, 1.0, 0.0, 1.0]))


def test_invert_round_trips_points_and_composes_to_the_identity():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(100, 3))
    for _ in range(20):
        T = to_matrix(float(rng.uniform(0.2, 5.0)), random_rotation(rng), rng.normal(scale=10.0, size=3))
        Ti = invert(T)
        np.testing.assert_allclose(apply(Ti, apply(T, pts)), pts, rtol=0, atol=1e-12)
        np.testing.assert_allclose(T @ Ti, np.eye(4), rtol=0, atol=1e-13)
        s, R, t = split(Ti)
        s0, R0, t0 = split(T)
        assert s == pytest.approx(1.0 / s0, rel=1e-13)  # the inverse similarity: 1/s, R^T, -R^T t / s
        np.testing.assert_allclose(R, R0.T, atol=1e-13)
        np.testing.assert_allclose(t, -R0.T @ t0 / s0, atol=1e-12)
    np.testing.assert_array_equal(invert(to_matrix(2.0, np.eye(3), [2.0, 4.0, 8.0])),
                                  to_matrix(0.5, np.eye(3), [-1.0, -2.0, -4.0]))


def test_composition_applies_right_to_left():
    A = to_matrix(2.0, RZ90, [1.0, 0.0, 0.0])
    B = to_matrix(1.0, np.eye(3), [0.0, 0.0, 5.0])
    p = np.array([[1.0, 1.0, 1.0]])
    np.testing.assert_array_equal(apply(A @ B, p), apply(A, apply(B, p)))


def test_random_rotation_is_a_proper_rotation_and_matches_scipy():
    from scipy.spatial.transform import Rotation

    for seed in range(200):
        R = random_rotation(np.random.default_rng(seed))
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
        # the same draws as scipy, the same matrix to the last bit or two: scipy's compiled quaternion
        # code may round differently on another CPU (1 ulp seen on an AMD EPYC), so equal within 1e-15
        rng = np.random.default_rng(seed)
        np.testing.assert_allclose(R, Rotation.random(random_state=rng).as_matrix(), rtol=0, atol=1e-15)
    # one normal(size=4) draw per rotation: the generator's state afterwards is scipy's too
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    random_rotation(a)
    b.normal(size=4)
    assert a.random() == b.random()


def test_random_rotation_is_uniform():
    """Uniform on SO(3): angle density (1 - cos θ) / π, so E[cos θ] = -1/2 and E[trace R] = 1 + 2 E[cos θ] = 0."""
    rng = np.random.default_rng(2)
    traces = np.array([np.trace(random_rotation(rng)) for _ in range(4000)])
    assert abs(traces.mean()) < 0.05  # E[trace R] = 0 for the Haar measure (std of the mean ~0.016)


def test_geometry_imports_nothing_of_the_package():
    tree = ast.parse(inspect.getsource(geometry))
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert all(m == "__future__" or m.split(".")[0] == "numpy" for m in imported), imported
