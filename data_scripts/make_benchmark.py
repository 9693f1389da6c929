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
    Optionally (``--real``) pairs of real raw bunny scans with their true relative pose, made
    cross-source by a random similarity on the source and a 1/4 density target.

``demo``
    A small set (6 synthetic ``cross`` pairs + 2 real scan pairs) in a few seconds; ``make demo``.

Randomness: every pair draws from its own ``np.random.default_rng([seed, level_index, model_key, k])``
(``model_key`` = CRC32 of the model name, so a pair does not depend on which other models or levels
are generated in the same call). The same command gives byte-identical files.

Matrix convention (GUIDE §1): ``T = [[s R, t], [0 0 0 1]]`` maps the source onto the target.
"""

from __future__ import annotations

import csv
import logging
import zlib
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from data_scripts.common import (
    FORMATS,
    bbox_diagonal,
    read_points,
    read_pose_file,
    remove_isolated,
    transform,
    voxel_downsample_to_count,
    write_matrix,
    write_ply,
    write_points,
)

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT / "data"
DEFAULT_MODELS = tuple(DATA_DIR / "models" / f"{m}.ply" for m in ("bunny", "dragon", "redkitchen"))
MANIFEST_COLUMNS = ["pair_id", "source", "target", "gt", "model", "level", "scale_gt", "overlap_src", "overlap_tgt"]


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
LEVEL_INDEX = {"easy": 0, "cross": 1, "hard": 2, "real": 3}

# Real scan pairs (source, target): partial overlaps 0.5-0.9 (table in the shared bunny SOURCE.md).
REAL_PAIRS = (
    ("bun045", "bun000"),
    ("bun090", "bun045"),
    ("bun315", "bun000"),
    ("chin", "bun315"),
    ("top3", "bun000"),
    ("top3", "bun045"),
)
REAL_LEVEL = Level("real", density=1 / 4, noise=0.0, outliers=0.0, crop_lo=1.0, crop_hi=1.0, s_lo=0.5, s_hi=2.0)


@dataclass(frozen=True)
class Pair:
    """A generated pair: ``target ≈ transform(T_gt, source)`` for the inlier points."""

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
    from scipy.spatial.transform import Rotation

    rot = Rotation.random(random_state=rng).as_matrix()
    scale = float(np.exp(rng.uniform(np.log(s_lo), np.log(s_hi))))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    trans = direction * t_radius * rng.uniform() ** (1.0 / 3.0)
    mat = np.eye(4)
    mat[:3, :3] = scale * rot
    mat[:3, 3] = trans
    return mat


def invert_similarity(mat: np.ndarray) -> np.ndarray:
    return np.linalg.inv(mat)


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
    src = transform(invert_similarity(T_gt), src)
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

    rigid = np.linalg.inv(pose_tgt) @ pose_src
    A = random_similarity(rng, level.s_lo, level.s_hi, level.t_radius * bbox_diagonal(src_scan))
    idx_s = downsample(len(src_scan), n_source, rng)
    idx_t = downsample(len(tgt_scan), int(round(level.density * len(idx_s))), rng)

    # overlap: points within 2x the median point spacing of the other scan, both in the target frame
    src_in_t = transform(rigid, src_scan)
    tree_t, tree_s = cKDTree(tgt_scan), cKDTree(src_in_t)
    spacing_t = np.median(tree_t.query(tgt_scan, k=2)[0][:, 1])
    spacing_s = np.median(tree_s.query(src_in_t, k=2)[0][:, 1])
    overlap_src = float((tree_t.query(src_in_t[idx_s])[0] < 2 * spacing_t).mean())
    overlap_tgt = float((tree_s.query(tgt_scan[idx_t])[0] < 2 * spacing_s).mean())

    return Pair(
        source=transform(A, src_scan[idx_s]),
        target=tgt_scan[idx_t].copy(),
        T_gt=rigid @ invert_similarity(A),
        src_outlier=np.zeros(len(idx_s), dtype=bool),
        tgt_outlier=np.zeros(len(idx_t), dtype=bool),
        overlap_src=overlap_src,
        overlap_tgt=overlap_tgt,
    )


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
        rows = []
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
    scans = {n: read_points(folder / f"{n}.ply") for n in names}
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


def load_models(paths) -> dict[str, np.ndarray]:
    models = {}
    for p in paths:
        name = Path(p).stem
        if name in models:
            raise click.BadParameter(f"two models named {name!r}")
        models[name] = read_points(p)
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
        write_ply(out / rel, pts, dtype="float32", comment=comment)
        counts[rel] = len(pts)
        log.info("%s: %d points", rel, len(pts))

    credit = "Stanford 3D Scanning Repository, Stanford Computer Graphics Laboratory; research use only"
    bunny = read_points(shared / "stanford/bunny/reconstruction/bun_zipper.ply")
    save("models/bunny.ply", bunny, f"{credit}\nbun_zipper.ply vertices")

    dragon_dir = shared / "stanford/dragon/scans"
    dposes = read_pose_file(dragon_dir / "dragonStandRight_poses_world_from_scan.txt")
    fused = np.vstack([transform(dposes[n], read_points(dragon_dir / f"{n}.ply")) for n in sorted(dposes)])
    dragon, voxel = voxel_downsample_to_count(fused, SHIP_MODEL_POINTS)
    n_before = len(dragon)
    dragon = remove_isolated(dragon)  # ~10 stray scanner returns up to 8 cm off the surface inflate the bbox
    save("models/dragon.ply", dragon, f"{credit}\n15 dragonStandRight scans fused in world frame, voxel {voxel:.6g} m, "
         f"{n_before - len(dragon)} isolated points removed")

    kitchen = read_points(shared / "real/3dmatch_redkitchen/cloud_bin_0.ply")
    kitchen, voxel = voxel_downsample_to_count(kitchen, SHIP_MODEL_POINTS)
    save("models/redkitchen.ply", kitchen, f"3DMatch 7-scenes-redkitchen cloud_bin_0, voxel {voxel:.6g} m; non-commercial research use")

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
        pts, voxel = voxel_downsample_to_count(read_points(scan_dir / f"{name}.ply"), SHIP_SCAN_POINTS)
        save(f"scans/{name}.ply", pts, f"{credit}\nraw range scan {name}.ply in its own scanner frame, voxel {voxel:.6g} m")
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
              help="comma-separated model point clouds")
@click.option("--levels", default="easy,cross,hard", show_default=True, help=f"comma-separated: {','.join(LEVELS)}")
@click.option("--pairs-per-model", type=click.IntRange(min=0), default=10, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True)
@click.option("--real", is_flag=True, help="also write real bunny scan pairs (folder real/)")
@click.option("--shared", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="with --real: read the full-resolution scans from this shared data folder")
@click.option("--formats", default="ply", show_default=True, help="formats cycled over pairs: ply,pcd,xyz")
@click.option("--n-source", type=click.IntRange(min=10), default=20000, show_default=True)
@click.option("--pcd-encoding", type=click.Choice(["binary", "ascii"]), default="binary", show_default=True,
              help="PCD DATA type (Open3D's legacy reader mis-reads binary float64 PCD)")
def generate(models, levels, pairs_per_model, seed, out, real, shared, formats, n_source, pcd_encoding) -> None:
    """Generate synthetic (and optionally real) cross-source pairs with ground truth.

    Example: python -m data_scripts.make_benchmark generate --levels cross --pairs-per-model 10 --out bench/work/data
    """
    level_names = _split(levels)
    bad = [lv for lv in level_names if lv not in LEVELS]
    if bad:
        raise click.BadParameter(f"unknown level(s) {bad}; choose from {','.join(LEVELS)}", param_hint="--levels")
    fmts = _parse_formats(formats)
    rows = generate_synthetic(load_models(_split(models)), level_names, pairs_per_model, seed, out, fmts,
                              n_source, pcd_encoding)
    if real:
        rows += generate_real(*load_scans(shared=shared), seed, out, fmts, n_source, pcd_encoding=pcd_encoding)
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
