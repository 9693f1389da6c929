"""The verdict's relief evidence (:mod:`gctr_cli.engine.height`) on a synthetic street scene with
exact answers: the dominant plane, the heights per cell, and how an alignment's agreement ranks the
right transform above a turned or shifted one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gctr_cli.engine.height import HeightMap, cell_heights, dominant_plane
from gctr_cli.engine.preprocess import estimate_normals

CELL, TOLERANCE = 0.04, 0.01


def _street(rng: np.random.Generator, n_ground: int = 4000) -> np.ndarray:
    """A 1 x 1 patch of ground (z = 0) with boxes of different heights on it, 0.002 noise."""
    ground = np.column_stack([rng.uniform(-0.5, 0.5, (n_ground, 2)), np.zeros(n_ground)])
    boxes = []
    for (x, y), h in zip([(-0.3, -0.2), (0.1, 0.3), (0.3, -0.3), (-0.1, 0.1), (0.35, 0.15)],
                         [0.05, 0.12, 0.08, 0.2, 0.03]):
        top = np.column_stack([rng.uniform(x - 0.06, x + 0.06, (300, 1)), rng.uniform(y - 0.04, y + 0.04, (300, 1)),
                               np.full((300, 1), h)])
        boxes.append(top)
    pts = np.vstack([ground, *boxes])
    return pts + rng.normal(0, 0.002, pts.shape)


def _moved(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return points @ R.T + t


def test_dominant_plane_is_the_ground_and_faces_the_relief():
    rng = np.random.default_rng(0)
    R = Rotation.from_euler("xyz", [30, -20, 50], degrees=True).as_matrix()
    pts = _moved(_street(rng), R, np.array([0.2, -0.1, 0.3]))
    normal, offset = dominant_plane(pts, estimate_normals(pts), band=0.01)
    up = R @ np.array([0.0, 0.0, 1.0])
    assert normal @ up > 0.999  # the ground's normal, turned towards the boxes
    assert abs(offset - up @ np.array([0.2, -0.1, 0.3])) < 0.003


def test_cell_heights_are_the_top_of_each_cell():
    pts = np.array([[0.01, 0.01, 0.0], [0.02, 0.02, 0.5], [0.03, 0.01, 0.1],  # one cell, heights 0, 0.1, 0.5
                    [0.11, 0.01, 0.2],  # a cell with one point: no height
                    [0.21, 0.01, 0.3], [0.22, 0.01, 0.3]])
    keys, heights = cell_heights(pts, np.array([0.0, 0.0, 1.0]), 0.0, np.eye(3)[:2], 0.1)
    assert len(keys) == 2
    np.testing.assert_allclose(np.sort(heights), [0.1, 0.3])  # 90th percentile of (0, 0.1, 0.5): rank 1.8 -> 0.1


def test_right_alignment_agrees_and_turned_or_shifted_ones_do_not():
    rng = np.random.default_rng(1)
    target = _street(rng)
    source = _street(np.random.default_rng(2))  # another sampling of the same street
    hm = HeightMap.build(target, estimate_normals(target), band=0.01, cell=CELL, tolerance=TOLERANCE)
    assert hm is not None and hm.relief_cells > 20
    right = hm.agreement(source, conflict_weight=0.25)
    turned = hm.agreement(_moved(source, Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.zeros(3)), 0.25)
    shifted = hm.agreement(source + np.array([0.15, 0.0, 0.0]), 0.25)
    upside_down = hm.agreement(_moved(source, Rotation.from_euler("x", 180, degrees=True).as_matrix(), np.zeros(3)),
                               0.25)
    assert right > 0.8
    assert max(turned, shifted, upside_down) < 0.2
    assert min(turned, shifted, upside_down) >= 0.0


def test_a_cloud_without_relief_has_no_height_map():
    rng = np.random.default_rng(3)
    flat = np.column_stack([rng.uniform(-0.5, 0.5, (2000, 2)), rng.normal(0, 0.001, 2000)])
    assert HeightMap.build(flat, estimate_normals(flat), band=0.01, cell=CELL, tolerance=TOLERANCE) is None


def test_relief_confidence_backs_the_right_alignment_only():
    from gctr_cli.config import EngineConfig
    from gctr_cli.engine.decide import relief_confidence, tight_agreement, tight_test
    from gctr_cli.engine.prepare import RefinementCloud

    cfg = EngineConfig.model_validate({"verdict": {"height_weight": 0.5}, "refine": {"voxel_ratio": 0.01}})
    target = RefinementCloud.build(_street(np.random.default_rng(4)), cfg, np.random.default_rng(5))
    source = RefinementCloud.build(_street(np.random.default_rng(6)), cfg, np.random.default_rng(7))
    test = tight_test(source, target, 1.0, cfg)
    right = np.eye(4)
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    a_right, a_turned = (tight_agreement(T, source, target, test) for T in (right, turned))
    backed = relief_confidence(right, a_right, [(turned, a_turned)], source, target, test, cfg)
    # the relief adds at least 0.5 x 0.8 to the right answer's lead, counted against a margin of 0.5
    assert backed == pytest.approx(1.0)
    assert relief_confidence(turned, a_turned, [(right, a_right)], source, target, test, cfg) == 0.0


def test_the_relief_never_changes_the_answer_and_only_raises_the_confidence():
    from pathlib import Path

    from gctr_cli.config import EngineConfig
    from gctr_cli.engine import register
    from gctr_cli.io import load_point_cloud

    scans = Path(__file__).resolve().parent.parent / "data" / "scans"
    source, target = (np.asarray(load_point_cloud(scans / f), dtype=float) for f in ("bun000.ply", "bun045.ply"))
    plain = register(source, target, EngineConfig.model_validate({"verdict": {"height_weight": 0.0}}), 3)
    relief = register(source, target, EngineConfig(), 3)
    assert EngineConfig().verdict.height_weight > 0
    np.testing.assert_allclose(relief.transform, plain.transform, atol=1e-12)
    assert relief.confidence >= plain.confidence
    assert relief.evidence["relief_confidence"] >= 0.0 and plain.evidence["relief_confidence"] == 0.0
