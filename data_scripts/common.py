"""Small I/O and geometry helpers shared by the data scripts (plain numpy arrays, no loops over points).

Point clouds are ``(N, 3)`` float64 arrays. Writers are our own (header + ``ndarray.tofile``) so the
output bytes depend only on the array: the same array always gives the same file.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

import numpy as np

FORMATS = ("ply", "pcd", "xyz")


# --------------------------------------------------------------------------------------------- reading
def read_points(path: str | Path) -> np.ndarray:
    """Load the xyz coordinates of a PLY/PCD/XYZ file (vertices only, faces ignored) as float64.

    Open3D only warns on an unreadable file and returns an empty cloud, so emptiness is checked here.
    PCD files go through the tensor reader ``o3d.t.io``: Open3D 0.20's legacy ``o3d.io.read_point_cloud``
    returns all-zero coordinates for *binary* PCD files with float64 (``SIZE 8``) fields.
    """
    import open3d as o3d  # deferred: heavy import

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point cloud file not found: {path}")
    if path.suffix.lower() == ".pcd":
        pcd = o3d.t.io.read_point_cloud(str(path))
        pts = pcd.point.positions.numpy().astype(np.float64) if "positions" in pcd.point else np.empty((0, 3))
    else:
        pts = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[0] == 0:
        raise ValueError(f"no points could be read from {path}")
    if not np.isfinite(pts).all():
        raise ValueError(f"non-finite coordinates in {path}")
    return pts


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


def read_matrix(path: str | Path) -> np.ndarray:
    mat = np.loadtxt(path, dtype=np.float64)
    if mat.shape != (4, 4):
        raise ValueError(f"{path}: expected a 4x4 matrix, got shape {mat.shape}")
    return mat


# --------------------------------------------------------------------------------------------- writing
def write_ply(path: str | Path, points: np.ndarray, dtype: str = "float64", comment: str | None = None) -> None:
    """Binary little-endian PLY with x y z only (``dtype`` float32 -> ``float``, float64 -> ``double``)."""
    np_dtype = {"float32": "<f4", "float64": "<f8"}[dtype]
    ply_type = {"float32": "float", "float64": "double"}[dtype]
    pts = np.ascontiguousarray(points, dtype=np_dtype)
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header += [f"comment {c}" for c in comment.splitlines()]
    header += [f"element vertex {len(pts)}"] + [f"property {ply_type} {a}" for a in "xyz"] + ["end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        pts.tofile(fh)


def write_pcd(path: str | Path, points: np.ndarray, encoding: str = "binary") -> None:
    """PCD v0.7 with float64 fields x y z (TYPE F, SIZE 8); ``encoding`` ``binary`` or ``ascii`` (%.17g).

    Both are exact. Caution: Open3D 0.20's legacy ``o3d.io.read_point_cloud`` reads the *binary* float64
    variant as all zeros (its tensor reader ``o3d.t.io.read_point_cloud`` and PCL read it correctly);
    the ascii variant is read correctly by both Open3D readers.
    """
    pts = np.ascontiguousarray(points, dtype="<f8")
    n = len(pts)
    if encoding not in ("binary", "ascii"):
        raise ValueError(f"unknown PCD encoding {encoding!r}")
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\n"
        f"COUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {encoding}\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        if encoding == "binary":
            pts.tofile(fh)
        else:
            np.savetxt(fh, pts, fmt="%.17g")


def write_xyz(path: str | Path, points: np.ndarray) -> None:
    """Text file, one ``x y z`` line per point at full precision (%.17g)."""
    np.savetxt(path, np.asarray(points, dtype=np.float64), fmt="%.17g")


def write_points(path: str | Path, points: np.ndarray, pcd_encoding: str = "binary") -> None:
    """Write float64 coordinates exactly; the format is chosen by the file extension."""
    ext = Path(path).suffix.lower().lstrip(".")
    if ext == "ply":
        write_ply(path, points, dtype="float64")
    elif ext == "pcd":
        write_pcd(path, points, encoding=pcd_encoding)
    elif ext == "xyz":
        write_xyz(path, points)
    else:
        raise ValueError(f"unsupported point cloud format {ext!r} (use one of {FORMATS})")


def write_matrix(path: str | Path, mat: np.ndarray) -> None:
    """4x4 matrix, four lines of four numbers, row-major, %.17g (GUIDE §1)."""
    np.savetxt(path, np.asarray(mat, dtype=np.float64).reshape(4, 4), fmt="%.17g")


# --------------------------------------------------------------------------------------------- geometry
def transform(mat: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 (similarity) matrix to ``(N, 3)`` points: ``p' = A p + t``."""
    return points @ mat[:3, :3].T + mat[:3, 3]


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
    best = None
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
    voxel = float(best[1])
    return voxel_downsample(points, voxel), voxel


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
