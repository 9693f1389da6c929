"""The result record of one registration."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: why the engine refused a pair (``RegistrationResult.refusal``); only ``low_confidence`` depends on
#: ``min_confidence``: the others refuse at any threshold
REFUSALS = ("invalid_input", "no_correspondences", "weak_evidence", "scale_bounds", "low_confidence",
            "scale_held", "not_confirmed", "mirrored")
#: the only refusal a lower ``min_confidence`` could turn into an ``ok`` (an ambiguous pair is one too); it
#: might not: the reverse confirmation and the mirror check never ran on such a pair
THRESHOLD_REFUSAL = "low_confidence"


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of registering one source cloud onto one target cloud.

    ``transform`` is the 4x4 similarity ``[[s*R, t], [0, 0, 0, 1]]`` mapping source points onto the
    target (``target ~ transform @ [source; 1]``) in the original coordinates of the inputs.

    ``fitness`` is the fraction of the (downsampled) source points that, after the transform, have a
    target point within the inlier distance (``inlier_distance_ratio`` x the target's robust
    diameter, 3% by default; robust diameter = twice the 90th percentile of the distances to the
    median point); ``inlier_rmse`` is the RMS of those distances, in target units. ``status`` is
    ``"ok"`` or ``"failed"``; a failed result still carries the best transform found (or the
    identity) and a ``message`` saying why.

    ``confidence`` in [0, 1] says how strongly the data single out this transform (see the
    engine's verdict stage): it measures how distinct the answer is from every other alignment, not
    how precise it is. 0 when the engine failed before its verdict (degenerate input, no RANSAC
    hypothesis); NaN where a comparison method does not compute one.

    The rest describe the search run that found the answer: ``n_inliers`` its RANSAC inliers among the
    salient points (supervoxel centroids, not input points), ``iterations`` its outer rounds,
    ``overlap`` the overlap hypothesis it ran with (0.25 ... 1.0, or a part-region share). ``runtime_s``
    is the engine's wall time and ``timings`` its seconds per stage; ``evidence`` holds the verdict's
    inputs (its score, the best rival's score, agreement and conflict shares, support, relief
    confidence: of the verdict's transform, before the polish of stage 5b) and the polish's view
    (``polish_end``, ``polished``, ``polish_before``, ``polish_fine``: :func:`~gctr_cli.engine.polish.polish`;
    absent when the answer was refused); ``fitness`` and ``inlier_rmse`` describe the returned transform;
    ``seed`` is the seed the draws came from; ``ok`` is ``status == "ok"``.

    ``refusal`` says why a failed result was refused, one of :data:`REFUSALS` (``""`` when ok, and for
    the comparison methods): ``low_confidence`` (below ``min_confidence``, ambiguous pairs included) is
    the only one a lower threshold could have accepted, which is what an offline sweep of the threshold
    needs to know (an upper bound: the checks that run only on accepted answers never ran on it).
    """

    transform: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    fitness: float
    inlier_rmse: float
    n_inliers: int
    iterations: int
    status: str
    message: str
    runtime_s: float
    seed: int
    overlap: float = float("nan")
    confidence: float = float("nan")
    timings: dict[str, float] = field(default_factory=dict)
    evidence: dict[str, float] = field(default_factory=dict)  # the verdict's inputs (see engine.verdict)
    refusal: str = ""  # why a failed result was refused: one of REFUSALS

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def __repr__(self) -> str:
        return (
            f"RegistrationResult(status={self.status!r}, scale={self.scale:.6g}, "
            f"fitness={self.fitness:.3f}, confidence={self.confidence:.3f}, inlier_rmse={self.inlier_rmse:.4g}, "
            f"n_inliers={self.n_inliers}, "
            f"iterations={self.iterations}, overlap={self.overlap}, runtime_s={self.runtime_s:.3f}, "
            f"message={self.message!r})"
        )
