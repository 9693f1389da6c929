"""Stage 5: the verdict — how well a transform explains both clouds, and how sure the engine is.

Two measures, both on the working clouds in normalised coordinates:

* **surface agreement** of a transform: the (weighted, see below) share of source points that land
  within the inlier distance of the target surface *with a normal that agrees* (angle below
  ``max_angle_deg``), and the same share of target points mapped back onto the source. Proximity
  alone is a weak test on noisy, outlier-ridden or partial clouds (a wrong pose still puts a third
  of the points near some surface); proximity with agreeing normals is rare by chance. The engine
  ranks its candidates by :attr:`Agreement.score`, the mean of the two shares, which works for
  partial overlaps in both directions: a part inside a whole has a high source share and a low
  target share. Each sample point counts with the weight ``count ** -verdict.normal_balance`` of its
  normal direction (:func:`normal_space_weights`), so that a dominant plane — the ground of a LiDAR
  sweep, the walls and floor of a room — cannot explain most of a scene on its own.
  In the final comparison (``decide``) the score also counts **conflicts**: a point that lands *near*
  the other cloud (within ``verdict.conflict_ratio`` of the smaller cloud) but not on its surface is
  evidence against the transform, and costs ``verdict.conflict_weight`` of an agreeing point. A
  half-turned slab or a low-overlap crop laid beside the right place puts a third to a half of the
  data beside the other surface; the right pose leaves only noise and the overlap's border there.
* **confidence** in [0, 1]: how far the answer's score leads the best *distinct* alternative, or
  "no alignment" (score 0) when every alternative scores less (a second transform that explains the
  data almost as well means the data do not single out one answer). See :func:`confidence`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gctr_cli.engine.scipy_parts import cKDTree
from gctr_cli.geometry import apply, invert


@dataclass(frozen=True)
class Surface:
    """A working cloud as the verdict sees it: all points with normals and a tree, plus a fixed
    evenly strided sample that is moved and looked up (keeps scoring cheap and deterministic), and
    the sample's weights by normal direction (:func:`normal_space_weights`)."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree
    sample: np.ndarray
    sample_normals: np.ndarray
    sample_weights: np.ndarray | None = None  # None: every sample point counts the same

    @classmethod
    def build(cls, points: np.ndarray, normals: np.ndarray, tree: cKDTree, n_sample: int,
              normal_balance: float) -> Surface:
        """``normal_balance``: the weights' exponent (``verdict.normal_balance``; 0 = unweighted)."""
        step = max(1, len(points) // n_sample)
        sample, sample_normals = points[::step], normals[::step]
        weights = normal_space_weights(sample_normals, normal_balance) if normal_balance > 0 else None
        return cls(points, normals, tree, sample, sample_normals, weights)


#: cells per axis of each cube face in the normal histogram of :func:`normal_space_weights`
NORMAL_BIN_CELLS = 4


def normal_space_weights(normals: np.ndarray, exponent: float) -> np.ndarray:
    """Weights ``count(bin) ** -exponent`` of unsigned unit normals binned on a cube map of the
    half-sphere (3 faces x ``NORMAL_BIN_CELLS``^2 cells), scaled to mean 1.

    A dominant plane (the ground of a LiDAR sweep, the walls of a room) holds most points of a scene;
    counted point by point it lets any transform that aligns that plane explain most of the data.
    Weighting each point by the rarity of its normal direction makes every direction of constraint
    count (normal-space sampling, Rusinkiewicz & Levoy 2001, as weights).

    Known limitation: with an even number of cells per face the cell borders run through the
    coordinate axes, so a noisy plane whose normal is a coordinate axis spreads over four cells and is
    down-weighted less than the same plane turned away from the axes (measured in review: the share
    of a 90% plane 0.52 axis-aligned, 0.32-0.45 turned). An odd count centres a cell on each axis;
    5 cells per face gave no better answers on the tuning sets (seeds 1+2, 244 hard-level pairs at
    threshold 0.35: 135 right / 4 silent wrong against 136 / 3), so the count stays 4.
    """
    face = np.argmax(np.abs(normals), axis=1)  # the cube face: the dominant axis
    rows = np.arange(len(normals))
    lead = normals[rows, face]
    lead = np.where(lead == 0, 1.0, lead)
    other = np.stack([normals[rows, (face + 1) % 3], normals[rows, (face + 2) % 3]], axis=1) / lead[:, None]
    cells = np.clip(((other + 1.0) * 0.5 * NORMAL_BIN_CELLS).astype(np.int64), 0, NORMAL_BIN_CELLS - 1)
    bins = (face * NORMAL_BIN_CELLS + cells[:, 0]) * NORMAL_BIN_CELLS + cells[:, 1]
    counts = np.bincount(bins, minlength=3 * NORMAL_BIN_CELLS ** 2).astype(np.float64)
    w = counts[bins] ** -exponent
    return w / w.mean()


@dataclass(frozen=True)
class Agreement:
    """Shares of the source and target samples that the transform puts on the other surface, and (when
    conflicts are counted, in the verdict) the shares it puts beside it (each sample point weighted by
    :func:`normal_space_weights`, when the surface has weights)."""

    source: float
    target: float
    conflict_source: float = 0.0  # share of the source sample that lands near the target but not on it
    conflict_target: float = 0.0  # the same of the target sample mapped back onto the source
    conflict_weight: float = 0.0  # how much a conflicting point costs against an agreeing one

    @property
    def score(self) -> float:
        """Mean of the two shares, less ``conflict_weight`` times the mean of the two conflict shares:
        the engine's objective for ranking candidates."""
        return 0.5 * (self.source + self.target) - 0.5 * self.conflict_weight * (self.conflict_source
                                                                                 + self.conflict_target)


def surface_matches(points: np.ndarray, normals: np.ndarray | None, other_normals: np.ndarray, tree: cKDTree,
                    distance: float, min_cos: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into ``points``, into the tree's points) of each point's nearest partner within
    ``distance``; with ``normals``, only partners whose normal agrees (|cos| ≥ ``min_cos``; lines,
    not directions, since PCA normals have no sign)."""
    d, j = tree.query(points, distance_upper_bound=distance)
    keep = np.isfinite(d)
    if normals is not None:
        _drop_disagreeing_normals(keep, j, normals, other_normals, min_cos)
    i = np.flatnonzero(keep)
    return i, j[i]


def _drop_disagreeing_normals(keep: np.ndarray, j: np.ndarray, normals: np.ndarray, other_normals: np.ndarray,
                              min_cos: float) -> None:
    """Clear ``keep`` (in place) where the normal of a kept point and that of its partner ``j`` differ
    (|cos| < ``min_cos``; lines, not directions); nothing to do when ``min_cos`` is 0."""
    if min_cos <= 0:
        return
    kept = np.flatnonzero(keep)
    cos = np.abs(np.einsum("ij,ij->i", normals[kept], other_normals[j[kept]]))
    keep[kept[cos < min_cos]] = False


def _share_on_surface(moved: np.ndarray, moved_normals: np.ndarray, other: Surface, distance: float,
                      min_cos: float, weights: np.ndarray | None = None, near: float = 0.0) -> tuple[float, float]:
    """(weighted share of ``moved`` on the ``other`` surface — nearest partner within ``distance`` with an
    agreeing normal, as :func:`surface_matches` —, weighted share whose nearest partner is within the
    larger of ``near`` and ``distance`` but that is not on the surface; 0 when ``near`` is 0).
    One neighbour query serves both (the nearest partner is the same)."""
    if len(moved) == 0:
        return 0.0, 0.0
    w = np.ones(len(moved)) if weights is None else weights
    d, j = other.tree.query(moved, distance_upper_bound=max(distance, near))
    close = np.isfinite(d)
    on = close & (d <= distance)
    _drop_disagreeing_normals(on, j, moved_normals, other.normals, min_cos)
    total = w.sum()
    conflict = float(w[close & ~on].sum() / total) if near > 0 else 0.0
    return float(w[on].sum() / total), conflict


def _scale_rotation(T: np.ndarray) -> tuple[float, np.ndarray] | None:
    """Scale ``s`` and rotation ``R`` of the similarity ``T``; ``None`` if its 3x3 block has no
    positive scale (not a similarity)."""
    A = T[:3, :3]
    s = float(np.cbrt(np.linalg.det(A)))
    if not np.isfinite(s) or s <= 0:
        return None
    return s, A / s


def _pulled_back(T: np.ndarray, s: float, R: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Target ``points`` taken into the source frame by the inverse of ``T = [[s R, t]]``."""
    return (points - T[:3, 3]) @ R / s


def surface_agreement(T: np.ndarray, src: Surface, tgt: Surface, distance: float,
                      max_angle_deg: float = 30.0, near: float = 0.0, conflict_weight: float = 0.0) -> Agreement:
    """Surface agreement of the similarity ``T`` (normalised source -> normalised target), with the
    conflict shares (points within ``near`` of the other cloud but not on its surface) when
    ``conflict_weight`` > 0.

    ``distance`` and ``near`` are in target units; the backward test uses ``distance / s`` and
    ``near / s`` in source units.
    """
    scale_rotation = _scale_rotation(T)
    if scale_rotation is None:
        return Agreement(0.0, 0.0)
    s, R = scale_rotation
    min_cos = float(np.cos(np.radians(max_angle_deg)))
    near = near if conflict_weight > 0 else 0.0
    fwd, cf = _share_on_surface(apply(T, src.sample), src.sample_normals @ R.T, tgt, distance, min_cos,
                                src.sample_weights, near)
    back, cb = _share_on_surface(_pulled_back(T, s, R, tgt.sample), tgt.sample_normals @ R, src, distance / s,
                                 min_cos, tgt.sample_weights, near / s)
    return Agreement(fwd, back, cf, cb, conflict_weight)


def displacement(T1: np.ndarray, T2: np.ndarray, points: np.ndarray) -> float:
    """RMS distance between where two transforms put ``points`` (target units)."""
    return _rms(apply(T1, points) - apply(T2, points))


def _rms(vectors: np.ndarray) -> float:
    """Root mean square length of (N, 3) ``vectors``."""
    return float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1))))


#: below this many shared sample points on a side, that side's rival test uses the whole source sample
MIN_SHARED_POINTS = 20


@dataclass(frozen=True)
class SharedData:
    """The sample points an answer aligns: of the source, those it moves within the inlier distance
    of the target; of the target, those whose inverse images land within that distance of the source
    (in source units). In a part-inside-whole or low-overlap pair this is the overlap; the rest of
    each cloud says nothing about the alignment."""

    source: np.ndarray
    target: np.ndarray

    @classmethod
    def of(cls, T: np.ndarray, src: Surface, tgt: Surface, distance: float) -> SharedData:
        """Proximity alone (no normal test), at ``distance`` in target units as
        :func:`surface_agreement`; nothing is shared if ``T`` is not a similarity."""
        scale_rotation = _scale_rotation(T)
        if scale_rotation is None:
            return cls(src.sample[:0], tgt.sample[:0])
        s, R = scale_rotation
        fwd, _ = surface_matches(apply(T, src.sample), None, tgt.normals, tgt.tree, distance, 0.0)
        back, _ = surface_matches(_pulled_back(T, s, R, tgt.sample), None, src.normals, src.tree, distance / s, 0.0)
        return cls(src.sample[fwd], tgt.sample[back])


def shared_displacement(T: np.ndarray, T_answer: np.ndarray, shared: SharedData, sample: np.ndarray) -> float:
    """How differently ``T`` aligns the data the answer aligns (target units): the larger of the RMS
    distance between where the two put the shared source points and the RMS distance between the
    shared target points and where ``T_answer`` puts the source points ``T`` maps onto them
    (``T_answer T^-1 q - q``). A side with fewer than ``MIN_SHARED_POINTS`` shared points uses the
    whole source ``sample`` instead.

    The plain :func:`displacement` over the whole source sample counts a small turn about a part
    inside a whole as a distinct alignment: the far side of the whole moves a lot, though the shared
    data barely move (measured on the benchmark's part and hard pairs, such near copies of the answer
    were the rivals that held right answers below the confidence threshold).
    """
    enough_source, enough_target = (len(side) >= MIN_SHARED_POINTS for side in (shared.source, shared.target))
    whole = displacement(T, T_answer, sample) if not (enough_source and enough_target) else 0.0
    on_source = displacement(T, T_answer, shared.source) if enough_source else whole
    on_target = (_rms(apply(T_answer, apply(invert(T), shared.target)) - shared.target) if enough_target
                 else whole)
    return max(on_source, on_target)


@dataclass(frozen=True)
class Verdict:
    confidence: float
    score: float  # score of the answer (Agreement.score: agreement less conflicts; can be negative)
    rival_score: float  # best score among distinct alternatives (as computed, so it can be negative; 0 if none)
    agreement: Agreement
    support: float  # share of the independent overlap searches that ended at the answer
    relief_confidence: float = 0.0  # the confidence the relief over the target's dominant plane gives (decide)
    sample_points: int = 0  # points in the smaller of the two samples the score was measured on (0: not known)
    sample_weight: float = 1.0  # the factor :func:`sample_weight` applied to both confidences (1: not sparse)


def sample_weight(n_points: int, full_points: int) -> float:
    """The factor ``min(1, sqrt(n_points / full_points))`` by which a verdict measured on only
    ``n_points`` sample points a cloud scales its confidence (1 when ``full_points`` is 0).

    Scores are shares of sample points, so their noise grows like ``1 / sqrt(n)``: the confidence
    threshold was calibrated on samples of ``full_points`` (``verdict.sample_points``) or more, and on
    a cloud of a few hundred points the same lead is a fraction of the evidence. Without it, random
    subsets of 300-800 points of the shipped models came back ``ok`` but wrong (half-turns, tens of
    degrees off) in 10 of 144 pairs (``data_scripts/probe_pairs.py``; docs/how-it-works.md)."""
    if full_points <= 0 or n_points >= full_points:
        return 1.0
    return float(np.sqrt(max(n_points, 0) / full_points))


def confidence(score: float, rival_score: float, full_margin: float) -> float:
    """Confidence in [0, 1] of an answer with score ``score`` whose best distinct rival scores
    ``rival_score``: the answer's lead over the rival — or over 0, the score of putting the source
    nowhere near the target, when the rival scores less —, ``(score - max(rival_score, 0)) /
    full_margin``, clipped to [0, 1].

    0 means another transform explains the data as well as the answer (or better), or the answer
    lays more of the clouds beside each other than on each other (a score below 0 is no evidence
    for it, however much worse the rivals are); 1 means the answer's score leads anything else the
    search found by at least ``full_margin``. A lead rather than a ratio: on sparse, noisy or
    low-overlap data every agreement is small, and a small answer with nothing near it is still a
    clear answer.
    """
    return float(np.clip((score - max(rival_score, 0.0)) / full_margin, 0.0, 1.0))
