"""Shared fixtures: synthetic point cloud pairs with ground truth, manifests, and engine detection.

``dataset`` builds, in ``tmp_path``, pairs whose target is an exact similarity transform of the source
point by point (``target[i] = T_gt @ source[i]``), in mixed formats (.ply/.pcd/.xyz), with
ground-truth matrix files and a manifest. Tests that run the real GCTR engine are marked
``@pytest.mark.engine``, tests over ~5 s ``@pytest.mark.slow`` (markers registered in pyproject.toml;
``make test-fast`` leaves the slow ones out).
"""

from __future__ import annotations

import csv
import ctypes
import glob
import math
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import scipy

from gctr_cli.geometry import apply, to_matrix

TESTS_DIR = Path(__file__).resolve().parent
REPO = TESTS_DIR.parent


# ----------------------------------------------------------------------------------------------------
# single-threaded BLAS for the whole session
# ----------------------------------------------------------------------------------------------------

def _openblas_libs() -> list:
    """The OpenBLAS builds bundled with numpy and scipy (wheels), with their thread-count setters."""
    libs = []
    for pkg in (np, scipy):
        for path in glob.glob(os.path.join(os.path.dirname(pkg.__file__), os.pardir, f"{pkg.__name__}.libs",
                                           "*openblas*")):
            try:
                lib = ctypes.CDLL(path)
                libs.append((lib.scipy_openblas_get_num_threads64_, lib.scipy_openblas_set_num_threads64_))
            except (OSError, AttributeError):
                continue
    return libs


@pytest.fixture(autouse=True, scope="session")
def single_threaded_blas():
    """Run the engine single-threaded, as batch workers do. The engine's small BLAS calls gain
    nothing from threads, and when the cores are shared (parallel test runs, other jobs) OpenBLAS's
    spinning threads slow the power iteration down by 10-30x. Set once per test process (each
    pytest-xdist worker) and restored at its end; subprocesses get ``OMP_NUM_THREADS`` and friends from
    the code they run."""
    libs = _openblas_libs()
    before = [get() for get, _ in libs]
    for _, set_threads in libs:
        set_threads(1)
    yield
    for (_, set_threads), n in zip(libs, before):
        set_threads(n)


# ----------------------------------------------------------------------------------------------------
# geometry helpers
# ----------------------------------------------------------------------------------------------------


def rotation(axis, angle_deg: float) -> np.ndarray:
    """Rotation by ``angle_deg`` degrees about ``axis`` (Rodrigues)."""
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    a = math.radians(angle_deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def random_similarity(rng: np.random.Generator, max_angle: float = 40.0) -> np.ndarray:
    """A moderate similarity: rotation of 5-``max_angle`` degrees, scale in [0.5, 2], translation in [-3, 3]^3."""
    R = rotation(rng.normal(size=3), rng.uniform(5.0, max_angle))
    return to_matrix(float(rng.uniform(0.5, 2.0)), R, rng.uniform(-3, 3, 3))


def translation(offset) -> np.ndarray:
    """The 4x4 pure translation by ``offset``."""
    return to_matrix(1.0, np.eye(3), offset)


def bumpy_surface(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on a smooth, asymmetric, clearly non-planar height field over [-1, 1]^2."""
    xy = rng.uniform(-1.0, 1.0, size=(n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = (
        0.30 * np.sin(3.0 * x) * np.cos(2.0 * y)
        + 0.45 * np.exp(-((x - 0.3) ** 2 + (y + 0.2) ** 2) / 0.05)
        + 0.20 * np.exp(-((x + 0.5) ** 2 + (y - 0.5) ** 2) / 0.02)
        + 0.10 * x * y
    )
    return np.column_stack([x, y, z])


def write_cloud(path: Path, points: np.ndarray) -> Path:
    from gctr_cli.io import save_point_cloud

    save_point_cloud(path, points)
    return path


def write_manifest_rows(path: Path, rows: list[dict], columns=("pair_id", "source", "target", "gt")) -> Path:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow([r.get(c, "") or "" for c in columns])
    return path


def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
        return list(reader.fieldnames or []), rows


def row_matrix(row: dict[str, str]) -> np.ndarray:
    return np.array([[float(row[f"m{i}{j}"]) for j in range(4)] for i in range(4)])


# ----------------------------------------------------------------------------------------------------
# the dataset fixture
# ----------------------------------------------------------------------------------------------------


@dataclass
class Dataset:
    """Pairs written under ``root``; ``rows`` are manifest rows (relative paths), ``gt`` the true matrices."""

    root: Path
    rng: np.random.Generator
    rows: list[dict] = field(default_factory=list)
    gt: dict[str, np.ndarray] = field(default_factory=dict)

    def add_pair(self, pair_id: str, n: int = 200, exts=(".ply", ".ply"), with_gt: bool = True,
                 offset=None) -> dict:
        src = bumpy_surface(self.rng, n)
        T = random_similarity(self.rng)
        if offset is not None:
            T[:3, 3] += offset
        tgt = apply(T, src)
        d = self.root / "clouds"
        s_path = write_cloud(d / f"{pair_id}_src{exts[0]}", src)
        t_path = write_cloud(d / f"{pair_id}_tgt{exts[1]}", tgt)
        row = {"pair_id": pair_id, "source": s_path.relative_to(self.root).as_posix(),
               "target": t_path.relative_to(self.root).as_posix()}
        if with_gt:
            from gctr_cli.io import write_matrix

            g = self.root / "gt" / f"{pair_id}.txt"
            write_matrix(g, T)
            row["gt"] = g.relative_to(self.root).as_posix()
            self.gt[pair_id] = T
        self.rows.append(row)
        return row

    def add_raw(self, pair_id: str, source: str, target: str, gt: str | None = None) -> dict:
        row = {"pair_id": pair_id, "source": source, "target": target, "gt": gt or ""}
        self.rows.append(row)
        return row

    def manifest(self, name: str = "pairs.csv") -> Path:
        return write_manifest_rows(self.root / name, self.rows)

    def specs(self, name: str = "pairs.csv"):
        from gctr_cli.manifest import read_manifest

        return read_manifest(self.manifest(name))


@pytest.fixture
def dataset(tmp_path) -> Dataset:
    """Empty dataset in ``tmp_path/data`` with a seeded generator (add pairs in the test)."""
    root = tmp_path / "data"
    root.mkdir()
    return Dataset(root=root, rng=np.random.default_rng(12345))


@pytest.fixture
def four_pairs(dataset) -> Dataset:
    """Four pairs with ground truth in mixed formats (one with a UTM-like 1e6 offset) + one without gt."""
    dataset.add_pair("ply_ply", exts=(".ply", ".ply"))
    dataset.add_pair("pcd_xyz", exts=(".pcd", ".xyz"))
    dataset.add_pair("xyz_ply", exts=(".xyz", ".ply"))
    dataset.add_pair("ply_pcd_utm", exts=(".ply", ".pcd"), offset=np.array([4.5e5, 5.3e6, 120.0]))
    dataset.add_pair("no_gt", exts=(".pcd", ".ply"), with_gt=False)
    return dataset


@pytest.fixture
def fast_config():
    """Defaults with a short per-pair time limit (fake-engine tests take milliseconds per pair)."""
    from gctr_cli.config import config_from_dict

    return config_from_dict({"seed": 7, "batch": {"workers": 2, "time_limit_s": 30}})


def make_subprocess_env() -> dict[str, str]:
    """Environment for ``python -m gctr_cli`` / driver subprocesses: the tests folder importable."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS_DIR), str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    env.pop("COLUMNS", None)
    return env


@pytest.fixture
def subprocess_env():
    """:func:`make_subprocess_env` for one test."""
    return make_subprocess_env()


PYTHON = sys.executable


@pytest.fixture(scope="session")
def easy_bunny_pair(tmp_path_factory) -> Path:
    """A benchmark folder (``pairs.csv``, generated like ``make_benchmark``) with one easy bunny pair
    (3000-point source): the developer tools' fixture (settle_margin, truth_score)."""
    from data_scripts import make_benchmark as mb
    from gctr_cli.io import load_point_cloud

    out = tmp_path_factory.mktemp("easy_bunny") / "data"
    bunny = load_point_cloud(mb.DATA_DIR / "models" / "bunny.ply")
    pair = mb.make_pair(bunny, mb.LEVELS["easy"], mb.pair_rng(0, "easy", "bunny", 0), n_source=3000)
    row = mb.write_pair(out / "easy", "easy_bunny_0", pair, "ply")
    mb.write_manifest(out / "pairs.csv", [{**row, **{c: f"easy/{row[c]}" for c in ("source", "target", "gt")},
                                           "model": "bunny", "level": "easy"}])
    return out


#: the target of :func:`easy_bunny_pair_broken`, which cannot be read
BROKEN_TARGET = "easy_bunny_0_tgt.ply"


@pytest.fixture
def easy_bunny_pair_broken(easy_bunny_pair, tmp_path) -> Path:
    """A copy of :func:`easy_bunny_pair` whose target (``BROKEN_TARGET``) is a corrupt PLY."""
    data = tmp_path / "data"
    shutil.copytree(easy_bunny_pair, data)
    (data / "easy" / BROKEN_TARGET).write_text("ply\nformat nonsense\n")
    return data
