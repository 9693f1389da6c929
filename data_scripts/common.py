"""Small helpers shared by the data scripts (plain numpy arrays, no loops over points).

Point clouds are ``(N, 3)`` float64 arrays, read with ``gctr_cli.io.load_point_cloud`` and written with the
package's writers (:func:`write_points`), so the benchmark files are exactly what ``gctr`` reads and
writes; 4x4 matrices go through ``gctr_cli.io.read_matrix`` / ``write_matrix`` and ``gctr_cli.geometry``.
"""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from gctr_cli.engine.result import THRESHOLD_REFUSAL

FORMATS = ("ply", "pcd", "xyz")


# --------------------------------------------------------------------------------------------- reading
def float_or_nan(x: Any) -> float:
    """``x`` as a float (a manifest cell, a CSV field), NaN when it is empty, missing or not a number."""
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def read_pose_file(path: str | Path) -> dict[str, np.ndarray]:
    """Parse a ``*_poses_world_from_scan.txt`` file: a scan name line, then 4 rows of a 4x4 matrix.

    Lines starting with ``#`` are comments. Returns ``{scan name without extension: 4x4 world_from_scan}``.
    """
    lines = [ln.strip() for ln in Path(path).read_text().splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    poses: dict[str, np.ndarray] = {}
    i = 0
    while i < len(lines):
        name = lines[i]
        rows = [np.array(lines[i + 1 + r].split(), dtype=np.float64) for r in range(4)]
        mat = np.vstack(rows)
        if mat.shape != (4, 4):
            raise ValueError(f"{path}: bad matrix for {name}")
        poses[Path(name).stem] = mat
        i += 5
    return poses


# --------------------------------------------------------------------------------------------- writing
def write_points(path: str | Path, points: np.ndarray, pcd_encoding: str = "binary") -> None:
    """Write float64 coordinates exactly with the package's writer (``gctr_cli.io``); the format is chosen
    by the file extension, one of :data:`FORMATS`; ``pcd_encoding`` ``binary`` or ``ascii`` (PCD only)."""
    from gctr_cli.io import save_point_cloud

    ext = Path(path).suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise ValueError(f"unsupported point cloud format {ext!r} (use one of {FORMATS})")
    if pcd_encoding not in ("binary", "ascii"):
        raise ValueError(f"unknown PCD encoding {pcd_encoding!r}")
    save_point_cloud(path, points, binary=pcd_encoding == "binary")


def write_ply_float32(path: str | Path, points: np.ndarray, comment: str | None = None) -> None:
    """Binary little-endian PLY with float32 x y z and ``comment`` lines: the small shipped files of ``data/``
    (the package's writer keeps float64 and has no comment lines for the attribution)."""
    pts = np.ascontiguousarray(points, dtype="<f4")
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header += [f"comment {c}" for c in comment.splitlines()]
    header += [f"element vertex {len(pts)}"] + [f"property float {a}" for a in "xyz"] + ["end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        pts.tofile(fh)


# --------------------------------------------------------------------------------------------- geometry
def bbox_diagonal(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Voxel-grid centroid filter: one point (the mean) per occupied voxel, voxels in lexicographic order."""
    cells = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    dims = cells.max(axis=0) + 1
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]  # lexicographic linear index
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=points[:, d], minlength=len(counts)) for d in range(3)], axis=1)
    return sums / counts[:, None]


def remove_isolated(points: np.ndarray, k: int = 8, factor: float = 5.0) -> np.ndarray:
    """Drop points whose k-th nearest neighbour is farther than ``factor`` x the median of that distance
    (stray scanner returns far from the surface)."""
    from scipy.spatial import cKDTree

    dk = cKDTree(points).query(points, k=k + 1)[0][:, -1]
    return points[dk <= factor * np.median(dk)]


def voxel_downsample_to_count(points: np.ndarray, target: int, iterations: int = 40) -> tuple[np.ndarray, float]:
    """Voxel-downsample with the voxel size found by bisection so the result has about ``target`` points.

    Returns ``(points, voxel_size)``; deterministic (same input, same output).
    """
    if len(points) <= target:
        return points.copy(), 0.0
    diag = bbox_diagonal(points)
    lo, hi = diag * 1e-5, diag * 0.5  # lo gives (nearly) all points, hi very few
    best: tuple[int, float] | None = None
    for _ in range(iterations):
        mid = np.sqrt(lo * hi)
        n = len(voxel_downsample(points, mid))
        if best is None or abs(n - target) < abs(best[0] - target):
            best = (n, mid)
        if n == target:
            break
        if n > target:
            lo = mid
        else:
            hi = mid
    assert best is not None  # iterations >= 1
    voxel = float(best[1])
    return voxel_downsample(points, voxel), voxel


#: repetitions of :func:`reference_workload_seconds` (the minimum is reported)
REFERENCE_REPEATS = 5


def reference_workload_seconds(repeats: int = REFERENCE_REPEATS) -> float:
    """Seconds (minimum of ``repeats``) of a fixed numpy/scipy task that does not depend on gctr's code:
    a k-d tree over 6000 seeded random points, their 30 nearest neighbours, 6000 symmetric 3x3
    eigen-decompositions and a sort of a million numbers — the kinds of work the engine does.

    On a shared machine the same code has run up to 2x faster on one day than on another (the engine, and
    even ``python -c pass``), as much as a code change moves the times. Reported beside a benchmark's
    times, this task says how fast the machine was during the run: divide each run's times by its
    reference before comparing two runs.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(20261202)
    points = rng.random((6000, 3))
    numbers = rng.random(1_000_000)
    best = math.inf
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        _, idx = cKDTree(points).query(points, k=30)
        local = points[idx] - points[:, None, :]
        np.linalg.eigh(np.matmul(local.transpose(0, 2, 1), local))
        np.sort(numbers)
        best = min(best, time.perf_counter() - start)
    return best


def machine_info() -> dict[str, str]:
    """The machine a benchmark ran on: CPU model, cores, memory, Python and library versions."""
    from importlib.metadata import PackageNotFoundError, version

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count() or 1
    info = {"cpu": cpu, "cores": str(os.cpu_count()), "usable_cores": str(usable),
            "python": platform.python_version(), "platform": platform.platform()}
    for pkg in ("numpy", "scipy", "open3d"):
        try:
            info[pkg] = version(pkg)
        except PackageNotFoundError:
            info[pkg] = "?"
    try:
        with open("/proc/meminfo") as fh:
            kb = int(fh.readline().split()[1])
        info["memory_gb"] = f"{kb / 1024 / 1024:.1f}"
    except (OSError, ValueError, IndexError):
        info["memory_gb"] = "?"
    return info


# --------------------------------------------------------------------------------------------- verdicts
# Shared by bench_engine (bench/ENGINE.md) and bench_compare (bench/RESULTS.md), issue 9. A result row is
# a dict with at least ``status`` ("ok" / "failed" / anything else = the pair did not run) and ``success``
# (status ok and errors within the config's success thresholds); for the confidence trade-off also
# ``confidence`` (float in [0, 1], NaN when the method has none) and ``would_succeed`` (True / False: the
# errors of the returned transform are / are not within the thresholds, whatever the status; None: no
# usable transform, e.g. an empty matrix, the identity or a non-finite matrix).
OUTCOMES = ("success", "silent_wrong", "failed")
OUTCOME_LABELS = {"success": "success", "silent_wrong": "silent wrong", "failed": "honest failure"}
CONFIDENCE_THRESHOLDS = tuple(i / 10 for i in range(10))


def sweep_thresholds(configured: float | None) -> tuple[float, ...]:
    """The sweep's thresholds: the 0.1 grid plus the configured threshold (so its row is in the table)."""
    grid = CONFIDENCE_THRESHOLDS
    if isinstance(configured, bool) or not isinstance(configured, (int, float)):
        return grid
    if any(abs(float(configured) - t) < 1e-9 for t in grid):
        return grid
    return tuple(sorted((*grid, float(configured))))


#: failure diagnostics: engine scores (in [0, 1]) of the truth and of the answer closer than this are "equal"
DIAGNOSIS_MARGIN = 0.02
DIAGNOSES = ("search missed", "objective can't tell", "precision")


def outcome(row: dict) -> str:
    """``success`` (status ok, errors within the thresholds), ``silent_wrong`` (status ok, wrong) or
    ``failed`` (any other status: an honest failure, or a pair that crashed / timed out)."""
    if row.get("status") == "ok":
        return "success" if row.get("success") else "silent_wrong"
    return "failed"


def outcome_counts(rows: list[dict]) -> dict[str, int]:
    counts = {k: 0 for k in OUTCOMES}
    for r in rows:
        counts[outcome(r)] += 1
    counts["pairs"] = len(rows)
    return counts


def usable_transform(mat) -> bool:
    """A transform that can be scored: finite 4x4, not the identity, positive determinant of the linear part
    (engines return the identity as the placeholder of a failed pair)."""
    try:
        m = np.asarray(mat, dtype=float).reshape(4, 4)
    except (TypeError, ValueError):
        return False
    return bool(np.isfinite(m).all() and not np.allclose(m, np.eye(4)) and np.linalg.det(m[:3, :3]) > 0)


def _is_nan(x) -> bool:
    return x is None or (isinstance(x, float) and math.isnan(x))


def confidence_sweep(rows: list[dict], thresholds=CONFIDENCE_THRESHOLDS) -> list[dict]:
    """The confidence threshold's trade-off, offline: for each threshold ``t`` a pair is *accepted* when it
    has a usable transform (``would_succeed`` not None) and ``confidence >= t`` (NaN confidence: always
    accepted — a method without a confidence never refuses). Counts per threshold:

    * ``silent_wrong``: accepted and wrong (``would_succeed`` False);
    * ``correct_refused``: refused although the transform was right (``would_succeed`` True, ``conf < t``);
    * ``success``: accepted and right; ``refused``: all the refused pairs; ``pairs``: all pairs.

    A pair the engine refused for another reason than its confidence (``refusal`` set and not
    :data:`~gctr_cli.engine.result.THRESHOLD_REFUSAL`: not confirmed the other way round, mirrored, held at
    a scale bound, too weak evidence) counts as refused at every threshold: no threshold would accept it.
    An ambiguous or low-confidence refusal is accepted from the thresholds its confidence reaches: an upper
    bound, since the reverse confirmation and the mirror check, which run only on accepted answers, never ran
    on it (so ``success`` and ``silent_wrong`` below the configured threshold may be slightly high).
    """
    out = []
    for t in thresholds:
        c = {"threshold": float(t), "pairs": len(rows), "success": 0, "silent_wrong": 0, "correct_refused": 0,
             "refused": 0}
        for r in rows:
            ws = r.get("would_succeed")
            conf = r.get("confidence", math.nan)
            refused_anyway = str(r.get("refusal") or "") not in ("", THRESHOLD_REFUSAL)
            accepted = ws is not None and not refused_anyway and (_is_nan(conf) or conf >= t)
            if not accepted:
                c["refused"] += 1
                c["correct_refused"] += int(ws is True)
            elif ws:
                c["success"] += 1
            else:
                c["silent_wrong"] += 1
        out.append(c)
    return out


def diagnose(score_truth: float, score_answer: float, margin: float = DIAGNOSIS_MARGIN) -> str:
    """Why a pair failed, from the engine's own score of the ground truth and of its answer: ``search missed``
    (truth higher by more than ``margin``), ``objective can't tell`` (answer higher by more than ``margin``),
    ``precision`` (equal within ``margin``: the right basin, not precise enough); ``''`` if either is NaN."""
    if _is_nan(score_truth) or _is_nan(score_answer):
        return ""
    if score_truth > score_answer + margin:
        return "search missed"
    if score_answer > score_truth + margin:
        return "objective can't tell"
    return "precision"


def _pct(n: int, total: int) -> str:
    return f"{n} ({100.0 * n / total:.1f}%)" if total else "0"


def _quantile(xs, q: float) -> float:
    xs = [float(x) for x in xs if x is not None and math.isfinite(float(x))]
    return float(np.quantile(xs, q)) if xs else math.nan


def _t(x: float) -> str:
    return "–" if _is_nan(x) else f"{x:.2f}"


def outcome_table(groups: list[tuple[str, str, list[dict]]], time_key: str) -> list[str]:
    """Markdown: one line per (method, level, rows) group: pairs, success, silent wrong, honest failures
    (each with its % of the group's pairs), median and p90 of ``time_key``."""
    out = ["| method | level | pairs | success | **silent wrong** | honest failures | median time (s) | p90 time (s) |",
           "|---|---|---:|---:|---:|---:|---:|---:|"]
    for method, level, rows in groups:
        c = outcome_counts(rows)
        times = [r.get(time_key) for r in rows]
        out.append(f"| {method} | {level} | {c['pairs']} | {_pct(c['success'], c['pairs'])} "
                   f"| {_pct(c['silent_wrong'], c['pairs'])} | {_pct(c['failed'], c['pairs'])} "
                   f"| {_t(_quantile(times, 0.5))} | {_t(_quantile(times, 0.9))} |")
    return out


def sweep_table(sweeps: dict[str, list[dict]], configured: float | None = None) -> list[str]:
    """Markdown: per method (column pair) and threshold (row): silent wrong and correct-but-refused, each as a
    count and % of the method's pairs; the configured threshold's row is marked."""
    methods = list(sweeps)
    head = "| threshold | " + " | ".join(f"{m}: silent wrong | {m}: correct refused" for m in methods) + " |"
    out = [head, "|---:|" + "---:|---:|" * len(methods)]
    thresholds = [c["threshold"] for c in next(iter(sweeps.values()))] if sweeps else []
    for i, t in enumerate(thresholds):
        mark = " (configured)" if configured is not None and abs(t - configured) < 1e-9 else ""
        cells = []
        for m in methods:
            c = sweeps[m][i]
            cells += [_pct(c["silent_wrong"], c["pairs"]), _pct(c["correct_refused"], c["pairs"])]
        out.append(f"| {t:.2f}{mark} | " + " | ".join(cells) + " |")
    return out


def diagnosis_table(rows: list[dict], levels: list[str]) -> list[str]:
    """Markdown: per level, the unsuccessful pairs by ``diagnosis`` (rows without one: ``not scored``)."""
    cols = [*DIAGNOSES, "not scored"]
    out = ["| level | unsuccessful | " + " | ".join(cols) + " |", "|---|---:|" + "---:|" * len(cols)]
    for lv in [*levels, "all"]:
        bad = [r for r in rows if (lv == "all" or r.get("level") == lv) and outcome(r) != "success"]
        counts = {c: 0 for c in cols}
        for r in bad:
            d = r.get("diagnosis") or ""
            counts[d if d in DIAGNOSES else "not scored"] += 1
        name = "**all**" if lv == "all" else lv
        out.append(f"| {name} | {len(bad)} | " + " | ".join(str(counts[c]) for c in cols) + " |")
    return out


def plot_confidence_tradeoff(sweeps: dict[str, list[dict]], path, configured: float | None = None,
                             title: str = "Confidence threshold trade-off") -> None:
    """PNG: silent wrong and correct-but-refused (% of all pairs) against the threshold, one colour per
    method (solid: silent wrong, dashed: correct refused); the configured threshold as a vertical line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.4))
    for i, (m, sweep) in enumerate(sweeps.items()):
        colour = f"C{i}"
        ts = [c["threshold"] for c in sweep]
        ax.plot(ts, [100.0 * c["silent_wrong"] / max(c["pairs"], 1) for c in sweep], "-o", color=colour, ms=3,
                label=f"{m}: silent wrong")
        ax.plot(ts, [100.0 * c["correct_refused"] / max(c["pairs"], 1) for c in sweep], "--s", color=colour, ms=3,
                label=f"{m}: correct refused")
    if configured is not None:
        ax.axvline(configured, color="k", lw=1.0, ls=":", label=f"configured ({configured:g})")
    ax.set_xlabel("confidence threshold (engine.min_confidence)")
    ax.set_ylabel("% of all pairs")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
