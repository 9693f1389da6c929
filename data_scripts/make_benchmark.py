"""Shipped data and synthetic cross-source registration benchmark for gctr.

Three subcommands (``python -m data_scripts.make_benchmark --help``):

``ship``
    Build the small real data committed under ``data/`` from the shared raw data
    (Stanford bunny/dragon, 3DMatch redkitchen): three "models" and six down-sampled raw bunny scans
    with their poses. See ``data/ATTRIBUTION.md``.

``generate``
    Synthetic cross-source pairs in the way of the GCTR paper (which follows CSGM): from a model cloud
    ``M`` draw a source and a target that differ in density, noise, outliers, partial overlap (two
    different planar crops) and a random similarity ``T_gt`` with ``target ≈ T_gt @ source``.
    Optionally (``--real``) pairs of real raw range scans with their true relative pose, made
    cross-source by a random similarity on the source and a 1/4 density target.

    Levels (``--levels``): ``easy``, ``cross``, ``hard`` (two planar crops of a model, see ``LEVELS``),
    ``real`` (= ``--real``: the 6 real bunny scan pairs drawn 3 times each, 6 dragon scan pairs from ``--shared``
drawn twice, the 6 shipped bunny scans against the bunny reconstruction: 36 pairs), and, for issue 9:

    * ``part`` — a compact patch (the points of a Euclidean ball around a random model point holding
      15–40 % of the model) against the whole model at 1/4 density; 0.5 % noise, 10 % outliers, scale
      0.5–2. Even ``k``: the patch is the source; odd ``k``: the patch is the target (manifest columns
      ``patch`` = source/target and ``patch_fraction``).
    * ``lowoverlap`` — two slab crops sliding along a random direction sharing 25–50 % of their points,
      target at 1/4 density, 0.5 % noise, 5–10 % outliers.
    * ``sfm`` — photogrammetry-like target (density varying 20x across the surface, 2–4 holes, noise
      1 % along a random viewing direction and 0.2 % across, 5–10 % floaters in a few blobs near the
      surface) against a clean-ish scan-like crop (70–100 % of the model, 0.25 % noise).
    * ``scene`` — from the shared data (``--shared``, default ``shared/data`` beside the repository):
      two overlapping windows (25–60 % mutual overlap, horizontal slabs for the LiDAR sweep) of each of
      the 3DMatch redkitchen fragments 0 and 4 and of the NCLT sweep, with target density 1/4–1/2,
      noise 0.3–0.5 % of the window diagonal, 5 % outliers, scale 0.5–2 (``--pairs-per-model`` window
      pairs per scene); plus two draws of the real redkitchen pair (fragment 0 moved by a random
      similarity as source, fragment 4 as target, truth from ``gt.log``).

``demo``
    A small set (6 synthetic ``cross`` pairs + 2 real scan pairs) in a few seconds; ``make demo``.

Randomness: every pair draws from its own ``np.random.default_rng([seed, level_index, model_key, k])``
(``model_key`` = CRC32 of the model name, so a pair does not depend on which other models or levels
are generated in the same call). The same command gives byte-identical files.

Tuning set and report set: the engine is tuned on ``--seed 1`` and reported on ``--seed 0`` (the
default), so the committed reports (bench/ENGINE.md, bench/RESULTS.md) are measured on pairs the
engine's parameters were not chosen on:

    python -m data_scripts.make_benchmark generate --levels easy,cross,hard,real,part,lowoverlap,sfm,scene \
        --seed 1 --out bench/work/data-seed1     # tuning set
    python -m data_scripts.make_benchmark generate --levels easy,cross,hard,real,part,lowoverlap,sfm,scene \
        --seed 0 --out bench/work/data           # report set

Matrix convention (GUIDE §1): ``T = [[s R, t], [0 0 0 1]]`` maps the source onto the target.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import zlib
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from data_scripts.common import (
    FORMATS,
    bbox_diagonal,
    read_pose_file,
    remove_isolated,
    voxel_downsample_to_count,
    write_ply_float32,
    write_points,
)
from gctr_cli.geometry import apply, invert, random_rotation, to_matrix
from gctr_cli.io import PointCloudError, load_point_cloud, write_matrix

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT / "data"
DEFAULT_MODELS = tuple(DATA_DIR / "models" / f"{m}.ply" for m in ("bunny", "dragon", "redkitchen"))
MANIFEST_COLUMNS = ["pair_id", "source", "target", "gt", "model", "level", "scale_gt", "overlap_src", "overlap_tgt",
                    "patch", "patch_fraction"]  # patch: level part only, which side is the patch


# ============================================================================================ levels
@dataclass(frozen=True)
class Level:
    """One named difficulty: every fraction is of the point count, noise is relative to the model diagonal."""

    name: str
    density: float  # target point count / source point count
    noise: float  # Gaussian sigma as a fraction of the model's bounding-box diagonal
    outliers: float  # outlier fraction of each cloud's final point count
    crop_lo: float  # each cloud keeps a fraction in [crop_lo, crop_hi] of the model's points
    crop_hi: float
    s_lo: float  # ground-truth scale, log-uniform in [s_lo, s_hi]
    s_hi: float
    t_radius: float = 1.0  # translation uniform in a ball of this radius x model diagonal


LEVELS: dict[str, Level] = {
    lv.name: lv
    for lv in (
        Level("easy", density=1 / 2, noise=0.0025, outliers=0.0, crop_lo=0.9, crop_hi=1.0, s_lo=0.5, s_hi=2.0),
        Level("cross", density=1 / 4, noise=0.005, outliers=0.10, crop_lo=0.7, crop_hi=0.9, s_lo=0.5, s_hi=2.0),
        Level("hard", density=1 / 8, noise=0.01, outliers=0.30, crop_lo=0.5, crop_hi=0.9, s_lo=0.25, s_hi=4.0),
    )
}
LEVEL_INDEX = {"easy": 0, "cross": 1, "hard": 2, "real": 3, "part": 4, "lowoverlap": 5, "sfm": 6, "scene": 7}

# Real scan pairs (source, target): partial overlaps 0.5-0.9 (table in the shared bunny SOURCE.md).
REAL_PAIRS = (
    ("bun045", "bun000"),
    ("bun090", "bun045"),
    ("bun315", "bun000"),
    ("chin", "bun315"),
    ("top3", "bun000"),
    ("top3", "bun045"),
)
# Level real (issue 9: >= 30 pairs from >= 3 groups): every bunny scan pair drawn REAL_DRAWS times (another
# random similarity and subsampling each time; draw 0 is the pair of earlier versions), REAL_DRAGON_PAIRS
# of raw dragon scans (24 deg apart, overlaps 0.6-0.9, from --shared) drawn REAL_DRAWS_DRAGON times, and
# each shipped bunny scan against the bunny reconstruction (data/models/bunny.ply, world frame).
REAL_DRAWS = 3
REAL_DRAGON_PAIRS = tuple((f"dragonStandRight_{a}", f"dragonStandRight_{b}")
                          for a, b in ((24, 0), (72, 48), (120, 96), (168, 144), (216, 192), (264, 240)))
REAL_DRAWS_DRAGON = 2
DRAGON_SCANS = "stanford/dragon/scans"
DRAGON_POSES = "dragonStandRight_poses_world_from_scan.txt"
REAL_LEVEL = Level("real", density=1 / 4, noise=0.0, outliers=0.0, crop_lo=1.0, crop_hi=1.0, s_lo=0.5, s_hi=2.0)


@dataclass(frozen=True)
class Pair:
    """A generated pair: ``target ≈ apply(T_gt, source)`` for the inlier points."""

    source: np.ndarray
    target: np.ndarray
    T_gt: np.ndarray
    src_outlier: np.ndarray  # bool mask over source points
    tgt_outlier: np.ndarray  # bool mask over target points
    overlap_src: float  # fraction of source inliers whose model point is also in the target's crop
    overlap_tgt: float  # fraction of target inliers whose model point is also in the source's crop

    @property
    def scale(self) -> float:
        return float(np.cbrt(np.linalg.det(self.T_gt[:3, :3])))


def pair_rng(seed: int, level: str, model: str, k: int) -> np.random.Generator:
    """The generator of one pair, independent of which other pairs are generated."""
    return np.random.default_rng([seed, LEVEL_INDEX[level], zlib.crc32(model.encode("utf-8")), k])


# ============================================================================================ steps
def crop_by_plane(points: np.ndarray, keep: float, rng: np.random.Generator) -> np.ndarray:
    """Boolean mask keeping the fraction ``keep`` of the points on one side of a random plane.

    The plane normal is uniform on the sphere; its offset is the ``keep`` quantile of the projections.
    """
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    if keep >= 1.0:
        return np.ones(len(points), dtype=bool)
    proj = points @ direction
    return proj <= np.quantile(proj, keep)


def downsample(n_points: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``min(n, n_points)`` points drawn without replacement (random order)."""
    return rng.choice(n_points, size=min(n, n_points), replace=False)


def add_noise(points: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Isotropic Gaussian noise of standard deviation ``sigma`` on every coordinate."""
    return points + rng.normal(scale=sigma, size=points.shape) if sigma > 0 else points.copy()


def add_outliers(
    points: np.ndarray, fraction: float, rng: np.random.Generator, margin: float = 0.10
) -> tuple[np.ndarray, np.ndarray]:
    """Append outliers making up ``fraction`` of the final count, uniform in the bounding box of
    ``points`` enlarged by ``margin`` (of its extent, around its centre); then shuffle.

    Returns ``(points, is_outlier mask)``.
    """
    n_out = int(round(fraction * len(points) / (1.0 - fraction))) if fraction > 0 else 0
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * (1.0 + margin)
    outliers = rng.uniform(centre - half, centre + half, size=(n_out, 3))
    allpts = np.vstack([points, outliers])
    is_out = np.r_[np.zeros(len(points), dtype=bool), np.ones(n_out, dtype=bool)]
    order = rng.permutation(len(allpts))
    return allpts[order], is_out[order]


def random_similarity(rng: np.random.Generator, s_lo: float, s_hi: float, t_radius: float) -> np.ndarray:
    """4x4 similarity: rotation uniform on SO(3), scale log-uniform in [s_lo, s_hi],
    translation uniform in the ball of radius ``t_radius``."""
    rot = random_rotation(rng)
    scale = float(np.exp(rng.uniform(np.log(s_lo), np.log(s_hi))))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    trans = direction * t_radius * rng.uniform() ** (1.0 / 3.0)
    return to_matrix(scale, rot, trans)


# ============================================================================================ pairs
def make_pair(model: np.ndarray, level: Level, rng: np.random.Generator, n_source: int = 20000) -> Pair:
    """One synthetic cross-source pair from the model cloud ``model`` (see the module docstring).

    target = crop_t(M) -> downsample to density x n_src -> noise -> outliers   (stays in the model frame)
    source = crop_s(M) -> downsample to n_src -> noise -> outliers -> moved by inv(T_gt)

    ``n_src`` is chosen so that the source has ``n_source`` points *including* its outliers (fewer if
    the crop has fewer points; never duplicated); both clouds get the same outlier fraction, so the
    final count ratio target/source is ``level.density`` up to rounding.
    """
    diag = bbox_diagonal(model)
    sigma = level.noise * diag
    T_gt = random_similarity(rng, level.s_lo, level.s_hi, level.t_radius * diag)

    crop_s = crop_by_plane(model, rng.uniform(level.crop_lo, level.crop_hi), rng)
    crop_t = crop_by_plane(model, rng.uniform(level.crop_lo, level.crop_hi), rng)
    n_src_inliers = int(round(n_source * (1.0 - level.outliers)))  # outliers included, the source has n_source points
    idx_s = np.flatnonzero(crop_s)[downsample(int(crop_s.sum()), n_src_inliers, rng)]
    n_tgt = int(round(level.density * len(idx_s)))
    idx_t = np.flatnonzero(crop_t)[downsample(int(crop_t.sum()), n_tgt, rng)]

    src, src_out = add_outliers(add_noise(model[idx_s], sigma, rng), level.outliers, rng)
    tgt, tgt_out = add_outliers(add_noise(model[idx_t], sigma, rng), level.outliers, rng)
    src = apply(invert(T_gt), src)
    return Pair(
        source=src,
        target=tgt,
        T_gt=T_gt,
        src_outlier=src_out,
        tgt_outlier=tgt_out,
        overlap_src=float(crop_t[idx_s].mean()),
        overlap_tgt=float(crop_s[idx_t].mean()),
    )


def make_real_pair(
    src_scan: np.ndarray,
    tgt_scan: np.ndarray,
    pose_src: np.ndarray,
    pose_tgt: np.ndarray,
    rng: np.random.Generator,
    n_source: int = 20000,
    level: Level = REAL_LEVEL,
) -> Pair:
    """A real scan pair made cross-source.

    The rigid truth is ``inv(pose_tgt) @ pose_src`` (scan frames, poses are world_from_scan). The source
    is subsampled to ``min(n_source, len)`` points and moved by a random similarity ``A`` (scale
    log-uniform in [s_lo, s_hi], uniform rotation, translation in a ball of 1 x the scan diagonal); the
    target is subsampled to ``density`` x the source count. No synthetic noise or outliers (real scans).
    Then ``T_gt = inv(pose_tgt) @ pose_src @ inv(A)``.
    """
    from scipy.spatial import cKDTree

    rigid = invert(pose_tgt) @ pose_src
    A = random_similarity(rng, level.s_lo, level.s_hi, level.t_radius * bbox_diagonal(src_scan))
    idx_s = downsample(len(src_scan), n_source, rng)
    idx_t = downsample(len(tgt_scan), int(round(level.density * len(idx_s))), rng)

    # overlap: points within 2x the median point spacing of the other scan, both in the target frame
    src_in_t = apply(rigid, src_scan)
    tree_t, tree_s = cKDTree(tgt_scan), cKDTree(src_in_t)
    spacing_t = np.median(tree_t.query(tgt_scan, k=2)[0][:, 1])
    spacing_s = np.median(tree_s.query(src_in_t, k=2)[0][:, 1])
    overlap_src = float((tree_t.query(src_in_t[idx_s])[0] < 2 * spacing_t).mean())
    overlap_tgt = float((tree_s.query(tgt_scan[idx_t])[0] < 2 * spacing_s).mean())

    return Pair(
        source=apply(A, src_scan[idx_s]),
        target=tgt_scan[idx_t].copy(),
        T_gt=rigid @ invert(A),
        src_outlier=np.zeros(len(idx_s), dtype=bool),
        tgt_outlier=np.zeros(len(idx_t), dtype=bool),
        overlap_src=overlap_src,
        overlap_tgt=overlap_tgt,
    )


# ============================================================================================ new levels (issue 9)
# Parameters of the levels that are not a pair of planar crops. Fractions are of point counts, noise is
# relative to the model's (or scene window's) bounding-box diagonal.
PART = dict(frac_lo=0.15, frac_hi=0.40, density=1 / 4, noise=0.005, outliers=0.10, s_lo=0.5, s_hi=2.0)
LOWOVERLAP = dict(ov_lo=0.25, ov_hi=0.50, span_lo=0.8, span_hi=1.0, density=1 / 4, noise=0.005,
                  out_lo=0.05, out_hi=0.10, s_lo=0.5, s_hi=2.0)
SFM = dict(density_range=20.0, holes_lo=2, holes_hi=4, hole_lo=0.03, hole_hi=0.08, noise_depth=0.01,
           noise_across=0.002, floaters_lo=0.05, floaters_hi=0.10, blobs_lo=3, blobs_hi=6, blob_sigma=0.01,
           blob_offset=0.03, density=1 / 2, src_crop_lo=0.7, src_crop_hi=1.0, src_noise=0.0025, s_lo=0.5, s_hi=2.0)
SCENE = dict(ov_lo=0.25, ov_hi=0.60, span_lo=0.8, span_hi=1.0, dens_lo=1 / 4, dens_hi=1 / 2, noise_lo=0.003,
             noise_hi=0.005, outliers=0.05, s_lo=0.5, s_hi=2.0, windows_per_scene=10, real_pairs=2)
# Scenes of the `scene` level (paths relative to the shared data folder) and the real 3DMatch pair.
SCENE_FILES = {
    "redkitchen0": "real/3dmatch_redkitchen/cloud_bin_0.ply",
    "redkitchen4": "real/3dmatch_redkitchen/cloud_bin_4.ply",
    "nclt": "real/nclt_lidar/scan_1326652795280148.ply",
}
SCENE_UP = {"nclt": np.array([0.0, 0.0, 1.0])}  # windows slide horizontally in the LiDAR sweep (z up)
KITCHEN_GT_LOG = "real/3dmatch_redkitchen/gt.log"
SPECIAL_LEVELS = ("part", "lowoverlap", "sfm")  # synthetic from the models, not planar-crop levels
ALL_LEVELS = (*LEVELS, "real", *SPECIAL_LEVELS, "scene")


def _unit(rng: np.random.Generator, plane_normal: np.ndarray | None = None) -> np.ndarray:
    """A direction uniform on the sphere (or on the circle perpendicular to ``plane_normal``)."""
    d = rng.normal(size=3)
    if plane_normal is not None:
        d -= (d @ plane_normal) * plane_normal
    return d / np.linalg.norm(d)


def ball_crop(points: np.ndarray, centre: np.ndarray, fraction: float) -> np.ndarray:
    """Mask of the points within the Euclidean ball around ``centre`` whose radius is the ``fraction``
    quantile of the distances (so the ball holds that fraction of the points)."""
    d = np.linalg.norm(points - centre, axis=1)
    return d <= np.quantile(d, fraction)


def slab_pair(points: np.ndarray, overlap: float, span: float, rng: np.random.Generator,
              plane_normal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Two slab crops sliding along a random direction that overlap by ``overlap`` of each one's points.

    In quantile space of the projections: each slab holds ``w`` of the points, the second starts
    ``w (1 - overlap)`` after the first, together they span ``span = w (2 - overlap)`` of the points,
    placed at a random offset. So the shared points are ``overlap`` of either slab.
    """
    direction = _unit(rng, plane_normal)
    w = span / (2.0 - overlap)
    start = rng.uniform(0.0, 1.0 - span)
    proj = points @ direction
    q = np.quantile(proj, [start, start + w, start + w * (1 - overlap), start + span])
    a = (proj >= q[0]) & (proj <= q[1])
    b = (proj >= q[2]) & (proj <= q[3])
    return a, b


def _finish_pair(model: np.ndarray, idx_s: np.ndarray, idx_t: np.ndarray, src: np.ndarray, tgt: np.ndarray,
                 src_out: np.ndarray, tgt_out: np.ndarray, in_s: np.ndarray, in_t: np.ndarray,
                 T_gt: np.ndarray) -> Pair:
    """Move the source by inv(T_gt); overlaps from the model-point masks of the two clouds."""
    return Pair(source=apply(invert(T_gt), src), target=tgt, T_gt=T_gt, src_outlier=src_out,
                tgt_outlier=tgt_out, overlap_src=float(in_t[idx_s].mean()), overlap_tgt=float(in_s[idx_t].mean()))


def make_part_pair(model: np.ndarray, rng: np.random.Generator, patch_is_source: bool,
                   n_source: int = 20000, p: dict = PART) -> tuple[Pair, float]:
    """Part in whole: a compact patch (the points of a ball around a random model point holding 15-40 %
    of the model) against the whole model at 1/4 of the patch's density; both with 0.5 % noise and 10 %
    uniform outliers. ``patch_is_source`` chooses which side the patch is. Returns (pair, patch fraction).

    The patch keeps up to ``n_source`` x (1 - outliers) of its points; the whole keeps 1/4 of the model's
    points at that same sampling rate.
    """
    diag = bbox_diagonal(model)
    sigma = p["noise"] * diag
    T_gt = random_similarity(rng, p["s_lo"], p["s_hi"], diag)
    fraction = rng.uniform(p["frac_lo"], p["frac_hi"])
    ball = ball_crop(model, model[rng.integers(len(model))], fraction)
    n_patch_in = int(round(n_source * (1.0 - p["outliers"])))
    idx_p = np.flatnonzero(ball)[downsample(int(ball.sum()), n_patch_in, rng)]
    rate = len(idx_p) / ball.sum()  # sampling rate of the patch; the whole gets density x that rate
    idx_w = downsample(len(model), int(round(p["density"] * rate * len(model))), rng)
    patch, patch_out = add_outliers(add_noise(model[idx_p], sigma, rng), p["outliers"], rng)
    whole, whole_out = add_outliers(add_noise(model[idx_w], sigma, rng), p["outliers"], rng)
    everything = np.ones(len(model), dtype=bool)
    if patch_is_source:
        pair = _finish_pair(model, idx_p, idx_w, patch, whole, patch_out, whole_out, ball, everything, T_gt)
    else:
        pair = _finish_pair(model, idx_w, idx_p, whole, patch, whole_out, patch_out, everything, ball, T_gt)
    return pair, float(fraction)


def make_lowoverlap_pair(model: np.ndarray, rng: np.random.Generator, n_source: int = 20000,
                         p: dict = LOWOVERLAP) -> Pair:
    """Low mutual overlap: two slab crops of the model sliding along a random direction that share 25-50 %
    of their points (see ``slab_pair``), target at 1/4 density, 0.5 % noise, 5-10 % uniform outliers."""
    diag = bbox_diagonal(model)
    sigma = p["noise"] * diag
    T_gt = random_similarity(rng, p["s_lo"], p["s_hi"], diag)
    overlap = rng.uniform(p["ov_lo"], p["ov_hi"])
    crop_s, crop_t = slab_pair(model, overlap, rng.uniform(p["span_lo"], p["span_hi"]), rng)
    outliers = rng.uniform(p["out_lo"], p["out_hi"])
    idx_s = np.flatnonzero(crop_s)[downsample(int(crop_s.sum()), int(round(n_source * (1.0 - outliers))), rng)]
    idx_t = np.flatnonzero(crop_t)[downsample(int(crop_t.sum()), int(round(p["density"] * len(idx_s))), rng)]
    src, src_out = add_outliers(add_noise(model[idx_s], sigma, rng), outliers, rng)
    tgt, tgt_out = add_outliers(add_noise(model[idx_t], sigma, rng), outliers, rng)
    return _finish_pair(model, idx_s, idx_t, src, tgt, src_out, tgt_out, crop_s, crop_t, T_gt)


def smooth_field(points: np.ndarray, rng: np.random.Generator, n_waves: int = 4) -> np.ndarray:
    """A smooth random function of position scaled to [0, 1] over ``points``: a sum of ``n_waves`` plane
    waves with 0.5-1.5 periods across the bounding-box diagonal."""
    diag = bbox_diagonal(points)
    x = points - points.mean(axis=0)
    f = np.zeros(len(points))
    for _ in range(n_waves):
        k = _unit(rng) * rng.uniform(0.5, 1.5) * 2 * np.pi / diag
        f += np.cos(x @ k + rng.uniform(0, 2 * np.pi))
    return (f - f.min()) / (f.max() - f.min())


def anisotropic_noise(n: int, camera: np.ndarray, sigma_depth: float, sigma_across: float,
                      rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` Gaussian noise with standard deviation ``sigma_depth`` along the unit vector ``camera``
    (the viewing direction) and ``sigma_across`` perpendicular to it."""
    noise = rng.normal(scale=sigma_across, size=(n, 3))
    extra = np.sqrt(max(sigma_depth**2 - sigma_across**2, 0.0))
    return noise + np.outer(rng.normal(scale=extra, size=n), camera)


def clustered_floaters(surface: np.ndarray, n: int, diag: float, rng: np.random.Generator,
                       p: dict = SFM) -> np.ndarray:
    """``n`` floaters in a few Gaussian blobs (sigma ``blob_sigma`` x diag) whose centres sit
    ``blob_offset`` x diag (in a random direction) off random surface points."""
    n_blobs = int(rng.integers(p["blobs_lo"], p["blobs_hi"] + 1))
    centres = surface[rng.choice(len(surface), n_blobs, replace=False)]
    centres = centres + np.array([_unit(rng) for _ in range(n_blobs)]) * p["blob_offset"] * diag
    which = rng.integers(n_blobs, size=n)
    return centres[which] + rng.normal(scale=p["blob_sigma"] * diag, size=(n, 3))


def make_sfm_pair(model: np.ndarray, rng: np.random.Generator, n_source: int = 20000, p: dict = SFM) -> Pair:
    """Photogrammetry-like target against a clean-ish scan-like source.

    target: keep each model point with probability ``20 ** (f(x) - 1)`` for a smooth random field
    ``f`` in [0, 1] (local density varies 20x across the surface), remove 2-4 holes (balls around random
    model points holding 3-8 % of the points each), subsample to 1/2 of the source count if larger,
    anisotropic noise (sigma 1 % of the diagonal along a random "camera" direction, 0.2 % across) and
    5-10 % floaters clustered in 3-6 small blobs near the surface (``clustered_floaters``).
    source: a planar crop keeping 70-100 % of the model, up to ``n_source`` points, 0.25 % isotropic noise,
    no outliers.
    """
    diag = bbox_diagonal(model)
    T_gt = random_similarity(rng, p["s_lo"], p["s_hi"], diag)

    crop_s = crop_by_plane(model, rng.uniform(p["src_crop_lo"], p["src_crop_hi"]), rng)
    idx_s = np.flatnonzero(crop_s)[downsample(int(crop_s.sum()), n_source, rng)]
    src = add_noise(model[idx_s], p["src_noise"] * diag, rng)

    keep_prob = p["density_range"] ** (smooth_field(model, rng) - 1.0)
    keep = rng.uniform(size=len(model)) < keep_prob
    covered = np.ones(len(model), dtype=bool)  # outside the holes: the part of the model the target covers
    for _ in range(int(rng.integers(p["holes_lo"], p["holes_hi"] + 1))):
        covered &= ~ball_crop(model, model[rng.integers(len(model))], rng.uniform(p["hole_lo"], p["hole_hi"]))
    cand = np.flatnonzero(keep & covered)
    floaters = rng.uniform(p["floaters_lo"], p["floaters_hi"])
    n_t = int(round(p["density"] * len(idx_s) * (1.0 - floaters)))
    idx_t = cand[downsample(len(cand), n_t, rng)] if len(cand) > n_t else rng.permutation(cand)
    tgt = model[idx_t] + anisotropic_noise(len(idx_t), _unit(rng), p["noise_depth"] * diag,
                                           p["noise_across"] * diag, rng)
    n_float = int(round(floaters * len(tgt) / (1.0 - floaters)))
    allpts = np.vstack([tgt, clustered_floaters(model, n_float, diag, rng, p)])
    is_out = np.r_[np.zeros(len(tgt), dtype=bool), np.ones(n_float, dtype=bool)]
    order = rng.permutation(len(allpts))
    return _finish_pair(model, idx_s, idx_t, src, allpts[order], np.zeros(len(src), dtype=bool), is_out[order],
                        crop_s, covered, T_gt)


def make_scene_window_pair(scene: np.ndarray, rng: np.random.Generator, n_source: int = 20000,
                           up: np.ndarray | None = None, p: dict = SCENE) -> Pair:
    """Two overlapping windows of a real scene (slab crops sharing 25-60 % of their points, sliding along
    a random direction, horizontal when ``up`` is given) made cross-source: target density 1/4-1/2 of
    the source, noise 0.3-0.5 % of the source window's bounding-box diagonal, 5 % uniform outliers,
    random similarity (scale 0.5-2, translation within one scene diagonal)."""
    diag = bbox_diagonal(scene)
    T_gt = random_similarity(rng, p["s_lo"], p["s_hi"], diag)
    overlap = rng.uniform(p["ov_lo"], p["ov_hi"])
    crop_s, crop_t = slab_pair(scene, overlap, rng.uniform(p["span_lo"], p["span_hi"]), rng, up)
    sigma = rng.uniform(p["noise_lo"], p["noise_hi"]) * bbox_diagonal(scene[crop_s])
    density = float(np.exp(rng.uniform(np.log(p["dens_lo"]), np.log(p["dens_hi"]))))
    idx_s = np.flatnonzero(crop_s)[downsample(int(crop_s.sum()), int(round(n_source * (1.0 - p["outliers"]))), rng)]
    idx_t = np.flatnonzero(crop_t)[downsample(int(crop_t.sum()), int(round(density * len(idx_s))), rng)]
    src, src_out = add_outliers(add_noise(scene[idx_s], sigma, rng), p["outliers"], rng)
    tgt, tgt_out = add_outliers(add_noise(scene[idx_t], sigma, rng), p["outliers"], rng)
    return _finish_pair(scene, idx_s, idx_t, src, tgt, src_out, tgt_out, crop_s, crop_t, T_gt)


def read_gt_log(path: Path, i: int, j: int) -> np.ndarray:
    """The 4x4 of block ``i j`` of a 3DMatch ``gt.log`` (maps fragment ``j`` into fragment ``i``'s frame)."""
    lines = [ln.split() for ln in Path(path).read_text().splitlines() if ln.strip()]
    for b in range(0, len(lines) - 4, 5):
        if int(lines[b][0]) == i and int(lines[b][1]) == j:
            return np.array(lines[b + 1:b + 5], dtype=np.float64)
    raise ValueError(f"{path}: no block for fragments {i} {j}")


def default_shared() -> Path | None:
    """``shared/data`` beside the repository, if it exists."""
    folder = REPO_ROOT.parent / "shared" / "data"
    return folder if folder.is_dir() else None


def load_scenes(shared: Path | None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The scenes of the `scene` level and ``T_4to0`` (from gt.log); a clear error naming a missing file."""
    if shared is None:
        raise click.UsageError("level 'scene' needs the shared data folder: pass --shared (e.g. ../shared/data)")
    needed = [*SCENE_FILES.values(), KITCHEN_GT_LOG]
    missing = [str(Path(shared) / rel) for rel in needed if not (Path(shared) / rel).is_file()]
    if missing:
        raise click.UsageError(f"level 'scene': missing shared data file(s): {', '.join(missing)}")
    scenes = {name: load_point_cloud(Path(shared) / rel) for name, rel in SCENE_FILES.items()}
    return scenes, read_gt_log(Path(shared) / KITCHEN_GT_LOG, 0, 4)


def generate_special(models: dict[str, np.ndarray], levels: list[str], pairs_per_model: int, seed: int, out: Path,
                     formats: list[str], n_source: int = 20000, pcd_encoding: str = "binary") -> list[dict]:
    """Write the levels ``part``, ``lowoverlap``, ``sfm`` (those of them in ``levels``); return the rows.

    ``part``: even k -> the patch is the source, odd k -> the patch is the target (column ``patch``).
    """
    combined = []
    for level_name in [lv for lv in levels if lv in SPECIAL_LEVELS]:
        rows: list[dict] = []
        for model_name, model in models.items():
            for k in range(pairs_per_model):
                rng = pair_rng(seed, level_name, model_name, k)
                extra = {}
                if level_name == "part":
                    pair, fraction = make_part_pair(model, rng, patch_is_source=(k % 2 == 0), n_source=n_source)
                    extra = {"patch": "source" if k % 2 == 0 else "target", "patch_fraction": f"{fraction:.4f}"}
                elif level_name == "lowoverlap":
                    pair = make_lowoverlap_pair(model, rng, n_source)
                else:
                    pair = make_sfm_pair(model, rng, n_source)
                fmt = formats[len(rows) % len(formats)]
                row = write_pair(out / level_name, f"{level_name}_{model_name}_{k}", pair, fmt, pcd_encoding)
                rows.append({**row, "model": model_name, "level": level_name, **extra})
        combined += _write_level(out, level_name, rows)
        log.info("level %s: %d pairs", level_name, len(rows))
    return combined


def generate_scene(scenes: dict[str, np.ndarray], T_4to0: np.ndarray, seed: int, out: Path, formats: list[str],
                   n_source: int = 20000, windows_per_scene: int = int(SCENE["windows_per_scene"]),
                   real_pairs: int = int(SCENE["real_pairs"]), pcd_encoding: str = "binary",
                   noise: tuple[float, float] | None = None) -> list[dict]:
    """Level ``scene``: ``windows_per_scene`` window pairs per scene + ``real_pairs`` draws of the real
    3DMatch redkitchen pair (source fragment 0 moved by a random similarity, target fragment 4 at 1/4-1/2
    density, truth ``inv(T_4to0) @ inv(A)``). ``noise``: the windows' noise range as fractions of the
    window diagonal instead of the level's 0.3-0.5 % (e.g. sensor-like 0.0002-0.0003, about 2-4 cm on the
    NCLT windows), for measuring the engine away from the level's cross-source noise."""
    p = SCENE if noise is None else {**SCENE, "noise_lo": noise[0], "noise_hi": noise[1]}
    rows: list[dict] = []
    for name, scene in scenes.items():
        for k in range(windows_per_scene):
            pair = make_scene_window_pair(scene, pair_rng(seed, "scene", name, k), n_source, SCENE_UP.get(name), p)
            fmt = formats[len(rows) % len(formats)]
            row = write_pair(out / "scene", f"scene_{name}_{k}", pair, fmt, pcd_encoding)
            rows.append({**row, "model": name, "level": "scene"})
    for k in range(real_pairs):
        rng = pair_rng(seed, "scene", "redkitchen0>4", k)
        density = float(np.exp(rng.uniform(np.log(SCENE["dens_lo"]), np.log(SCENE["dens_hi"]))))
        level = dataclasses.replace(REAL_LEVEL, density=density, s_lo=SCENE["s_lo"], s_hi=SCENE["s_hi"])
        pair = make_real_pair(scenes["redkitchen0"], scenes["redkitchen4"], np.eye(4), T_4to0, rng, n_source, level)
        fmt = formats[len(rows) % len(formats)]
        row = write_pair(out / "scene", f"scene_redkitchen_0to4_{k}", pair, fmt, pcd_encoding)
        rows.append({**row, "model": "redkitchen0>4", "level": "scene"})
    log.info("level scene: %d pairs", len(rows))
    return _write_level(out, "scene", rows)


# ============================================================================================ writing
def write_pair(folder: Path, pair_id: str, pair: Pair, fmt: str, pcd_encoding: str = "binary") -> dict:
    """Write ``<pair_id>_src.<fmt>``, ``<pair_id>_tgt.<fmt>``, ``<pair_id>_gt.txt``; return the manifest row
    (paths relative to ``folder``)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = {"source": f"{pair_id}_src.{fmt}", "target": f"{pair_id}_tgt.{fmt}", "gt": f"{pair_id}_gt.txt"}
    write_points(folder / names["source"], pair.source, pcd_encoding=pcd_encoding)
    write_points(folder / names["target"], pair.target, pcd_encoding=pcd_encoding)
    write_matrix(folder / names["gt"], pair.T_gt)
    return {
        "pair_id": pair_id,
        **names,
        "scale_gt": f"{pair.scale:.17g}",
        "overlap_src": f"{pair.overlap_src:.4f}",
        "overlap_tgt": f"{pair.overlap_tgt:.4f}",
    }


def write_manifest(path: Path, rows: list[dict]) -> None:
    ids = [r["pair_id"] for r in rows]
    if len(set(ids)) != len(ids):
        raise ValueError(f"duplicate pair_id in {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=MANIFEST_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)


def _write_level(out: Path, level: str, rows: list[dict]) -> list[dict]:
    """Write ``<out>/<level>/pairs.csv``; return the rows with paths relative to ``out``."""
    write_manifest(out / level / "pairs.csv", rows)
    return [{**r, **{c: f"{level}/{r[c]}" for c in ("source", "target", "gt")}} for r in rows]


def generate_synthetic(
    models: dict[str, np.ndarray],
    levels: list[str],
    pairs_per_model: int,
    seed: int,
    out: Path,
    formats: list[str],
    n_source: int = 20000,
    pcd_encoding: str = "binary",
) -> list[dict]:
    """Write all synthetic levels; return the combined manifest rows (paths relative to ``out``)."""
    combined = []
    for level_name in levels:
        level = LEVELS[level_name]
        rows: list[dict] = []
        for model_name, model in models.items():
            for k in range(pairs_per_model):
                pair = make_pair(model, level, pair_rng(seed, level_name, model_name, k), n_source)
                fmt = formats[len(rows) % len(formats)]
                row = write_pair(out / level_name, f"{level_name}_{model_name}_{k}", pair, fmt, pcd_encoding)
                rows.append({**row, "model": model_name, "level": level_name})
        combined += _write_level(out, level_name, rows)
        log.info("level %s: %d pairs", level_name, len(rows))
    return combined


def load_scans(scans_dir: Path | None = None, shared: Path | None = None) -> tuple[dict, dict]:
    """Scans and world_from_scan poses: the shipped ``data/scans`` by default, or the full-resolution
    raw scans of ``<shared>/stanford/bunny/scans``."""
    names = sorted({n for p in REAL_PAIRS for n in p})
    if shared is not None:
        folder = Path(shared) / "stanford" / "bunny" / "scans"
        poses = read_pose_file(folder / "bun_poses_world_from_scan.txt")
    else:
        folder = Path(scans_dir) if scans_dir is not None else DATA_DIR / "scans"
        poses = read_pose_file(folder / "poses.txt")
    scans = {n: load_point_cloud(folder / f"{n}.ply") for n in names}
    return scans, poses


def generate_real(
    scans: dict,
    poses: dict,
    seed: int,
    out: Path,
    formats: list[str],
    n_source: int = 20000,
    pairs: tuple = REAL_PAIRS,
    pcd_encoding: str = "binary",
) -> list[dict]:
    rows = []
    for k, (s, t) in enumerate(pairs):
        rng = pair_rng(seed, "real", f"{s}>{t}", k)
        pair = make_real_pair(scans[s], scans[t], poses[s], poses[t], rng, n_source)
        fmt = formats[k % len(formats)]
        row = write_pair(out / "real", f"real_{s}_to_{t}", pair, fmt, pcd_encoding)
        rows.append({**row, "model": "bunny_scans", "level": "real"})
    log.info("level real: %d pairs", len(rows))
    return _write_level(out, "real", rows)


def load_dragon_scans(shared: Path | None) -> tuple[dict, dict]:
    """The raw dragon scans of ``REAL_DRAGON_PAIRS`` and their world_from_scan poses, from the shared data."""
    if shared is None:
        raise click.UsageError("level 'real' needs the shared data folder for the dragon scans: pass --shared")
    folder = Path(shared) / DRAGON_SCANS
    names = sorted({n for p in REAL_DRAGON_PAIRS for n in p})
    needed = [folder / DRAGON_POSES, *(folder / f"{n}.ply" for n in names)]
    missing = [str(f) for f in needed if not f.is_file()]
    if missing:
        raise click.UsageError(f"level 'real': missing shared data file(s): {', '.join(missing)}")
    return {n: load_point_cloud(folder / f"{n}.ply") for n in names}, read_pose_file(folder / DRAGON_POSES)


def generate_real_all(scans: dict, poses: dict, dragon_scans: dict, dragon_poses: dict, recon: np.ndarray, seed: int,
                      out: Path, formats: list[str], n_source: int = 20000, pcd_encoding: str = "binary",
                      draws: int = REAL_DRAWS, dragon_draws: int = REAL_DRAWS_DRAGON,
                      per_group: int | None = None) -> list[dict]:
    """Level ``real`` (see ``REAL_DRAWS``): bunny scan pairs x ``draws``, dragon scan pairs x ``dragon_draws``,
    bunny scan -> reconstruction pairs; model column ``bunny_scans`` / ``dragon_scans`` / ``bunny_scan2recon``.
    ``per_group``: only the first that many pairs of each group (quick runs); a pair does not change."""
    jobs = []  # (rng, pair id, model, src, tgt, pose_src, pose_tgt)
    for d in range(draws):
        for k, (s, t) in enumerate(REAL_PAIRS):
            key = f"{s}>{t}" if d == 0 else f"{s}>{t}#{d}"
            jobs.append((pair_rng(seed, "real", key, k), f"real_{s}_to_{t}" + (f"_d{d}" if d else ""), "bunny_scans",
                         scans[s], scans[t], poses[s], poses[t]))
    for d in range(dragon_draws):
        for k, (s, t) in enumerate(REAL_DRAGON_PAIRS):
            short = f"{s.rsplit('_', 1)[1]}_to_{t.rsplit('_', 1)[1]}"
            jobs.append((pair_rng(seed, "real", f"dragon{s}>{t}#{d}", k), f"real_dragon_{short}_d{d}", "dragon_scans",
                         dragon_scans[s], dragon_scans[t], dragon_poses[s], dragon_poses[t]))
    for k, s in enumerate(sorted({n for p in REAL_PAIRS for n in p})):
        jobs.append((pair_rng(seed, "real", f"{s}>recon", k), f"real_{s}_to_recon", "bunny_scan2recon",
                     scans[s], recon, poses[s], np.eye(4)))
    if per_group is not None:
        seen: dict[str, int] = {}
        kept = []
        for job in jobs:
            seen[job[2]] = seen.get(job[2], 0) + 1
            if seen[job[2]] <= per_group:
                kept.append(job)
        jobs = kept
    rows: list[dict] = []
    for rng, pid, model, src, tgt, pose_s, pose_t in jobs:
        pair = make_real_pair(src, tgt, pose_s, pose_t, rng, n_source)
        row = write_pair(out / "real", pid, pair, formats[len(rows) % len(formats)], pcd_encoding)
        rows.append({**row, "model": model, "level": "real"})
    log.info("level real: %d pairs", len(rows))
    return _write_level(out, "real", rows)


def load_models(paths) -> dict[str, np.ndarray]:
    models = {}
    for p in paths:
        name = Path(p).stem
        if name in models:
            raise click.BadParameter(f"two models named {name!r}")
        models[name] = load_point_cloud(p)
    return models


# ============================================================================================ shipping
SHIP_SCANS = ("bun000", "bun045", "bun090", "bun315", "top3", "chin")
SHIP_MODEL_POINTS = 35000
SHIP_SCAN_POINTS = 9000


def prepare_shipped_data(shared_dir: str | Path, out_dir: str | Path) -> dict[str, int]:
    """Build ``data/`` (models + scans + poses) from the shared raw data; return ``{file: point count}``.

    All point files: binary little-endian float32 PLY, xyz only. Down-sampling is a numpy voxel-grid
    centroid filter whose voxel size is bisected to reach the wanted point count (deterministic).
    """
    shared, out = Path(shared_dir), Path(out_dir)
    (out / "models").mkdir(parents=True, exist_ok=True)
    (out / "scans").mkdir(parents=True, exist_ok=True)
    counts = {}

    def save(rel: str, pts: np.ndarray, comment: str) -> None:
        write_ply_float32(out / rel, pts, comment=comment)
        counts[rel] = len(pts)
        log.info("%s: %d points", rel, len(pts))

    credit = "Stanford 3D Scanning Repository, Stanford Computer Graphics Laboratory; research use only"
    bunny = load_point_cloud(shared / "stanford/bunny/reconstruction/bun_zipper.ply")
    save("models/bunny.ply", bunny, f"{credit}\nbun_zipper.ply vertices")

    dragon_dir = shared / "stanford/dragon/scans"
    dposes = read_pose_file(dragon_dir / "dragonStandRight_poses_world_from_scan.txt")
    fused = np.vstack([apply(dposes[n], load_point_cloud(dragon_dir / f"{n}.ply")) for n in sorted(dposes)])
    dragon, voxel = voxel_downsample_to_count(fused, SHIP_MODEL_POINTS)
    n_before = len(dragon)
    dragon = remove_isolated(dragon)  # ~10 stray scanner returns up to 8 cm off the surface inflate the bbox
    save("models/dragon.ply", dragon, f"{credit}\n15 dragonStandRight scans fused in world frame, voxel {voxel:.6g} m, "
         f"{n_before - len(dragon)} isolated points removed")

    kitchen = load_point_cloud(shared / "real/3dmatch_redkitchen/cloud_bin_0.ply")
    kitchen, voxel = voxel_downsample_to_count(kitchen, SHIP_MODEL_POINTS)
    save("models/redkitchen.ply", kitchen,
         f"3DMatch 7-scenes-redkitchen cloud_bin_0, voxel {voxel:.6g} m; non-commercial research use")

    scan_dir = shared / "stanford/bunny/scans"
    bposes = read_pose_file(scan_dir / "bun_poses_world_from_scan.txt")
    lines = [
        "# 4x4 world_from_scan poses of the shipped bunny scans (copied from the shared",
        "# stanford/bunny/scans/bun_poses_world_from_scan.txt, derived from Stanford's bun.conf with the",
        "# quaternion conjugated). For each scan: a line with the file name, then the 4x4 matrix T (row-major):",
        "#   p_world = T[:3,:3] @ p_scan + T[:3,3]      (world = bun000's frame = bunny.ply's frame)",
        "# Relative ground truth mapping scan B onto scan A:  T_A_from_B = inv(T_A) @ T_B.",
    ]
    for name in SHIP_SCANS:
        pts, voxel = voxel_downsample_to_count(load_point_cloud(scan_dir / f"{name}.ply"), SHIP_SCAN_POINTS)
        save(f"scans/{name}.ply", pts,
             f"{credit}\nraw range scan {name}.ply in its own scanner frame, voxel {voxel:.6g} m")
        lines.append(f"{name}.ply")
        lines += [" ".join(repr(float(v)) for v in row) for row in bposes[name]]
    (out / "scans" / "poses.txt").write_text("\n".join(lines) + "\n")
    return counts


# ============================================================================================ CLI
def _split(value: str) -> list[str]:
    return [v.strip() for v in value.split(",") if v.strip()]


def _parse_formats(value: str) -> list[str]:
    fmts = [f.lower().lstrip(".") for f in _split(value)]
    bad = [f for f in fmts if f not in FORMATS]
    if bad or not fmts:
        raise click.BadParameter(f"unknown format(s) {bad}; choose from {','.join(FORMATS)}")
    return fmts


def _parse_noise(value: str) -> tuple[float, float]:
    """``LO,HI`` noise fractions, 0 <= LO <= HI < 0.1."""
    try:
        lo, hi = (float(v) for v in _split(value))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not two numbers LO,HI", param_hint="--scene-noise") from None
    if not 0 <= lo <= hi < 0.1:
        raise click.BadParameter(f"{value!r}: need 0 <= LO <= HI < 0.1 (fractions of the window diagonal)",
                                 param_hint="--scene-noise")
    return lo, hi


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", is_flag=True, help="log progress")
def cli(verbose: bool) -> None:
    """Shipped data and synthetic cross-source benchmark pairs for gctr."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s")


@cli.command()
@click.option("--shared", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True,
              help="the shared raw data folder (e.g. ../shared/data)")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=DATA_DIR, show_default=True)
def ship(shared: Path, out: Path) -> None:
    """Build data/models and data/scans from the shared raw data.

    Example: python -m data_scripts.make_benchmark ship --shared ../shared/data --out data
    """
    counts = prepare_shipped_data(shared, out)
    for rel, n in counts.items():
        click.echo(f"{rel}: {n} points, {(out / rel).stat().st_size} bytes")


@cli.command()
@click.option("--models", default=",".join(str(p) for p in DEFAULT_MODELS), show_default="the 3 shipped models",
              help="comma-separated model point clouds (synthetic levels)")
@click.option("--levels", default="easy,cross,hard", show_default=True,
              help=f"comma-separated: {','.join(ALL_LEVELS)} ('real' = --real; 'scene' needs --shared)")
@click.option("--pairs-per-model", type=click.IntRange(min=0), default=10, show_default=True,
              help="pairs per model (synthetic levels) and window pairs per scene (level scene)")
@click.option("--seed", type=int, default=0, show_default=True,
              help="0 = the report set (default), 1 = the tuning set")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True)
@click.option("--real", is_flag=True, help="also write the real scan pairs (folder real/), like --levels ...,real")
@click.option("--shared", type=click.Path(file_okay=False, path_type=Path), default=default_shared(),
              show_default="shared/data beside the repository, if it exists",
              help="the shared raw data folder: scenes of level scene, dragon scans of level real")
@click.option("--real-full-res", is_flag=True,
              help="real: read the full-resolution bunny scans from --shared instead of the shipped data/scans")
@click.option("--real-per-group", type=click.IntRange(min=1), default=None,
              help="real: only the first N pairs of each group (bunny scans, dragon scans, scan vs reconstruction)")
@click.option("--formats", default="ply", show_default=True, help="formats cycled over pairs: ply,pcd,xyz")
@click.option("--n-source", type=click.IntRange(min=10), default=20000, show_default=True)
@click.option("--scene-noise", default=None, metavar="LO,HI",
              help=f"noise of the scene level's windows as fractions of the window diagonal (default "
                   f"{SCENE['noise_lo']},{SCENE['noise_hi']}; 0.0002,0.0003 is sensor-like: about 2-4 cm on the NCLT "
                   f"windows, 1 mm on the kitchen windows; the real kitchen pairs get no noise either way)")
@click.option("--pcd-encoding", type=click.Choice(["binary", "ascii"]), default="binary", show_default=True,
              help="PCD DATA type (Open3D's legacy reader mis-reads binary float64 PCD)")
def generate(models, levels, pairs_per_model, seed, out, real, shared, real_full_res, real_per_group, formats,
             n_source, scene_noise, pcd_encoding) -> None:
    """Generate synthetic (and optionally real) cross-source pairs with ground truth.

    \b
    Examples:
      python -m data_scripts.make_benchmark generate --levels cross --pairs-per-model 10 --out bench/work/data
      python -m data_scripts.make_benchmark generate --levels easy,cross,hard,real,part,lowoverlap,sfm,scene \\
          --seed 1 --out bench/work/data-seed1          # the tuning set (reports use --seed 0)
    """
    level_names = _split(levels)
    bad = [lv for lv in level_names if lv not in ALL_LEVELS]
    if bad:
        raise click.BadParameter(f"unknown level(s) {bad}; choose from {','.join(ALL_LEVELS)}", param_hint="--levels")
    if not level_names and not real:
        raise click.BadParameter(f"no level given; choose from {','.join(ALL_LEVELS)}", param_hint="--levels")
    if pairs_per_model == 0 and not (real or "real" in level_names or "scene" in level_names):
        # (level scene with 0 windows still writes its two real kitchen pairs)
        raise click.BadParameter("0 pairs per model and no level with real pairs (real, scene): nothing to "
                                 "generate", param_hint="--pairs-per-model")
    fmts = _parse_formats(formats)
    noise = _parse_noise(scene_noise) if scene_noise is not None else None
    if noise is not None and "scene" not in level_names:
        raise click.UsageError("--scene-noise only applies to level 'scene'; add it to --levels")
    synthetic = [lv for lv in level_names if lv in LEVELS]
    special = [lv for lv in level_names if lv in SPECIAL_LEVELS]
    scenes = load_scenes(shared) if "scene" in level_names else None  # fail early on missing files
    dragon = load_dragon_scans(shared) if (real or "real" in level_names) else None  # likewise
    if (synthetic or special) and not _split(models):
        raise click.BadParameter("no model given", param_hint="--models")
    try:
        loaded = load_models(_split(models)) if synthetic or special else {}
    except PointCloudError as exc:  # a --models file that is missing or not a point cloud
        raise click.BadParameter(str(exc), param_hint="--models") from None
    if (blocked := next((d for d in (out, *out.parents) if d.exists()), None)) is not None and not blocked.is_dir():
        raise click.BadParameter(f"{out}: {blocked} is a file, not a folder", param_hint="--out")
    rows = generate_synthetic(loaded, synthetic, pairs_per_model, seed, out, fmts, n_source, pcd_encoding)
    if real or "real" in level_names:
        if real_full_res and shared is None:
            raise click.UsageError("--real-full-res needs --shared")
        recon = load_point_cloud(DATA_DIR / "models" / "bunny.ply")
        assert dragon is not None
        rows += generate_real_all(*load_scans(shared=shared if real_full_res else None), *dragon, recon, seed, out,
                                  fmts, n_source, pcd_encoding=pcd_encoding, per_group=real_per_group)
    rows += generate_special(loaded, special, pairs_per_model, seed, out, fmts, n_source, pcd_encoding)
    if scenes is not None:
        rows += generate_scene(*scenes, seed, out, fmts, n_source, windows_per_scene=pairs_per_model,
                               pcd_encoding=pcd_encoding, noise=noise)
    write_manifest(out / "pairs.csv", rows)
    click.echo(f"{len(rows)} pairs -> {out / 'pairs.csv'}")


@cli.command()
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=DATA_DIR / "demo", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
def demo(out: Path, seed: int) -> None:
    """Small demo set: 2 cross pairs per shipped model (n_source 8000) + 2 real scan pairs, formats ply,pcd,xyz."""
    fmts = ["ply", "pcd", "xyz"]
    rows = generate_synthetic(load_models(DEFAULT_MODELS), ["cross"], 2, seed, out, fmts, n_source=8000)
    rows += generate_real(*load_scans(), seed, out, fmts, n_source=8000, pairs=REAL_PAIRS[:2])
    write_manifest(out / "pairs.csv", rows)
    click.echo(f"{len(rows)} pairs -> {out / 'pairs.csv'}")


if __name__ == "__main__":
    cli()
