"""Issue 5, end to end: a nightly ``gctr batch`` that survives bad inputs, kills and huge clouds.

Everything here goes through the real command line (``python -m gctr_cli batch`` in a subprocess)
and, for the good pairs, the real GCTR engine. One *mixed* manifest holds five good pairs built
from ``data/models/bunny.ply`` with known similarities (one of them with UTM-like 10^6 coordinates,
one with a few NaN/inf rows), one pair per bad input of the issue, four pairs with bad ground truth
and a nearly planar pair (must fail as planar, not return a confident wrong matrix); the module-scoped fixture
runs it once (``-j 2``) and the tests check its outputs. Worker crashes, timeouts, SIGKILL + resume,
-j independence and the lock are covered with the fake engine in ``test_batch.py`` /
``test_cli.py``; this file adds what those cannot show: the same guarantees with the real engine
and real files (kill the CLI mid-run, resume, compare with the uninterrupted run byte for byte),
the failure message of every bad input, the UTM offset, and the 2-million-point memory budget.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from conftest import PYTHON, REPO, read_csv, rotation, row_matrix, translation, write_manifest_rows

from gctr_cli import io as gio
from gctr_cli.batch import ERRORS_COLUMNS, LOCK_NAME, MATRIX_COLUMNS, TRANSFORMS_COLUMNS, derive_seed
from gctr_cli.config import Config
from gctr_cli.geometry import apply, split, to_matrix
from gctr_cli.io import PointCloudError, load_point_cloud, read_matrix, save_point_cloud, write_matrix
from gctr_cli.io import text as _text_module  # noqa: F401 - gio.text for monkeypatching
from gctr_cli.metrics import rotation_angle_deg

BUNNY = REPO / "data" / "models" / "bunny.ply"
N_GOOD = 4000  #: points per good cloud: ~0.8 s per pair with the default config

#: UTM-like offsets of the "utm" pair's source and target (metres east/north/up)
UTM_SOURCE = np.array([1.0e6, 2.0e6, 1.0e6])
UTM_TARGET = np.array([4.6e5, 5.2e6, 1.0e6])

needs_bunny = pytest.mark.skipif(not BUNNY.exists(), reason="data/models/bunny.ply not shipped")
linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses SIGKILL and getrusage semantics")


def gctr(*args, env=None, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "gctr_cli", *map(str, args)], capture_output=True, text=True, env=env,
                          timeout=timeout)


def by_id(rows):
    return {r["pair_id"]: r for r in rows}


def stable(row):
    """A transforms.csv row without its wall-clock column."""
    return {k: v for k, v in row.items() if k != "runtime_s"}


def ply_bytes(points: np.ndarray, n_declared: int | None = None) -> bytes:
    """A binary little-endian float64 PLY (``n_declared`` overrides the header's vertex count)."""
    n = len(points) if n_declared is None else n_declared
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty double x\n"
              "property double y\nproperty double z\nend_header\n").encode()
    return header + np.asarray(points, "<f8").tobytes()


# ----------------------------------------------------------------------------------------------------
# the mixed manifest
# ----------------------------------------------------------------------------------------------------


@dataclass
class Expected:
    """A bad pair: the file its message must name and the words that say what is wrong with it."""

    file: Path
    keywords: tuple[str, ...]
    names_file: bool = True  #: the failed row's message must contain the file's path


@dataclass
class Mixed:
    root: Path
    manifest: Path
    rows: list[dict]
    gt: dict[str, np.ndarray] = field(default_factory=dict)  #: ground truth of the good pairs
    good: tuple[str, ...] = ()
    bad: dict[str, Expected] = field(default_factory=dict)
    nan_source: Path | None = None
    utm_files: tuple[Path, Path] | None = None


def _bunny_pair(rng, base, diag, scale, angle, n=N_GOOD):
    """Two different samplings of the bunny with noise; the target moved by a known similarity."""
    src = base[rng.choice(len(base), n, replace=False)] + rng.normal(scale=0.002 * diag, size=(n, 3))
    tgt_model = base[rng.choice(len(base), n, replace=False)]
    T = to_matrix(scale, rotation(rng.normal(size=3), angle), rng.uniform(-1, 1, 3) * diag)
    tgt = apply(T, tgt_model) + rng.normal(scale=0.002 * diag * scale, size=(n, 3))
    return src, tgt, T


def build_mixed(root: Path) -> Mixed:
    rng = np.random.default_rng(20240505)
    base = load_point_cloud(BUNNY)
    base = base - base.mean(axis=0)
    diag = float(np.linalg.norm(base.max(0) - base.min(0)))
    root.mkdir(parents=True)
    good, bad = root / "good", root / "bad"
    rows: list[dict] = []
    m = Mixed(root=root, manifest=root / "pairs.csv", rows=rows)

    def rel(p: Path) -> str:
        return p.relative_to(root).as_posix()

    def add(pid: str, source: Path, target: Path, gt: Path | None = None) -> None:
        rows.append({"pair_id": pid, "source": rel(source), "target": rel(target), "gt": rel(gt) if gt else ""})

    def add_good(pid: str, src: np.ndarray, tgt: np.ndarray, T: np.ndarray, exts: tuple[str, str]) -> tuple[Path, Path]:
        s = good / f"{pid}_src{exts[0]}"
        t = good / f"{pid}_tgt{exts[1]}"
        save_point_cloud(s, src)
        save_point_cloud(t, tgt)
        g = root / "gt" / f"{pid}.txt"
        write_matrix(g, T)
        m.gt[pid] = T
        add(pid, s, t, g)
        return s, t

    # --- good pairs (the manifest interleaves them with the bad ones: a kill lands mid-run) ---
    src1, tgt1, T1 = _bunny_pair(rng, base, diag, 1.6, 50.0)
    s1, t1 = add_good("good_ply_pcd", src1, tgt1, T1, (".ply", ".pcd"))
    src2, tgt2, T2 = _bunny_pair(rng, base, diag, 0.6, 110.0)
    # ... and the same pair with a few non-finite rows in the source: dropped with a warning
    bad_rows = rng.choice(N_GOOD, 7, replace=False)
    src2_nan = src2.copy()
    src2_nan[bad_rows[:4], rng.integers(0, 3, 4)] = np.nan
    src2_nan[bad_rows[4:6], 1] = np.inf
    src2_nan[bad_rows[6], 2] = -np.inf

    bad.mkdir(parents=True)
    tgt_ok = t1  # the good target the bad sources are paired with

    def add_bad(pid: str, path: Path, keywords: tuple[str, ...], as_target: bool = False,
                names_file: bool = True) -> None:
        m.bad[pid] = Expected(path, keywords, names_file)
        add(pid, tgt_ok if as_target else path, path if as_target else tgt_ok)

    add_bad("missing", bad / "missing.ply", ("file does not exist",))
    (bad / "empty.pcd").write_bytes(b"")
    add_bad("empty", bad / "empty.pcd", ("file is empty",))
    (bad / "zero.ply").write_bytes(ply_bytes(np.empty((0, 3))))
    add_bad("zero_points", bad / "zero.ply", ("contains no points",))
    save_point_cloud(bad / "one.xyz", src1[:1])
    add_bad("one_point", bad / "one.xyz", ("too few points", "only 1 finite point"))
    save_point_cloud(bad / "two.pcd", src1[:2])
    add_bad("two_points", bad / "two.pcd", ("too few points", "only 2 finite points"), as_target=True)

    _s2, t2 = add_good("good_xyz_ply", src2, tgt2, T2, (".xyz", ".ply"))
    nan_src = good / "nan_few_src.xyz"
    save_point_cloud(nan_src, src2_nan)
    add("nan_few", nan_src, t2, root / "gt" / "good_xyz_ply.txt")
    m.gt["nan_few"] = T2
    m.nan_source = nan_src

    mostly_nan = src1.copy()
    mostly_nan[5:] = np.nan
    save_point_cloud(bad / "mostly_nan.ply", mostly_nan)
    add_bad("nan_most", bad / "mostly_nan.ply",
            ("too few points", "only 5 finite points", f"after dropping {N_GOOD - 5} non-finite"))
    save_point_cloud(bad / "all_nan.pcd", np.full((50, 3), np.nan))
    add_bad("nan_all", bad / "all_nan.pcd", ("no finite points", "all 50 points are non-finite"))
    full = ply_bytes(src1)
    (bad / "truncated.ply").write_bytes(full[: len(full) // 2])
    add_bad("truncated_ply", bad / "truncated.ply", ("truncated", f"header declares {N_GOOD} vertices"))
    (bad / "noise.ply").write_bytes(np.random.default_rng(1).bytes(5000))
    add_bad("noise_ply", bad / "noise.ply", ("not a PLY file",))
    (bad / "noise.pcd").write_bytes(np.random.default_rng(2).bytes(5000))
    add_bad("noise_pcd", bad / "noise.pcd", ("not a PCD file",), as_target=True)

    # --- the UTM pair and its centred copy: same clouds, same ground truth up to the offsets ---
    src3, tgt3, T3 = _bunny_pair(rng, base, diag, 2.2, 75.0)
    add_good("centred", src3, tgt3, T3, (".ply", ".ply"))
    m.utm_files = add_good("utm", src3 + UTM_SOURCE, tgt3 + UTM_TARGET,
                           translation(UTM_TARGET) @ T3 @ translation(-UTM_SOURCE), (".ply", ".pcd"))

    save_point_cloud(bad / "broken_header.pcd", src1[:100], binary=False)
    text = (bad / "broken_header.pcd").read_text().replace("SIZE 8 8 8", "SIZE 8 8")
    (bad / "broken_header.pcd").write_text(text)
    add_bad("pcd_broken_header", bad / "broken_header.pcd", ("broken PCD header", "SIZE has 2 entries"))
    save_point_cloud(bad / "cloud.xyz", src1)
    shutil.copy(bad / "cloud.xyz", bad / "cloud.obj")
    add_bad("unsupported", bad / "cloud.obj", ("unsupported extension '.obj'",))
    save_point_cloud(bad / "identical.ply", np.tile([0.01, -0.02, 0.03], (500, 1)))
    add_bad("identical", bad / "identical.ply", ("degenerate cloud", "all 500 points are identical"))
    t = rng.uniform(-0.1, 0.1, size=(500, 1))
    save_point_cloud(bad / "line.pcd", np.array([0.01, 0.02, -0.03]) + t * np.array([0.3, -0.5, 0.8]))
    add_bad("collinear", bad / "line.pcd", ("degenerate cloud", "collinear"))
    uv = rng.uniform(-0.1, 0.1, size=(N_GOOD, 2))
    plane = np.c_[uv, np.zeros(N_GOOD)] @ rotation([1.0, 2.0, 0.5], 30.0).T + 0.05
    save_point_cloud(bad / "plane.ply", plane)
    add_bad("planar", bad / "plane.ply", ("points are planar",))
    # a scanned flat wall: planar up to a noise of 1e-4 of its size (must fail as planar)
    R4 = rotation([1.0, 2.0, 3.0], 40.0)
    wall = [np.c_[rng.uniform(-0.1, 0.1, size=(N_GOOD, 2)), rng.normal(scale=2e-5, size=N_GOOD)] for _ in range(2)]
    T4 = to_matrix(1.5, R4, [0.1, 0.2, 0.3])
    save_point_cloud(good / "wall_src.ply", wall[0])
    save_point_cloud(good / "wall_tgt.ply", apply(T4, wall[1]))
    write_matrix(root / "gt" / "nearly_planar.txt", T4)
    add("nearly_planar", good / "wall_src.ply", good / "wall_tgt.ply", root / "gt" / "nearly_planar.txt")

    # --- per-pair ground-truth problems (good clouds: they fail before the engine runs) ---
    gt_bad = root / "gt_bad"
    gt_bad.mkdir()
    gt_cases = {
        "gt_missing": (None, ("file does not exist",)),
        "gt_malformed": ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", ("expected 4 rows of 4 numbers, found 3",)),
        "gt_shear": ("1 0.5 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", ("not a similarity transform", "not a scaled rotation")),
        "gt_reflection": ("-1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", ("not a similarity transform", "reflection")),
    }
    for pid, (text, keywords) in gt_cases.items():
        g = gt_bad / f"{pid}.txt"
        if text is not None:
            g.write_text(text)
        m.bad[pid] = Expected(g, ("ground truth",) + keywords)
        add(pid, s1, t1, g)

    m.good = ("good_ply_pcd", "good_xyz_ply", "nan_few", "centred", "utm")
    write_manifest_rows(m.manifest, rows)
    return m


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """The mixed manifest and one uninterrupted ``gctr batch -j 2`` of it (the reference run)."""
    if not BUNNY.exists():
        pytest.skip("data/models/bunny.ply not shipped")
    m = build_mixed(tmp_path_factory.mktemp("mixed") / "data")
    out = m.root.parent / "out"
    t0 = time.monotonic()
    proc = gctr("batch", m.manifest, "-o", out, "-j", 2)
    return m, out, proc, time.monotonic() - t0


# ----------------------------------------------------------------------------------------------------
# item 1: bad input -> one failed row each, specific message; everything else completes
# ----------------------------------------------------------------------------------------------------


@pytest.mark.engine
def test_mixed_batch_every_pair_has_one_row_and_bad_inputs_say_what_is_wrong(mixed):
    m, out, proc, wall = mixed
    assert proc.returncode == 1, proc.stdout + proc.stderr  # some pairs failed, the batch finished

    header, rows = read_csv(out / "transforms.csv")
    assert header == list(TRANSFORMS_COLUMNS)
    ids = [r["pair_id"] for r in rows]
    assert sorted(ids) == sorted(r["pair_id"] for r in m.rows)  # every pair exactly once
    rows = by_id(rows)
    raw = (out / "transforms.csv").read_bytes()
    assert raw.endswith(b"\n") and raw.count(b"\n") == len(m.rows) + 1  # one physical line per pair

    for pid, exp in m.bad.items():
        r = rows[pid]
        assert r["status"] == "failed", (pid, r["message"])
        if exp.names_file:
            assert str(exp.file) in r["message"], (pid, r["message"])  # names the file ...
        else:  # the engine's message names the role; the row's source column names the file
            assert r["source"] == str(exp.file), pid
        for kw in exp.keywords:  # ... and the specific problem
            assert kw in r["message"], (pid, kw, r["message"])
        assert all(r[c] == "" for c in ("scale",) + MATRIX_COLUMNS), pid
        assert not (out / "matrices" / f"{pid}.txt").exists(), pid
        assert "\n" not in r["message"]
        assert int(r["seed"]) == derive_seed(0, pid)

    erows = by_id(read_csv(out / "tm_errors.csv")[1])
    assert read_csv(out / "tm_errors.csv")[0] == list(ERRORS_COLUMNS)
    # failed pairs have no error row, even with a gt file
    assert sorted(erows) == sorted(m.good)
    success = Config().success
    for pid in m.good:
        r = rows[pid]
        assert r["status"] == "ok", (pid, r["message"])
        assert np.array_equal(row_matrix(r), read_matrix(out / "matrices" / f"{pid}.txt"))  # full precision
        e = erows[pid]
        assert e["success"] == "true", (pid, e)
        assert float(e["rot_err_deg"]) < success.rotation_deg
        assert float(e["trans_err_rel"]) < success.translation_rel
        assert float(e["scale_err"]) < success.scale
    assert all(rows[p]["message"] == "" for p in m.good if p != "nan_few")

    # the summary a cron job mails: counts, then every failed pair with its message
    n_failed = len(m.bad) + (rows["nearly_planar"]["status"] == "failed")
    assert f"pairs: {len(m.rows)} ({len(m.rows) - n_failed} ok, {n_failed} failed)" in proc.stdout
    n_gt = sum(bool(r["gt"]) for r in m.rows)  # the good pairs, nearly_planar and the four bad-gt pairs
    assert f"success: {len(m.good)}/{n_gt} pairs with ground truth" in proc.stdout
    for pid in m.bad:
        assert f"  {pid}: {rows[pid]['message']}" in proc.stdout
    print(f"mixed batch: {len(m.rows)} pairs in {wall:.1f} s")


@pytest.mark.engine
def test_a_few_non_finite_points_are_dropped_with_a_warning(mixed):
    m, out, proc, _ = mixed
    r = by_id(read_csv(out / "transforms.csv")[1])["nan_few"]
    warning = f"{m.nan_source}: dropped 7 of {N_GOOD} points with non-finite (NaN/inf) coordinates"
    assert r["status"] == "ok"
    assert r["message"] == f"warning: {warning}"
    assert f"gctr: WARNING: pair nan_few: {warning}" in proc.stderr  # also in the log of the run
    # the 3993 finite points register as well as the same pair without the bad rows
    e = by_id(read_csv(out / "tm_errors.csv")[1])
    assert e["nan_few"]["success"] == "true"
    assert float(e["nan_few"]["rot_err_deg"]) < float(e["good_xyz_ply"]["rot_err_deg"]) + 0.5


@pytest.mark.engine
def test_planar_cloud_message_names_the_file(mixed):
    m, out, _, _ = mixed
    r = by_id(read_csv(out / "transforms.csv")[1])["planar"]
    assert r["status"] == "failed" and "planar" in r["message"]
    assert str(m.bad["planar"].file) in r["message"], r["message"]


@pytest.mark.engine
def test_nearly_planar_clouds_fail_instead_of_returning_a_wrong_transform(mixed):
    _m, out, _, _ = mixed
    r = by_id(read_csv(out / "transforms.csv")[1])["nearly_planar"]
    assert r["status"] == "failed" and "planar" in r["message"], (r["status"], r["message"], r["m00"])


@pytest.mark.engine
def test_utm_offset_registers_as_accurately_as_the_centred_copy(mixed):
    m, out, _, _ = mixed
    rows = by_id(read_csv(out / "transforms.csv")[1])
    errs = by_id(read_csv(out / "tm_errors.csv")[1])
    T_c, T_u = row_matrix(rows["centred"]), row_matrix(rows["utm"])
    for pid in ("centred", "utm"):
        e = errs[pid]
        assert e["success"] == "true", e
        # far inside the 5 deg / 5 % / 5 % thresholds: the offset costs no accuracy
        assert float(e["rot_err_deg"]) < 1.0 and float(e["trans_err_rel"]) < 0.01 and float(e["scale_err"]) < 0.01, e
    # the matrix is reported at full precision in the files' own coordinates: the 1e6 translation
    # is there, and removing the offsets gives back (about) the centred pair's transform
    assert np.abs(T_u[:3, 3]).max() > 1e6
    back = translation(-UTM_TARGET) @ T_u @ translation(UTM_SOURCE)
    s_b, R_b, _ = split(back)
    s_c, R_c, _ = split(T_c)
    assert rotation_angle_deg(R_b.T @ R_c) < 0.5
    assert abs(s_b / s_c - 1) < 0.005
    src = load_point_cloud(m.root / next(r["source"] for r in m.rows if r["pair_id"] == "centred"))
    c = src.mean(axis=0)
    tgt_diag = float(np.linalg.norm(np.ptp(apply(m.gt["centred"], src), axis=0)))
    assert np.linalg.norm(apply(back, c[None]) - apply(T_c, c[None])) < 0.005 * tgt_diag

    # with the same seed the offset pair gives the centred pair's transform up to rounding
    reg = gctr("register", *m.utm_files, "--seed", rows["centred"]["seed"], "-o", out.parent / "utm_seeded.txt")
    assert reg.returncode == 0, reg.stdout + reg.stderr
    back = translation(-UTM_TARGET) @ read_matrix(out.parent / "utm_seeded.txt") @ translation(UTM_SOURCE)
    np.testing.assert_allclose(back[:3, :3], T_c[:3, :3], rtol=0, atol=1e-6 * np.abs(T_c[:3, :3]).max())
    assert np.linalg.norm(apply(back, c[None]) - apply(T_c, c[None])) < 1e-6 * tgt_diag


# ----------------------------------------------------------------------------------------------------
# manifest problems: fatal ones stop before anything runs (exit 2) and never touch earlier outputs
# ----------------------------------------------------------------------------------------------------


@pytest.mark.engine
@pytest.mark.parametrize(
    "case, keywords",
    [
        ("duplicate_pair_id", ("duplicate pair_id 'good_ply_pcd'", "first on line 2")),
        ("missing_column", ("missing required column 'source'",)),
        ("empty_cell", ("empty 'target' cell",)),
        ("unsafe_pair_id", ("pair_id '../evil'", "unsafe as a file name")),
    ],
)
def test_fatal_manifest_problems_exit_2_and_leave_the_outputs_alone(mixed, tmp_path, case, keywords):
    m, ref_out, _, _ = mixed
    out = tmp_path / "out"
    shutil.copytree(ref_out, out)  # last night's finished run; tonight's cron job reruns with --resume
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    rows = [dict(r) for r in m.rows]
    columns = ("pair_id", "source", "target", "gt")
    if case == "duplicate_pair_id":
        rows.append(dict(rows[0], source=rows[5]["source"]))
    elif case == "missing_column":
        columns = ("pair_id", "target", "gt")
    elif case == "empty_cell":
        rows[3]["target"] = ""
    else:
        rows[2]["pair_id"] = "../evil"
    manifest = write_manifest_rows(m.root / f"{case}.csv", rows, columns=columns)

    proc = gctr("batch", manifest, "-o", out, "--resume", "-j", 2)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stdout == ""  # nothing ran, no summary
    assert proc.stderr.startswith(f"gctr: error: {manifest}: ")
    for kw in keywords:
        assert kw in proc.stderr, (kw, proc.stderr)
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before  # not a byte changed, no lock left behind
    assert not (out / LOCK_NAME).exists()


# ----------------------------------------------------------------------------------------------------
# items 3 and 4 with the real engine: SIGKILL mid-run, --resume, identical to the uninterrupted run
# ----------------------------------------------------------------------------------------------------


def _alive(pid: int) -> bool:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] not in ("Z", "X")


def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            continue
    return kids


@pytest.mark.engine
@pytest.mark.slow  # ~8 s
@linux_only
def test_sigkill_mid_run_then_resume_matches_the_uninterrupted_run(mixed, tmp_path):
    m, ref_out, ref_proc, _ = mixed
    assert ref_proc.returncode == 1
    out = tmp_path / "out"
    cmd = [PYTHON, "-m", "gctr_cli", "batch", str(m.manifest), "-o", str(out)]
    proc = subprocess.Popen(cmd + ["-j", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            t = out / "transforms.csv"
            if t.exists() and t.read_bytes().count(b"\n") >= 3:  # header + 2 pairs
                break
            assert proc.poll() is None, "the batch ended before it could be killed"
            time.sleep(0.02)
        else:
            pytest.fail("no rows within 120 s")
        workers = _children(proc.pid)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    deadline = time.monotonic() + 10  # the workers die with the batch (no orphans computing)
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(w) for w in workers)
    n_before = len(read_csv(out / "transforms.csv")[1])
    assert 2 <= n_before < len(m.rows), "the kill must land mid-run"
    assert (out / LOCK_NAME).exists()  # stale: taken over by the resume

    done = subprocess.run(cmd + ["--resume", "-j", "2"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 1, done.stdout + done.stderr  # the bad pairs still fail
    assert f"({n_before} done by an earlier run)" in done.stdout
    raw = (out / "transforms.csv").read_bytes()
    assert raw.endswith(b"\n") and raw.count(b"\n") == len(m.rows) + 1
    rows = read_csv(out / "transforms.csv")[1]
    assert sorted(r["pair_id"] for r in rows) == sorted(r["pair_id"] for r in m.rows)  # each exactly once

    # the same rows (transforms, messages, seeds, fitness) as the uninterrupted -j 2 run
    ref = by_id(read_csv(ref_out / "transforms.csv")[1])
    assert {r["pair_id"]: stable(r) for r in rows} == {k: stable(v) for k, v in ref.items()}
    assert sorted(read_csv(out / "tm_errors.csv")[1], key=lambda r: r["pair_id"]) == sorted(
        read_csv(ref_out / "tm_errors.csv")[1], key=lambda r: r["pair_id"])
    names = sorted(p.name for p in (out / "matrices").iterdir())
    assert names == sorted(p.name for p in (ref_out / "matrices").iterdir())  # no temporary files either
    assert set(names) >= {f"{p}.txt" for p in m.good}
    for name in names:
        assert (out / "matrices" / name).read_bytes() == (ref_out / "matrices" / name).read_bytes()
    assert not (out / LOCK_NAME).exists()


# ----------------------------------------------------------------------------------------------------
# item 5: a 2-million-point cloud within 2 GB per worker
# ----------------------------------------------------------------------------------------------------

MEASURE = textwrap.dedent(
    """
    import json, resource, subprocess, sys, time
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "gctr_cli", *sys.argv[1:]], capture_output=True, text=True)
    # the batch process reaps its workers, this process reaps the batch: the largest of them all
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print(json.dumps({"returncode": proc.returncode, "peak_mib": peak_kib / 1024, "wall_s": time.monotonic() - t0,
                      "stdout": proc.stdout, "stderr": proc.stderr}))
    """
)


@pytest.mark.engine
@pytest.mark.slow  # ~13 s
@needs_bunny
@linux_only
def test_two_million_points_register_within_2_gb_per_worker(tmp_path):
    rng = np.random.default_rng(5)
    base = load_point_cloud(BUNNY)
    base = base - base.mean(axis=0)
    diag = float(np.linalg.norm(np.ptp(base, axis=0)))
    T = to_matrix(1.7, rotation([0.3, -1.0, 0.4], 65.0), [0.2, -0.1, 0.05])
    save_point_cloud(tmp_path / "target.ply", apply(T, base[rng.choice(len(base), 20_000, replace=False)]))
    write_matrix(tmp_path / "gt.txt", T)

    # 2 M distinct points: the bunny upsampled with a jitter of 0.1 % of its diagonal, binary PLY
    n = 2_000_000
    big = base[rng.integers(0, len(base), n)] + rng.normal(scale=0.001 * diag, size=(n, 3))
    (tmp_path / "big.ply").write_bytes(ply_bytes(big))
    del big
    # 2 M lines of text with colour columns (a typical LiDAR export), built from a repeated block
    block = base[rng.choice(len(base), 10_000, replace=False)] + rng.normal(scale=0.001 * diag, size=(10_000, 3))
    colours = rng.integers(0, 256, size=(10_000, 3))
    text = "".join(f"{x:.6f} {y:.6f} {z:.6f} {r} {g} {b}\n"
                   for (x, y, z), (r, g, b) in zip(block.tolist(), colours.tolist()))
    (tmp_path / "big.xyz").write_bytes(text.encode() * (n // 10_000))

    rows = [{"pair_id": "big_ply", "source": "big.ply", "target": "target.ply", "gt": "gt.txt"},
            {"pair_id": "big_xyz", "source": "big.xyz", "target": "target.ply", "gt": "gt.txt"}]
    manifest = write_manifest_rows(tmp_path / "pairs.csv", rows)
    script = tmp_path / "measure.py"
    script.write_text(MEASURE)
    res = subprocess.run([PYTHON, str(script), "batch", str(manifest), "-o", str(tmp_path / "out"), "-j", "2"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["returncode"] == 0, info["stdout"] + info["stderr"]
    errs = by_id(read_csv(tmp_path / "out" / "tm_errors.csv")[1])
    rows = by_id(read_csv(tmp_path / "out" / "transforms.csv")[1])
    print(f"2M points: peak RSS {info['peak_mib']:.0f} MiB, wall {info['wall_s']:.1f} s, pair runtimes "
          + ", ".join(f"{p} {float(r['runtime_s']):.1f} s" for p, r in rows.items()))
    assert info["peak_mib"] < 2048, info
    for pid in ("big_ply", "big_xyz"):
        assert rows[pid]["status"] == "ok", rows[pid]["message"]
        assert errs[pid]["success"] == "true", errs[pid]
        assert float(rows[pid]["runtime_s"]) < 60


READ_PEAK = textwrap.dedent(
    """
    import json, resource, sys
    from gctr_cli.io import load_point_cloud
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    pts = load_point_cloud(sys.argv[1])
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    print(json.dumps({"shape": pts.shape, "grown_mib": grown / 1024, "sum": float(pts.sum())}))
    """
)


@linux_only
def test_text_clouds_are_read_with_memory_proportional_to_the_points(tmp_path):
    """The .xyz/.pts/.txt reader used to hold every line as Python strings (~650 bytes per point,
    1.3 GB for 2 M points); it now reads blocks of whole lines (~70 bytes per point)."""
    rng = np.random.default_rng(3)
    block = rng.normal(size=(5000, 3))
    text = "".join(f"{x!r} {y!r} {z!r} 255 128 0\n" for x, y, z in block.tolist())
    path = tmp_path / "big.xyz"
    path.write_bytes(b"X Y Z R G B\n" + text.encode() * 100)  # 500 000 points, 38 MB of text
    script = tmp_path / "read_peak.py"
    script.write_text(READ_PEAK)
    res = subprocess.run([PYTHON, str(script), str(path)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["shape"] == [500_000, 3]
    assert info["sum"] == pytest.approx(100 * block.sum(), rel=1e-9)
    nbytes_mib = 500_000 * 3 * 8 / 2**20  # 11.4 MiB of float64 points
    assert info["grown_mib"] < 4 * nbytes_mib + 64, info  # old reader: ~330 MiB


@pytest.mark.parametrize("first, block", [(8, 8), (16, 64), (64, 100), (1 << 16, 1 << 23)])
def test_block_reader_matches_the_line_format_across_block_boundaries(tmp_path, monkeypatch, first, block):
    """Header lines, a count line, comments, CRLF, commas, extra columns and blank lines split over
    blocks of any size parse the same, and errors keep the file's line numbers."""
    monkeypatch.setattr(gio.text, "_TEXT_FIRST_BLOCK", first)
    monkeypatch.setattr(gio.text, "_TEXT_BLOCK", block)
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(40, 3))
    lines = [f"{x!r} {y!r} {z!r}" for x, y, z in pts.tolist()]
    lines[3] = lines[3].replace(" ", ",")
    lines[9] += " 12 200 7"
    lines[20] = "  " + lines[20].replace(" ", "\t") + "  "
    body = "\r\n".join(lines[:10]) + "\r\n# a comment\n\n// another\n" + "\n".join(lines[10:30]) + "\n   \n"
    body += "\n".join(lines[30:])
    path = tmp_path / "c.xyz"
    path.write_bytes(("\ufeffX Y Z\n40\n" + body).encode())
    np.testing.assert_array_equal(load_point_cloud(path), pts)

    # errors name the first bad line of the file, wherever the blocks end
    all_lines = ("X Y Z\n40\n" + body).splitlines()
    bad_at = all_lines.index(lines[25]) + 1
    path.write_bytes(("X Y Z\n40\n" + body.replace(lines[25], "1.0 2.0 oops")).encode())
    with pytest.raises(PointCloudError, match=rf"line {bad_at}: non-numeric value 'oops'"):
        load_point_cloud(path)
    path.write_bytes(("X Y Z\n40\n" + body.replace(lines[25], "1.0 2.0 oops").replace(lines[33], "1 2")).encode())
    with pytest.raises(PointCloudError, match=rf"line {bad_at}: non-numeric value 'oops'"):
        load_point_cloud(path)  # the earlier of two problems
    path.write_bytes(("X Y Z\n40\n" + body.replace(lines[33], "1 2")).encode())
    with pytest.raises(PointCloudError, match=rf"line {all_lines.index(lines[33]) + 1} has 2 column\(s\)"):
        load_point_cloud(path)
