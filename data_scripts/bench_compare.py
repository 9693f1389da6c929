"""Side-by-side benchmark: gctr against the comparison methods on exactly the same pairs (issue 4).

    python -m data_scripts.bench_compare                 # full: make bench   -> bench/RESULTS.md + PNGs
    python -m data_scripts.bench_compare --quick         # make bench-quick (< 5 min on 2 cores), report in
                                                         # bench/work/compare-quick/ (the committed one is full)
    python -m data_scripts.bench_compare --report-only   # re-render the report from an earlier run

Steps:

1. **Pairs.** ``python -m data_scripts.make_benchmark generate --levels
   easy,cross,hard,real,part,lowoverlap,sfm,scene --pairs-per-model N --seed S`` into ``<work>/data`` (the
   pairs of ``make bench-engine`` for N = 10; S = 0 the report set, S = 1 the tuning set, work folder
   ``compare-<mode>-seed1``); ``--quick`` uses 1 pair per model/scene and level and 1 real pair per group —
   the first of each, identical to the full run's. Skipped when ``<work>/data`` already holds
   the output of the same command. The pairs and the success thresholds (``success:`` of the default
   config) are fixed before any method runs.
2. **Runs.** Level by level (every method on a level before the next level, the methods' order
   reversed on every second level: :func:`batch_order`), for every method the user-facing command
   ``gctr batch <work>/data/<level>/pairs.csv -c <work>/configs/<method>.yaml -o <work>/results/<method>/<level>
   -j J -q`` where the config is the default one with ``method:`` set: the rows are the same
   ``transforms.csv`` / ``tm_errors.csv`` users get.
3. **Report.** ``bench/RESULTS.md`` and the PNG plots next to it (``--out``).

What is measured:

* **time per pair** = the ``runtime_s`` column of ``transforms.csv``: wall time of the method's
  ``register`` call inside the worker (loading the files excluded), with one BLAS/OpenMP/Open3D thread
  per worker (the batch runner sets this). ``-j 1`` (full run) gives every pair a core to itself;
  competing load from other processes inflates it — the load average is sampled every 5 s and reported.
* **peak memory** = ``ru_maxrss`` of ``getrusage(RUSAGE_CHILDREN)`` read in a fresh wrapper process
  that runs exactly one ``gctr batch`` (so values do not accumulate across batches): the peak resident
  set of the largest single process of that batch — in practice the worker, over all the pairs it ran.
  It includes the interpreter + numpy/scipy/Open3D import baseline, measured the same way and reported.
  (Linux folds a parent's high-water mark into a child's at ``execve``; the CLI parent is smaller than
  a worker, so the figure is the worker's.)
* **CPU per pair** = user + system CPU time of the whole batch (same ``getrusage``) / pairs; includes
  the worker start-up, so it is an upper bound, but it is not inflated by other processes' load.
* **accuracy**: from ``tm_errors.csv`` (rotation geodesic angle; translation = distance between where
  the estimate and the truth put the source centroid, relative to the target's bounding-box diagonal;
  ``|s/s_gt - 1|``; TM = ``||T - T_gt||_F``, the paper's TM error; the paper
  reports ``log(TM)``, natural log: its GCTR row has T 1.89 and log(TM) 0.69). Medians are over *all*
  pairs of a level, a pair without a transform (status ``failed``) counting as an infinite error, so a
  method cannot improve its medians by giving up on hard pairs.
* **stage profile**: ``RegistrationResult.timings`` of gctr and of the fastest global baseline, run
  in-process on the first pairs of each level (to say where the time goes).
"""

from __future__ import annotations

import os

from gctr_cli.fsutil import THREAD_ENV_VARS  # no numpy import: safe before the thread caps are set

for _var in THREAD_ENV_VARS:
    os.environ.setdefault(_var, "1")  # the in-process stage profile runs single-threaded, as a batch worker

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import shlex  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator, Sequence  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from data_scripts.common import (  # noqa: E402
    DIAGNOSIS_MARGIN,
    confidence_sweep,
    diagnose,
    diagnosis_table,
    float_or_nan,
    machine_info,
    outcome,
    outcome_table,
    plot_confidence_tradeoff,
    sweep_table,
    sweep_thresholds,
    usable_transform,
)
from gctr_cli.methods import METHODS as REGISTERED_METHODS  # noqa: E402
from gctr_cli.methods import is_available  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
#: every method of the registry (gctr_cli.methods); a run without --methods takes those that are installed
METHODS = REGISTERED_METHODS
#: global (pose-independent) comparison methods: the time goal and the stage profile compare gctr with them
GLOBAL_BASELINES = ("fpfh_ransac", "fgr", "kiss_matcher")
SYNTHETIC_LEVELS = ("easy", "cross", "hard")
ALL_LEVELS = (*SYNTHETIC_LEVELS, "real", "part", "lowoverlap", "sfm", "scene")
#: levels whose pairs differ in density, outliers/partial overlap and scale (goal: gctr strictly better)
CROSS_SOURCE_LEVELS = ("cross", "hard", "real", "part", "lowoverlap", "sfm", "scene")
TRADEOFF_PNG = "compare_confidence_tradeoff.png"
LEVEL_DESCRIPTIONS = {
    "easy": "1/2 density, 0.25% noise, no outliers, 90–100% crops, scale 0.5–2",
    "cross": "1/4 density, 0.5% noise, 10% outliers, 70–90% crops, scale 0.5–2",
    "hard": "1/8 density, 1% noise, 30% outliers, 50–90% crops, scale 0.25–4",
    "real": "real range scans with their true relative pose (bunny scan pairs x3 draws, dragon scan pairs x2, bunny "
            "scans vs the reconstruction), random similarity on the source, 1/4 density target",
    "part": "a 15–40% ball patch vs the whole model at 1/4 density (patch as source / as target alternately), 0.5% "
            "noise, 10% outliers, scale 0.5–2",
    "lowoverlap": "two slab crops sharing 25–50% of their points, 1/4 density, 0.5% noise, 5–10% outliers, scale 0.5–2",
    "sfm": "photogrammetry-like target (20x density field, 2–4 holes, 1% depth / 0.2% lateral noise, 5–10% clustered "
           "floaters) vs a 70–100% crop with 0.25% noise, scale 0.5–2",
    "scene": "windows (25–60% overlap) of 3DMatch redkitchen fragments 0 and 4 and an NCLT LiDAR sweep, density "
             "1/4–1/2, 0.3–0.5% noise, 5% outliers, scale 0.5–2; plus the real redkitchen 0→4 pair",
}
METHOD_DESCRIPTIONS = {
    "gctr": "GCTR engine, default config (`engine:` section)",
    "icp": "statistical outlier removal, centroid + bounding-box-diagonal normalisation, Open3D point-to-point "
           "ICP with scale (`with_scaling=True`), distance 0.05 × diagonal, from the identity",
    "fpfh_ransac": "same cleaning + normalisation, voxel 0.02 × diagonal, FPFH (radii 2 / 5 voxels), Open3D RANSAC "
                   "feature matching (similarity hypotheses, mutual filter off, edge-length 0.9 + distance "
                   "checkers, ≤ 100k iterations, confidence 0.999, seeded, 1 thread), scaled ICP refinement",
    "fgr": "same cleaning, normalisation and features, Open3D Fast Global Registration, scaled ICP refinement",
    "cpd": "same cleaning + normalisation, rigid CPD with scale (numpy), both clouds subsampled to ≤ 1500 points "
           "(seeded), w = 0.1, EM to a relative objective change < 1e-6 or 150 iterations",
    "kiss_matcher": "same cleaning + normalisation, clouds scaled to a 20 m diagonal for KISS-Matcher 1.0.2 (pip "
                    "`kiss-matcher`, optional: GPL-3.0 code inside), voxel 0.4 m = 0.02 × diagonal, Faster-PFH (radii "
                    "3 / 5 voxels), ROBIN max-core pruning, GNC-TLS rigid solver (its own TBB threads), scale undone, "
                    "scaled ICP refinement",
}
PAPER_TABLE1 = (  # GCTR paper, Table 1 ("Angle" synthetic pair): R, T (absolute units), S, log(TM), time (s)
    ("CPD", "2.82", "64.4", "0.24", "4.21", "435"),
    ("ICP", "3.38", "50.1", "0.06", "3.98", "103"),
    ("Super4PCS", "0.22", "3.41", "0.06", "1.3", "333"),
    ("GCTR (paper)", "0.069", "1.89", "0.03", "0.69", "61.6"),
)
#: extra runs that justify a setup choice: (name, method, config overrides, level)
ABLATIONS = (
    ("fpfh_ransac-no_outlier_removal", "fpfh_ransac", {"baselines": {"outlier_removal": "none"}}, "cross"),
    ("fgr-no_outlier_removal", "fgr", {"baselines": {"outlier_removal": "none"}}, "cross"),
)
CDF_PNG = "compare_rotation_cdf.png"
TIME_PNG = "compare_time.png"


class BenchError(Exception):
    """The benchmark cannot run (bad arguments, a batch that could not start)."""


# ============================================================================================ settings
@dataclass(frozen=True)
class Settings:
    mode: str  # "full" or "quick"
    pairs_per_model: int
    seed: int
    workers: int
    methods: tuple[str, ...]
    levels: tuple[str, ...]
    profile_pairs: int  # pairs per level for the in-process stage profile (0 = none)
    models: tuple[str, ...] = ()  # model files (empty: the generator's default, the 3 shipped models)
    n_source: int | None = None  # source points per pair (None: the generator's default, 20000)

    def generate_command(self, data: Path) -> list[str]:
        cmd = [sys.executable, "-m", "data_scripts.make_benchmark", "generate", "--levels", ",".join(self.levels),
               "--pairs-per-model", str(self.pairs_per_model), "--seed", str(self.seed), "--out", str(data)]
        if self.models:
            cmd += ["--models", ",".join(self.models)]
        if self.n_source is not None:
            cmd += ["--n-source", str(self.n_source)]
        if self.mode == "quick" and "real" in self.levels:
            cmd += ["--real-per-group", "1"]
        return cmd


def settings_from_args(args: argparse.Namespace) -> Settings:
    quick = bool(args.quick)
    methods = tuple(_split(args.methods)) if args.methods else default_methods()
    levels = tuple(_split(args.levels)) if args.levels else ALL_LEVELS
    bad = [m for m in methods if m not in METHODS] + [lv for lv in levels if lv not in ALL_LEVELS]
    if bad:
        raise BenchError(f"unknown method(s)/level(s): {', '.join(bad)}")
    missing = [m for m in methods if not is_available(m)]
    if missing:
        raise BenchError(f"method(s) {', '.join(missing)} need an optional package that is not installed "
                         "(kiss_matcher: pip install kiss-matcher)")
    return Settings(
        mode="quick" if quick else "full",
        pairs_per_model=args.pairs_per_model if args.pairs_per_model is not None else (1 if quick else 10),
        seed=args.seed,
        workers=args.workers if args.workers is not None else (2 if quick else 1),
        methods=methods,
        levels=levels,
        profile_pairs=args.profile_pairs if args.profile_pairs is not None else (1 if quick else 2),
        models=tuple(_split(args.models)) if args.models else (),
        n_source=args.n_source,
    )


def default_methods() -> tuple[str, ...]:
    """Every registered method whose optional package (if any) is installed; the others are named on stderr."""
    skipped = [m for m in METHODS if not is_available(m)]
    if skipped:
        _log(f"not run (optional package not installed): {', '.join(skipped)}")
    return tuple(m for m in METHODS if m not in skipped)


def _split(value: str) -> list[str]:
    return [v.strip() for v in value.split(",") if v.strip()]


# ============================================================================================ machine
def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return math.nan


class LoadSampler:
    """Samples the 1-minute load average every ``interval`` seconds in a background thread."""

    def __init__(self, interval: float = 5.0) -> None:
        self.interval = interval
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append(load_average())
            self._stop.wait(self.interval)

    def __enter__(self) -> LoadSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()


# ============================================================================================ data
def ensure_data(settings: Settings, data: Path) -> list[str]:
    """Generate the pairs into ``data`` unless it already holds the output of the same command."""
    cmd = settings.generate_command(data)
    shown = ["python", *cmd[1:]]
    stamp = data / "bench_compare_generate.json"
    key = {"args": cmd[2:], "generator": _file_digest(REPO_ROOT / "data_scripts" / "make_benchmark.py")}
    if stamp.is_file() and (data / "pairs.csv").is_file():
        try:
            if json.loads(stamp.read_text()) == key:
                return shown
        except (OSError, ValueError):
            pass
    if data.exists():
        shutil.rmtree(data)
    _log(f"generating the pairs: {shlex.join(shown)}")
    done = subprocess.run(cmd, cwd=REPO_ROOT, stdout=subprocess.DEVNULL)
    if done.returncode != 0:  # its own message (e.g. where the shared data is) is already on stderr
        raise BenchError(f"generating the pairs into {data} failed (exit status {done.returncode})")
    stamp.write_text(json.dumps(key))
    return shown


def _file_digest(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def read_manifest_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


# ============================================================================================ runs
@dataclass
class BatchRun:
    """One ``gctr batch`` of one method on one level."""

    method: str
    level: str
    n_pairs: int
    command: list[str]
    exit_code: int = -1
    wall_s: float = math.nan
    cpu_s: float = math.nan  # user + system of the batch's processes
    peak_rss_mb: float = math.nan  # largest single process of the batch
    load_before: float = math.nan
    load_after: float = math.nan
    stderr_tail: str = ""


_MEASURE_CODE = (
    "import json, resource, subprocess, sys, time\n"
    "t = time.perf_counter()\n"
    "p = subprocess.run(sys.argv[2:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)\n"
    "wall = time.perf_counter() - t\n"
    "u = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
    "json.dump({'exit_code': p.returncode, 'wall_s': wall, 'cpu_s': u.ru_utime + u.ru_stime,\n"
    "           'peak_rss_mb': u.ru_maxrss / 1024.0, 'stderr_tail': p.stderr[-2000:]}, open(sys.argv[1], 'w'))\n"
)


def measure(command: list[str], record: Path) -> dict[str, Any]:
    """Run ``command`` in a fresh wrapper process; its children's peak RSS and CPU time, wall time, exit code."""
    subprocess.run([sys.executable, "-c", _MEASURE_CODE, str(record), *command], cwd=REPO_ROOT, check=True)
    return json.loads(record.read_text())


def gctr_executable() -> list[str]:
    exe = Path(sys.executable).with_name("gctr")
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "gctr_cli"]


def write_method_config(path: Path, method: str, overrides: dict[str, Any] | None = None) -> None:
    """The default config with ``method:`` set (and ``overrides``; everything else: defaults)."""
    import yaml

    from gctr_cli.config import config_from_dict

    data = {"method": method, **(overrides or {})}
    config_from_dict(data, str(path))  # fail here, not in every batch
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def run_one_batch(name: str, level: str, config: Path, settings: Settings, work: Path, data: Path) -> BatchRun:
    """``gctr batch`` of one level's manifest with one config, measured (see the module docstring)."""
    manifest = data / level / "pairs.csv"
    out = work / "results" / name / level
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [*gctr_executable(), "batch", str(manifest), "-c", str(config), "-o", str(out),
           "-j", str(settings.workers), "-q"]
    run = BatchRun(method=name, level=level, n_pairs=len(read_manifest_rows(manifest)), command=cmd)
    run.load_before = load_average()
    m = measure(cmd, work / "results" / f".{name}_{level}_measure.json")
    run.load_after = load_average()
    run.exit_code, run.wall_s, run.cpu_s = int(m["exit_code"]), m["wall_s"], m["cpu_s"]
    run.peak_rss_mb, run.stderr_tail = m["peak_rss_mb"], m["stderr_tail"]
    if run.exit_code not in (0, 1):
        raise BenchError(f"{shlex.join(cmd)} exited with {run.exit_code}:\n{run.stderr_tail}")
    _log(f"{name:12s} {level:6s} {run.n_pairs:3d} pairs  {run.wall_s:7.1f} s  peak {run.peak_rss_mb:6.0f} MB")
    return run


@contextmanager
def one_core(enabled: bool) -> Iterator[int | None]:
    """While active, pin this process, and so every batch, worker and profile process it starts, to one
    CPU (the last one it may use), and yield it (None when not ``enabled`` or where the OS has no
    affinity call); the previous affinity is restored afterwards. With one worker per batch each method
    then runs on one core — also KISS-Matcher, whose TBB threads would otherwise take a second core
    whenever the machine has one idle."""
    if not enabled or not hasattr(os, "sched_setaffinity"):
        yield None
        return
    before = os.sched_getaffinity(0)
    cpu = max(before)
    os.sched_setaffinity(0, {cpu})
    try:
        yield cpu
    finally:
        os.sched_setaffinity(0, before)


#: run.json's name for the order of :func:`batch_order` (older runs, without it, ran method by method)
BATCH_ORDER = "by level"


def batch_order(methods: Sequence[str], levels: Sequence[str]) -> list[tuple[str, str]]:
    """(method, level) in the order the batches run: level by level, every method on a level before
    the next level, the methods' order reversed on every second level.

    The machine's speed drifts (a shared host: the same code has run 1.5x slower an hour later), so
    methods run one after the other over the whole set would each meet a different machine. Level by
    level, the methods compared on a level run within minutes of each other, and the alternating order
    puts no method always first or always last."""
    return [(method, level) for i, level in enumerate(levels)
            for method in (methods if i % 2 == 0 else methods[::-1])]


def run_batches(settings: Settings, work: Path, data: Path) -> tuple[list[BatchRun], list[BatchRun]]:
    """Every method on every level (:func:`batch_order`), then the ablations; returns (runs, ablation runs)."""
    runs: list[BatchRun] = []
    configs = {method: work / "configs" / f"{method}.yaml" for method in settings.methods}
    for method, config in configs.items():
        write_method_config(config, method)
    for method, level in batch_order(settings.methods, settings.levels):
        runs.append(run_one_batch(method, level, configs[method], settings, work, data))
    ablations: list[BatchRun] = []
    for name, method, overrides, level in ABLATIONS if settings.mode == "full" else ():
        if method in settings.methods and level in settings.levels:
            config = work / "configs" / f"{name}.yaml"
            write_method_config(config, method, overrides)
            ablations.append(run_one_batch(name, level, config, settings, work, data))
    return runs, ablations


def baseline_rss(work: Path) -> dict[str, float]:
    """Peak RSS of processes that only import what a worker imports: the gctr engine's worker (no
    Open3D) and a comparison method's worker (with Open3D)."""
    imports = {
        "gctr": "import numpy, scipy.spatial, gctr_cli.io, gctr_cli.batch, gctr_cli.engine",
        "open3d": "import numpy, scipy.spatial, open3d, gctr_cli.io, gctr_cli.batch, gctr_cli.baselines",
    }
    return {k: float(measure([sys.executable, "-c", code], work / "results" / f".baseline_{k}.json")["peak_rss_mb"])
            for k, code in imports.items()}


#: the code that decides the numbers (accuracy and time); its fingerprint is taken before and after the runs
NUMERIC_CODE = ("gctr_cli/engine", "gctr_cli/baselines", "gctr_cli/config.py", "gctr_cli/methods.py",
                "gctr_cli/metrics.py")


def code_state() -> dict[str, str]:
    """Git commit, uncommitted files of gctr_cli/, and a fingerprint of :data:`NUMERIC_CODE`."""
    import hashlib

    digest = hashlib.sha256()
    for rel in NUMERIC_CODE:
        path = REPO_ROOT / rel
        for f in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            if f.is_file():
                digest.update(str(f.relative_to(REPO_ROOT)).encode() + b"\0" + f.read_bytes())
    state = {"fingerprint": digest.hexdigest()[:12], "head": "unknown", "dirty": ""}
    try:
        state["head"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True,
                                       text=True, check=True).stdout.strip()
        lines = subprocess.run(["git", "status", "--porcelain", "--", "gctr_cli"], cwd=REPO_ROOT,
                               capture_output=True, text=True, check=True).stdout.split("\n")
        state["dirty"] = ", ".join(ln[3:] for ln in lines if ln.strip())
    except (OSError, subprocess.CalledProcessError):
        pass
    return state


def describe_code(start: dict[str, str], end: dict[str, str]) -> str:
    def one(st: dict[str, str]) -> str:
        return f"commit {st['head']}" + (f" + uncommitted changes in gctr_cli/ ({st['dirty']})" if st["dirty"] else "")

    text = (f"{one(start)} at the start; fingerprint of the engine + baselines + config + metrics code "
            f"{start['fingerprint']}")
    if end["fingerprint"] != start["fingerprint"]:
        text += (f" — **changed during the run** (now {end['fingerprint']}, {one(end)}): later batches may have run "
                 "different code")
    else:
        text += " — unchanged during the run" + (f" (HEAD moved to {end['head']} meanwhile, other files)"
                                                 if end["head"] != start["head"] else "")
    return text


# ============================================================================================ rows
MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(4) for j in range(4))


def _matrix(t: dict[str, str] | None) -> np.ndarray | None:
    """The 4x4 of a ``transforms.csv`` row, None when its cells are empty (a failed pair)."""
    if not t:
        return None
    try:
        return np.array([float(t[c]) for c in MATRIX_COLUMNS]).reshape(4, 4)
    except (KeyError, TypeError, ValueError):
        return None


def _within(e: dict[str, str], thresholds: dict[str, float]) -> bool:
    return (float_or_nan(e.get("rot_err_deg")) < thresholds["rotation_deg"]
            and float_or_nan(e.get("trans_err_rel")) < thresholds["translation_rel"]
            and float_or_nan(e.get("scale_err")) < thresholds["scale"])


def load_rows(work: Path, data: Path, methods: tuple[str, ...], levels: tuple[str, ...],
              thresholds: dict[str, float] | None = None) -> list[dict[str, Any]]:
    """One row per (method, pair): the batch outputs joined with the manifest; a pair without a row
    in ``transforms.csv`` counts as failed."""
    rows: list[dict[str, Any]] = []
    for level in levels:
        manifest = read_manifest_rows(data / level / "pairs.csv")
        for method in methods:
            out = work / "results" / method / level
            tr = {r["pair_id"]: r for r in _read_csv(out / "transforms.csv")}
            er = {r["pair_id"]: r for r in _read_csv(out / "tm_errors.csv")}
            for m in manifest:
                pid = m["pair_id"]
                t, e = tr.get(pid), er.get(pid)
                row: dict[str, Any] = {
                    "method": method, "level": level, "pair_id": pid, "model": m.get("model", ""),
                    "scale_gt": float_or_nan(m.get("scale_gt")), "overlap_src": float_or_nan(m.get("overlap_src")),
                    "overlap_tgt": float_or_nan(m.get("overlap_tgt")),
                    "status": t["status"] if t else "missing", "message": t["message"] if t else "no row written",
                    "runtime_s": float_or_nan(t["runtime_s"]) if t else math.nan,
                    "fitness": float_or_nan(t["fitness"]) if t else math.nan,
                }
                ok_errors = e if t and t["status"] == "ok" and e else None  # the tm_errors row of an ok pair
                ok = ok_errors is not None
                for k in ("rot_err_deg", "trans_err", "trans_err_rel", "scale_err", "tm_err"):
                    row[k] = float_or_nan(ok_errors[k]) if ok_errors is not None else math.inf
                row["success"] = ok_errors is not None and ok_errors["success"] == "true"
                # issue 9: confidence column of transforms.csv (NaN when the batch has none or the method
                # returns NaN) and the would-be success of the returned matrix whatever the status (None when
                # the row has no usable matrix: failed rows of the batch runner have empty matrix cells)
                row["confidence"] = float_or_nan(t.get("confidence")) if t else math.nan
                mat = _matrix(t)
                row["matrix"] = mat
                if ok:
                    row["would_succeed"] = row["success"]
                elif mat is not None and usable_transform(mat) and e and thresholds:
                    row["would_succeed"] = _within(e, thresholds)
                else:
                    row["would_succeed"] = None
                rows.append(row)
    return rows


def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


# ============================================================================================ stats
def _median(xs: list[float]) -> float:
    xs = [x for x in xs if not math.isnan(x)]
    return float(np.median(xs)) if xs else math.nan


def _p90(xs: list[float]) -> float:
    xs = [x for x in xs if math.isfinite(x)]
    return float(np.percentile(xs, 90)) if xs else math.nan


def _ln(x: float) -> float:
    return math.log(x) if x > 0 and math.isfinite(x) else (math.inf if x == math.inf else math.nan)


def group_stats(rows: list[dict[str, Any]]) -> dict[str, Any]:
    n = len(rows)
    tm = [r["tm_err"] for r in rows]
    return {
        "pairs": n,
        "ok": sum(r["status"] == "ok" for r in rows),
        "success": sum(r["success"] for r in rows),
        "rate": sum(r["success"] for r in rows) / n if n else math.nan,
        "rot": _median([r["rot_err_deg"] for r in rows]),
        "trans_rel": _median([r["trans_err_rel"] for r in rows]),
        "scale": _median([r["scale_err"] for r in rows]),
        "tm": _median(tm),
        "ln_tm": _median([_ln(x) for x in tm]),
        "time_med": _median([r["runtime_s"] for r in rows]),
        "time_p90": _p90([r["runtime_s"] for r in rows]),
    }


def summarise(rows: list[dict[str, Any]], methods, levels) -> dict[tuple[str, str], dict[str, Any]]:
    """Stats per (method, level) and per (method, "all")."""
    out = {}
    for m in methods:
        for lv in (*levels, "all"):
            sel = [r for r in rows if r["method"] == m and (lv == "all" or r["level"] == lv)]
            if sel:
                out[(m, lv)] = group_stats(sel)
    return out


def median_ratio_spread(rows: list[dict[str, Any]], method: str, other: str, resamples: int = 5000,
                        seed: int = 0) -> dict[str, float]:
    """How firm "``method``'s median time per pair ≤ ``other``'s" is on this run's pairs.

    Over the pairs both methods ran: the ratio of the median times, its 95% bootstrap interval (pairs
    resampled with replacement, the same resample for both methods, seeded), the share of pairs on
    which ``method`` was faster, and the ratio of the mean times. A median that sits on a gap between
    a fast and a slow group of pairs swings widely when a few pairs change sides; the interval shows
    how widely.
    """
    a = {r["pair_id"]: r["runtime_s"] for r in rows if r["method"] == method and math.isfinite(r["runtime_s"])}
    b = {r["pair_id"]: r["runtime_s"] for r in rows if r["method"] == other and math.isfinite(r["runtime_s"])}
    ids = sorted(set(a) & set(b))
    if not ids:
        return {}
    ta, tb = np.array([a[i] for i in ids]), np.array([b[i] for i in ids])
    pick = np.random.default_rng(seed).integers(0, len(ids), size=(resamples, len(ids)))
    ratios = np.median(ta[pick], axis=1) / np.median(tb[pick], axis=1)
    low, high = np.percentile(ratios, [2.5, 97.5])
    return {"pairs": len(ids), "ratio": float(np.median(ta) / np.median(tb)), "low": float(low),
            "high": float(high), "faster_share": float(np.mean(ta < tb)), "mean_ratio": float(ta.mean() / tb.mean())}


def evaluate_goals(stats, methods, levels) -> list[dict[str, Any]]:
    """Issue 4, item 3. Each goal: text, measured, met (None when it cannot be evaluated)."""
    goals: list[dict[str, Any]] = []
    baselines = [m for m in methods if m != "gctr"]
    if "gctr" not in methods or not baselines:
        return goals
    for lv in levels:
        g = stats[("gctr", lv)]
        top = max(stats[(m, lv)]["success"] for m in baselines)
        best_m = ", ".join(m for m in baselines if stats[(m, lv)]["success"] == top)
        best = stats[(next(m for m in baselines if stats[(m, lv)]["success"] == top), lv)]
        strict = lv in CROSS_SOURCE_LEVELS
        met = g["success"] > best["success"] if strict else g["success"] >= best["success"]
        goals.append({
            "goal": f"`{lv}`: gctr success {'>' if strict else '≥'} every baseline's"
                    + (" (cross-source level: strictly)" if strict else ""),
            "measured": f"gctr {_rate(g['success'], g['pairs'])} vs best baseline ({best_m}) "
                        f"{_rate(best['success'], best['pairs'])}",
            "met": met,
        })
    globals_ = [m for m in GLOBAL_BASELINES if m in methods]
    if globals_:
        fastest = min(globals_, key=lambda m: stats[(m, "all")]["time_med"])
        g, f = stats[("gctr", "all")]["time_med"], stats[(fastest, "all")]["time_med"]
        goals.append({
            "goal": f"gctr median time per pair ≤ the fastest global baseline's ({' or '.join(globals_)}), all pairs",
            "measured": f"gctr {g:.2f} s vs {fastest} {f:.2f} s (ratio {g / f:.2f})",
            "met": g <= f,
            "fastest": fastest,
        })
    return goals


def _rate(n: int, total: int) -> str:
    return f"{n}/{total} ({100.0 * n / total:.0f}%)" if total else "0/0"


# ============================================================================================ profile
def stage_profile(data: Path, levels, methods, n_per_level: int) -> dict[str, dict[str, float]]:
    """Median seconds per stage (``RegistrationResult.timings``) of gctr and the global baselines, run
    in this process on the first ``n_per_level`` pairs of each level."""
    if n_per_level <= 0:
        return {}
    from gctr_cli.batch import derive_seed
    from gctr_cli.config import Config
    from gctr_cli.io import load_point_cloud
    from gctr_cli.methods import get_register_fn, method_config

    chosen = [m for m in ("gctr", *GLOBAL_BASELINES) if m in methods]
    timings: dict[str, list[dict[str, float]]] = {m: [] for m in chosen}
    totals: dict[str, list[float]] = {m: [] for m in chosen}
    for lv in levels:
        for row in read_manifest_rows(data / lv / "pairs.csv")[:n_per_level]:
            src = load_point_cloud(data / lv / row["source"])
            tgt = load_point_cloud(data / lv / row["target"])
            for m in chosen:
                cfg = Config(method=m)
                res = get_register_fn(m)(src, tgt, method_config(cfg), seed=derive_seed(cfg.seed, row["pair_id"]))
                timings[m].append(dict(res.timings))
                totals[m].append(res.runtime_s)
    out: dict[str, dict[str, float]] = {}
    for m in chosen:
        stages = sorted({k for t in timings[m] for k in t},
                        key=lambda k: -np.median([t.get(k, 0.0) for t in timings[m]]))
        out[m] = {k: float(np.median([t.get(k, 0.0) for t in timings[m]])) for k in stages}
        out[m]["(total)"] = float(np.median(totals[m]))
    return out


# ============================================================================================ plots
def plot_rotation_cdf(rows, methods, levels, path: Path, threshold_deg: float) -> None:
    """Per level: fraction of pairs whose rotation error is ≤ x, against x (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = min(len(levels), 2)
    nrows = math.ceil(len(levels) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6.0 * ncols, 4.2 * nrows), squeeze=False)
    xs = np.logspace(-2, math.log10(180.0), 300)
    for ax, lv in zip(axes.ravel(), levels):
        for m in methods:
            errs = np.array([r["rot_err_deg"] for r in rows if r["method"] == m and r["level"] == lv])
            if len(errs) == 0:
                continue
            frac = [(errs <= x).mean() for x in xs]
            ax.plot(xs, frac, label=m, lw=2.2 if m == "gctr" else 1.4)
        n = sum(1 for r in rows if r["method"] == methods[0] and r["level"] == lv)
        ax.axvline(threshold_deg, color="grey", ls="--", lw=0.8)
        ax.set_xscale("log")
        ax.set_ylim(0, 1.02)
        ax.set_xlim(xs[0], xs[-1])
        ax.set_title(f"{lv} ({n} pairs)")
        ax.set_xlabel("rotation error threshold (deg)")
        ax.set_ylabel("fraction of pairs with error ≤ threshold")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.ravel()[len(levels):]:
        ax.axis("off")
    axes.ravel()[0].legend(loc="upper left", fontsize=8)
    fig.suptitle(f"Cumulative success vs rotation error (dashed: success threshold {threshold_deg:g}°)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_times(rows, methods, path: Path) -> None:
    """Box plot of the time per pair of each method (all pairs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = [[r["runtime_s"] for r in rows if r["method"] == m and math.isfinite(r["runtime_s"])] for m in methods]
    fig, ax = plt.subplots(figsize=(1.4 * len(methods) + 2.5, 4.2))
    ax.boxplot([d if d else [math.nan] for d in data], whis=(10, 90), showfliers=True)
    ax.set_xticks(range(1, len(methods) + 1), methods)
    for i, d in enumerate(data, start=1):
        if d:
            ax.text(i + 0.27, float(np.median(d)), f"{np.median(d):.2f} s", va="center", ha="left", fontsize=8)
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter

    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
    ax.set_ylabel("time per pair (s, runtime_s column)")
    ax.set_title("Time per pair (box: quartiles, whiskers: p10–p90, line: median)")
    ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ============================================================================================ report
def _num(x: float, spec: str = ".3g") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if x == math.inf:
        return "∞"
    return format(x, spec)


def render_report(meta: dict[str, Any], rows, stats, goals, runs: list[BatchRun], profile, ablations=()) -> str:
    s = meta["settings"]
    methods, levels = tuple(s["methods"]), tuple(s["levels"])
    info = meta["machine"]
    succ = meta["success_thresholds"]
    L: list[str] = []
    L.append("# gctr vs. the comparison methods (issue 4)")
    L.append("")
    L.append(f"Command: `{meta['command']}`  ({s['mode']} run; generated {meta['date']}, "
             f"total wall time {meta['total_wall_s'] / 60:.1f} min)")
    L.append("")
    L.append(f"Machine: {info['cpu']}, {info['cores']} cores ({info['usable_cores']} usable), "
             f"{info['memory_gb']} GB RAM; Python {info['python']}, numpy {info['numpy']}, scipy {info['scipy']}, "
             f"Open3D {info['open3d']}; {info['platform']}.")
    L.append("")
    L.append(f"Code: {meta.get('code_state', 'unknown')}.")
    L.append("")
    loads = [x for x in meta["load_samples"] if math.isfinite(x)]
    if loads:
        mean_load, max_load = float(np.mean(loads)), float(np.max(loads))
        line = (f"Load average (1 min, sampled every 5 s during the runs): mean {mean_load:.2f}, max {max_load:.2f}, "
                f"for {s['workers']} worker(s) of this benchmark on {info['usable_cores']} cores.")
        if mean_load > s["workers"] + 0.5:
            line += (" **Other processes were competing for the cores: the wall-clock times per pair are inflated, "
                     "and not necessarily by the same factor for each method "
                     "(see the load before/after each batch in run.json); the CPU column is not inflated by the "
                     "load.**")
        L.append(line)
        L.append("")
    same_as_engine = (s["pairs_per_model"] == 10 and not s.get("models") and s.get("n_source") is None
                      and s["seed"] == 0)
    L.append(f"Pairs: `{meta['generate_command']}`"
             + (" — the pairs of `bench/ENGINE.md` (`make bench-engine`)." if same_as_engine else ".")
             + (" Quick run: the first pair per model and level, identical to the full run's." if s["mode"] == "quick"
                else ""))
    for lv in levels:
        L.append(f"- `{lv}`: {LEVEL_DESCRIPTIONS[lv]}")
    L.append("")
    L.append("Success (fixed before the runs; `success:` of the default config): "
             f"rotation < {succ['rotation_deg']:g}°, "
             f"translation < {succ['translation_rel']:g} × target bounding-box diagonal, "
             f"scale error < {succ['scale']:g}. "
             "Every method ran through `gctr batch` with the default config and `method:` set "
             f"(`-j {s['workers']}`); rows are the batch runner's `transforms.csv` / `tm_errors.csv`. "
             + ("The batches ran level by level: every method on a level before the next level, the methods' "
                "order reversed on every second level, so that the methods compared on a level met the same "
                "state of the machine (its speed drifts over an hour)."
                if meta.get("batch_order") == BATCH_ORDER else
                "The batches ran method by method (each method over every level, one method after the other)."))
    L.append("")

    L.extend(render_verdicts(rows, methods, levels, meta.get("min_confidence")))

    # goals
    L.append("## Goals of issue 4, item 3")
    L.append("")
    if goals:
        L.append("| goal | measured | met |")
        L.append("|---|---|---|")
        for g in goals:
            L.append(f"| {g['goal']} | {g['measured']} | {'yes' if g['met'] else '**no**'} |")
        L.append("")
        missed = [g for g in goals if not g["met"]]
        if missed:
            L.append(f"**{len(missed)} of {len(goals)} goals are not met.** What limits them: see "
                     "[Limits](#limits) below.")
        else:
            L.append("All goals are met on this run.")
        L.append("")
        L.append(f"Cross-source levels (strict goal): {', '.join(lv for lv in levels if lv in CROSS_SOURCE_LEVELS)} "
                 "— the levels with 1/4 density or less, partial overlap and an unknown scale (the synthetic ones "
                 "also with outliers). `easy` has to be matched, not beaten.")
        L.append("")

    # main table
    L.append("## Results per method and level")
    L.append("")
    L.append("Medians are over all pairs of the level; a pair without a transform counts as an infinite error (∞). "
             "Translation error = distance between where the estimate and the truth put the source centroid, "
             "relative to the target's bounding-box diagonal (the batch runner's definition). "
             "Time = `runtime_s` (the method's `register` call, files loading excluded). Peak memory = largest "
             "process of the batch (the worker), including its import baseline: "
             f"{meta['baseline_rss_mb']['gctr']:.0f} MB for gctr (numpy, scipy, gctr), "
             f"{meta['baseline_rss_mb']['open3d']:.0f} MB for the comparison methods (+ Open3D). CPU = CPU time of "
             "the whole batch / pairs (incl. worker start-up).")
    L.append("")
    L.append("| method | level | pairs | success | rot. err (°) | transl. err (rel) | scale err | TM | ln(TM) "
             "| time median (s) | time p90 (s) | CPU/pair (s) | peak mem (MB) |")
    L.append("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    run_by = {(r.method, r.level): r for r in runs}
    for lv in levels:
        for m in methods:
            st = stats.get((m, lv))
            if st is None:
                continue
            run = run_by.get((m, lv))
            cpu = run.cpu_s / run.n_pairs if run and run.n_pairs else math.nan
            peak = run.peak_rss_mb if run else math.nan
            name = f"**{m}**" if m == "gctr" else m
            L.append(f"| {name} | {lv} | {st['pairs']} | {_rate(st['success'], st['pairs'])} | {_num(st['rot'])} | "
                     f"{_num(st['trans_rel'])} | {_num(st['scale'])} | {_num(st['tm'])} | {_num(st['ln_tm'], '.2f')} | "
                     f"{_num(st['time_med'], '.2f')} | {_num(st['time_p90'], '.2f')} | {_num(cpu, '.2f')} | "
                     f"{_num(peak, '.0f')} |")
    L.append("")
    L.append("All levels together:")
    L.append("")
    L.append("| method | pairs | success | time median (s) | time p90 (s) | peak mem (MB) |")
    L.append("|---|---:|---:|---:|---:|---:|")
    for m in methods:
        st = stats[(m, "all")]
        peak = max((r.peak_rss_mb for r in runs if r.method == m), default=math.nan)
        L.append(f"| {m} | {st['pairs']} | {_rate(st['success'], st['pairs'])} | {_num(st['time_med'], '.2f')} | "
                 f"{_num(st['time_p90'], '.2f')} | {_num(peak, '.0f')} |")
    L.append("")

    L += single_core_section(stats, methods, meta)
    # paper quantities
    L.append("## The paper's quantities (beside its Table 1)")
    L.append("")
    L.append("Same columns as Table 1 of the GCTR paper: R = rotation error, T = translation error, S = scale "
             "error, log(TM) = natural log of the Frobenius norm of T_est − T_gt, time per pair. Here medians over "
             "the cross-source levels' pairs (" + ", ".join(lv for lv in levels if lv in CROSS_SOURCE_LEVELS)
             + "); R in degrees, T relative to the target's bounding-box diagonal (the paper's T is in the absolute "
             "units of its \"Angle\" pair and its R unit is not stated, so only the orders of magnitude and the "
             "ranking compare).")
    L.append("")
    L.append("| method | R (°) | T (rel) | S | log(TM) | time (s) | success |")
    L.append("|---|---:|---:|---:|---:|---:|---:|")
    for m in methods:
        sel = [r for r in rows if r["method"] == m and r["level"] in CROSS_SOURCE_LEVELS]
        if not sel:
            continue
        st = group_stats(sel)
        L.append(f"| {m} | {_num(st['rot'])} | {_num(st['trans_rel'])} | {_num(st['scale'])} | "
                 f"{_num(st['ln_tm'], '.2f')} | {_num(st['time_med'], '.2f')} | {_rate(st['success'], st['pairs'])} |")
    L.append("")
    L.append("The paper's Table 1 (one synthetic pair, \"Angle\"; i5 CPU, MATLAB/C):")
    L.append("")
    L.append("| method | R | T | S | log(TM) | time (s) |")
    L.append("|---|---:|---:|---:|---:|---:|")
    for row in PAPER_TABLE1:
        L.append("| " + " | ".join(row) + " |")
    L.append("")

    # plots
    L.append("## Plots")
    L.append("")
    L.append(f"![cumulative success vs rotation error]({CDF_PNG})")
    L.append("")
    L.append(f"`{CDF_PNG}`: per level, the fraction of pairs whose rotation error is at most x (failed pairs never "
             "count). A curve that reaches its plateau left of the dashed line is accurate; the plateau height "
             "is the rotation part of the success rate.")
    L.append("")
    L.append(f"![time per pair]({TIME_PNG})")
    L.append("")

    # profile
    if profile:
        L.append("## Where the time goes (stage profile)")
        L.append("")
        L.append(f"Median seconds per stage (`RegistrationResult.timings`), in-process, one thread, on the first "
                 f"{s['profile_pairs']} pair(s) of each level:")
        L.append("")
        for m, stages in profile.items():
            parts = ", ".join(f"{k} {v:.2f}" for k, v in stages.items() if k != "(total)")
            L.append(f"- **{m}** (total {stages.get('(total)', math.nan):.2f} s): {parts}")
        L.append("")

    # limits
    L.append("## Limits")
    L.append("")
    L.extend(limits_text(rows, stats, goals, methods, levels, profile, succ))
    L.append("")

    # unsuccessful gctr pairs
    bad = [r for r in rows if r["method"] == "gctr" and not r["success"]]
    if bad:
        L.append("## gctr's unsuccessful pairs")
        L.append("")
        L.append("| pair | overlap src / tgt | true scale | rot. err (°) | transl. err (rel) | scale err "
                 "| status / message |")
        L.append("|---|---:|---:|---:|---:|---:|---|")
        for r in bad:
            msg = r["status"] + (f": {r['message']}" if r["message"] else "")
            L.append(f"| {r['pair_id']} | {_num(r['overlap_src'], '.2f')} / {_num(r['overlap_tgt'], '.2f')} | "
                     f"{_num(r['scale_gt'])} | {_num(r['rot_err_deg'])} | {_num(r['trans_err_rel'])} | "
                     f"{_num(r['scale_err'])} | {msg[:120]} |")
        L.append("")

    # setup
    L.append("## How each method is set up")
    L.append("")
    for m in methods:
        L.append(f"- `{m}`: {METHOD_DESCRIPTIONS[m]}.")
    L.append("")
    L.append("All parameters are in the `baselines:` section of the config (`gctr config show`). The comparison "
             "methods follow the paper's protocol for its comparison methods: centroids aligned and the scale set by "
             "the ratio of bounding-box diagonals, which is biased (the axis-aligned box changes with the rotation, "
             "the crops and the outliers); ICP and CPD are local methods started from that normalisation only, so "
             "they fail whenever the unknown rotation is large — as they would for a user. The statistical outlier "
             "removal (Open3D's tutorial values: 20 neighbours, 2 σ) is the one step not named in the issue: "
             "without it the voxel downsampling turns uniform outliers into a large share of the voxels (a surface "
             "voxel merges many points, an outlier voxel one) and the FPFH methods break down, which would make "
             "them straw men." + (" Measured in this run (`outlier_removal: none`):" if ablations else ""))
    L.append("")
    for name, level, abl, base in ablations:
        with_ = _rate(base["success"], base["pairs"]) if base else "–"
        L.append(f"- `{name}` on `{level}`: success {_rate(abl['success'], abl['pairs'])} "
                 f"(with outlier removal: {with_}); median time {_num(abl['time_med'], '.2f')} s.")
    L.append("")
    L.append("Raw rows: `" + str(meta["work_rel"]) + "/results/<method>/<level>/` (transforms.csv, tm_errors.csv, "
             "config.yaml) and `" + str(meta["work_rel"]) + "/rows.csv`.")
    L.append("")
    return "\n".join(L)


PROCESS_REPORT = REPO_ROOT / "bench" / "PROCESS.md"


def process_times(path: Path) -> dict[str, float]:
    """Median whole-process wall times (s) from a ``bench/PROCESS.md`` table, keyed by method
    (``gctr`` for plain ``gctr register``, ``open3d_script`` for the Open3D script); {} if absent."""
    if not path.is_file():
        return {}
    out: dict[str, float] = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        m = re.match(r"\| `(gctr register(?:, method (\w+))?|Open3D script)` \| ([0-9.]+) \|", line)
        if m:
            key = m.group(2) or ("gctr" if m.group(1) == "gctr register" else "open3d_script")
            out[key] = float(m.group(3))
    return out


def single_core_section(stats, methods, meta: dict[str, Any]) -> list[str]:
    """Issue 10: per method, the registration time per pair of this run (one worker = one core) and
    the wall time of one whole ``gctr register`` process from ``bench/PROCESS.md``."""
    proc = process_times(PROCESS_REPORT)
    gctr_t = stats[("gctr", "all")]["time_med"] if ("gctr", "all") in stats else math.nan
    workers = int(meta.get("settings", {}).get("workers", 1))
    if workers != 1:  # (a quick run: -j 2) its times are not single-core figures; say so rather than claim them
        return ["## Time per pair (issue 10)", "",
                f"Not a single-core measurement: this run used `-j {workers}` (two workers share the machine's "
                "cores, and their times per pair differ from a one-worker run's). The single-core comparison of "
                "issue 10 comes from the full run (`make bench`, `-j 1`).", ""]
    L = ["## Single core: time per pair and whole process (issue 10)", "",
         f"Registration time per pair: median `runtime_s` over all pairs of this run, one worker per batch "
         f"(`{meta.get('command', 'python -m data_scripts.bench_compare')}`; "
         + (f"the whole run pinned to CPU {meta['pinned_cpu']} (`os.sched_setaffinity`), so every method, "
            "KISS-Matcher's TBB threads included, ran on one core; BLAS/OpenMP single-threaded). "
            if meta.get("pinned_cpu") is not None else
            "each batch process and its worker use one core, BLAS/OpenMP single-threaded; not pinned, so "
            "KISS-Matcher's TBB threads may have used a second core). ")
         + "Whole process: "
         "median wall time of `gctr register -c <method config> SOURCE TARGET -o MATRIX` on one 20k/20k-point "
         "pair pinned to one core, from `bench/PROCESS.md` (`make bench-process`, "
         "`python -m data_scripts.bench_process`; reading, imports and writing included)"
         + (f"; the 30-line Open3D script (`data_scripts/open3d_register.py`) takes {proc['open3d_script']:.2f} s."
            if "open3d_script" in proc else "; no bench/PROCESS.md yet."),
         "",
         "| method | registration time per pair (s) | × gctr | whole process, one pair (s) |",
         "|---|---:|---:|---:|"]
    for m in methods:
        st = stats.get((m, "all"))
        if st is None:
            continue
        whole = proc.get(m)
        L.append(f"| {m} | {_num(st['time_med'], '.2f')} | {_num(st['time_med'] / gctr_t, '.2f')} | "
                 f"{_num(whole, '.2f') if whole is not None else '–'} |")
    L.append("")
    return L


def render_verdicts(rows, methods, levels, configured: float | None) -> list[str]:
    """Issue 9: success / silent wrong / honest failures per method and level, the confidence threshold's
    trade-off per method (table + PNG) and gctr's failure diagnostics."""
    L = ["## Verdicts: success, silent wrong, honest failures (issue 9)", "",
         "*Silent wrong*: status `ok` but not a success — a wrong matrix reported as good, the number users care most "
         "about; *honest failure*: status `failed` (a refused pair, or one that could not run). Time: `runtime_s`.", ""]
    groups = [(m, lv, [r for r in rows if r["method"] == m and r["level"] == lv]) for m in methods for lv in levels]
    groups += [(m, "**all**", [r for r in rows if r["method"] == m]) for m in methods]
    L += outcome_table(groups, "runtime_s")
    L.append("")
    silent = {m: sum(outcome(r) == "silent_wrong" for r in rows if r["method"] == m) for m in methods}
    total = {m: sum(r["method"] == m for r in rows) for m in methods}
    L.append("Silent wrong over all levels: " + "; ".join(
        f"{m} {silent[m]} of {total[m]} pairs ({100.0 * silent[m] / max(1, total[m]):.1f}%)"
        for m in methods) + ".")
    L.append("")
    thresholds = sweep_thresholds(configured)
    sweeps = {m: confidence_sweep([r for r in rows if r["method"] == m], thresholds) for m in methods}
    no_conf = [m for m in methods if all(math.isnan(r.get("confidence", math.nan)) for r in rows if r["method"] == m)]
    unknown = sum(1 for r in rows if r["status"] != "ok" and r.get("would_succeed") is None)
    L += ["## Confidence threshold trade-off", "",
          f"`engine.min_confidence` = {configured if configured is not None else '?'} (gctr's configured threshold; "
          "the comparison methods have none). Offline sweep: at threshold t a pair is accepted when it has a usable "
          "matrix and its confidence ≥ t. *Silent wrong*: accepted and wrong; *correct refused*: confidence < t "
          "although the matrix was a success; % of the method's pairs. "
          + (f"Methods without a confidence (NaN), reported as never refusing: {', '.join(no_conf)}. "
             if no_conf else "")
          + (f"{unknown} failed rows have no matrix in `transforms.csv` (the batch runner leaves it empty), so their "
             "would-be success is unknown and they count as refused at every threshold; `bench/ENGINE.md` has the "
             "sweep with every failed pair's transform." if unknown else ""), ""]
    L += sweep_table(sweeps, configured)
    L += ["", f"![confidence trade-off]({TRADEOFF_PNG})", ""]
    if any("diagnosis" in r for r in rows if r["method"] == "gctr"):
        L += ["## gctr failure diagnostics", "",
              "For each gctr pair that is not a success and has a matrix: the engine's own score "
              "(`gctr_cli.engine.score_transform`) of the ground truth vs of the answer — truth higher by more than "
              f"{DIAGNOSIS_MARGIN:g}: *search missed*; answer higher by more than {DIAGNOSIS_MARGIN:g}: *objective "
              "can't tell*; else *precision*. *Not scored*: no matrix (failed rows).", ""]
        L += diagnosis_table([r for r in rows if r["method"] == "gctr"], list(levels))
        L.append("")
    return L


def diagnose_gctr(rows: list[dict[str, Any]], data: Path) -> None:
    """Add ``score_truth``, ``score_answer``, ``diagnosis`` to gctr's unsuccessful rows that have a matrix
    (in place; seeds as the batch runner derives them)."""
    bad = [r for r in rows if r["method"] == "gctr" and outcome(r) != "success" and r.get("matrix") is not None
           and usable_transform(r["matrix"])]
    if not bad:
        return
    try:
        from gctr_cli.engine import score_transform
    except ImportError:
        return
    from gctr_cli.batch import derive_seed
    from gctr_cli.config import Config
    from gctr_cli.io import load_point_cloud, read_matrix

    cfg = Config()
    manifests = {lv: {m["pair_id"]: m for m in read_manifest_rows(data / lv / "pairs.csv")}
                 for lv in {r["level"] for r in bad}}
    for r in bad:
        m = manifests[r["level"]][r["pair_id"]]
        folder = data / r["level"]
        src, tgt = load_point_cloud(folder / m["source"]), load_point_cloud(folder / m["target"])
        seed = derive_seed(cfg.seed, r["pair_id"])
        r["score_truth"] = float(score_transform(src, tgt, read_matrix(folder / m["gt"]), cfg.engine, seed))
        r["score_answer"] = float(score_transform(src, tgt, r["matrix"], cfg.engine, seed))
        r["diagnosis"] = diagnose(r["score_truth"], r["score_answer"])


def miss_breakdown(bad: list[dict[str, Any]], succ_th: dict[str, float]) -> str:
    """Unsuccessful pairs in words: how many were refused (status not ``ok``: no matrix to measure), and of
    the answered ones (silent wrong) how many are over each success threshold and how many are a wrong coarse
    match (rotation error ≥ 10°) rather than a near miss."""
    refused = sum(r["status"] != "ok" for r in bad)
    answered = [r for r in bad if r["status"] == "ok"]
    parts = [f"{refused} refused"]
    if answered:
        over = {k: sum(r[c] >= succ_th[t] for r in answered) for k, c, t in (
            ("rotation", "rot_err_deg", "rotation_deg"), ("translation", "trans_err_rel", "translation_rel"),
            ("scale", "scale_err", "scale"))}
        coarse = sum(r["rot_err_deg"] >= 10 for r in answered)
        parts.append(f"{len(answered)} answered wrongly: over the threshold in rotation {over['rotation']}, "
                     f"translation {over['translation']}, scale {over['scale']}; {coarse} with a rotation error "
                     f"≥ 10°, i.e. a wrong coarse match, the others near misses")
    else:
        parts.append("none answered wrongly")
    return ", ".join(parts)


def _spread_lines(rows: list[dict[str, Any]], fastest: str) -> list[str]:
    """The time goal's firmness (:func:`median_ratio_spread`) as a line of the limits section."""
    sp = median_ratio_spread(rows, "gctr", fastest)
    if not sp:
        return []
    return [f"  How firm the median comparison is: ratio {sp['ratio']:.2f}, 95% bootstrap interval over the "
            f"{sp['pairs']} pairs {sp['low']:.2f}–{sp['high']:.2f}; gctr was faster on "
            f"{100 * sp['faster_share']:.0f}% of the pairs; ratio of the mean times {sp['mean_ratio']:.2f}."]


def limits_text(rows, stats, goals, methods, levels, profile, succ_th) -> list[str]:
    """Plain statements on each goal that is not met (what the numbers say limits it), and on the time
    goal when met (how firm it is)."""
    out: list[str] = []
    if not goals:
        return ["(no goals evaluated: gctr or the baselines were not run)"]
    for g in goals:
        if g["met"]:
            continue
        out.append(f"- **Not met — {g['goal']}**: {g['measured']}.")
        if "median time" in g["goal"] and profile.get("gctr"):
            for m in ("gctr", g.get("fastest")):
                stages = [(k, v) for k, v in profile.get(m, {}).items() if k != "(total)"]
                if stages:
                    top = ", ".join(f"{k} {v:.2f} s" for k, v in stages[:4])
                    total = sum(v for _, v in stages)
                    out.append(f"  {m}'s largest stages (median per pair, stage profile above): {top}; the largest "
                               f"is {100 * stages[0][1] / total:.0f}% of the sum of the stage medians.")
            per_level = ", ".join(
                f"{lv} {stats[('gctr', lv)]['time_med']:.2f} vs {stats[(g['fastest'], lv)]['time_med']:.2f} s"
                for lv in levels if ("gctr", lv) in stats and (g.get("fastest"), lv) in stats)
            out.append(f"  Median time per level, gctr vs {g.get('fastest')}: {per_level}.")
            if profile.get(g.get("fastest")):
                out.append(f"  The stage profile runs the methods interleaved pair by pair (same load for both): "
                           f"median total gctr {profile['gctr'].get('(total)', math.nan):.2f} s vs {g['fastest']} "
                           f"{profile[g['fastest']].get('(total)', math.nan):.2f} s.")
            out.extend(_spread_lines(rows, g["fastest"]))
        elif "success" in g["goal"]:
            lv = g["goal"].split("`")[1]
            bad = [r for r in rows if r["method"] == "gctr" and r["level"] == lv and not r["success"]]
            good = [r for r in rows if r["method"] == "gctr" and r["level"] == lv and r["success"]]
            if bad:
                def overlap(rs):
                    return float(np.median([min(r["overlap_src"], r["overlap_tgt"]) for r in rs])) if rs else math.nan
                out.append(f"  gctr misses {len(bad)} `{lv}` pair(s) ({miss_breakdown(bad, succ_th)}); "
                           f"median overlap (smaller of source / target) of the missed pairs {overlap(bad):.2f}, of "
                           f"the successful ones {_num(overlap(good), '.2f')} (table of unsuccessful pairs below).")
            tied = [m for m in methods if m != "gctr" and stats[(m, lv)]["success"] >= stats[("gctr", lv)]["success"]]
            both = [r["pair_id"] for r in rows if r["method"] == "gctr" and r["level"] == lv and r["success"]
                    and any(q["success"] for q in rows if q["pair_id"] == r["pair_id"] and q["method"] in tied)]
            if tied:
                out.append(f"  Baselines with as many successes: {', '.join(tied)}; pairs solved by gctr and by one "
                           f"of them: {len(both)}.")
    if not out:
        out.append("- Goals: none missed on this run.")
    for g in goals:
        if "fastest" in g and g["met"]:
            gm = stats[("gctr", "all")]["time_med"]
            fm = stats[(g["fastest"], "all")]["time_med"]
            if gm > 0.9 * fm:
                out.append(f"- The time goal holds by a thin margin (gctr {gm:.2f} s vs {g['fastest']} {fm:.2f} s): "
                           "within run-to-run noise of the machine, so another run may tip it either way.")
            else:
                out.append(f"- The time goal holds (gctr {gm:.2f} s vs {g['fastest']} {fm:.2f} s).")
            out.extend(_spread_lines(rows, g["fastest"]))
    for lv in levels:
        bad = [r for r in rows if r["method"] == "gctr" and r["level"] == lv and not r["success"]]
        if not bad or any(f"`{lv}`" in g["goal"] and not g["met"] for g in goals):
            continue
        out.append(f"- gctr itself misses {len(bad)} of {stats[('gctr', lv)]['pairs']} `{lv}` pairs "
                   f"({miss_breakdown(bad, succ_th)}). See the table below.")
    return out


def write_rows_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    cols = ["method", "level", "pair_id", "model", "status", "success", "outcome", "confidence", "would_succeed",
            "rot_err_deg", "trans_err", "trans_err_rel", "scale_err", "tm_err", "runtime_s", "fitness", "scale_gt",
            "overlap_src", "overlap_tgt", "score_truth", "score_answer", "diagnosis", "message"]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({**{k: (repr(v) if isinstance(v, float) else v) for k, v in r.items() if k != "matrix"},
                        "outcome": outcome(r)})


def write_report(meta: dict[str, Any], runs: list[BatchRun], work: Path, data: Path, out: Path,
                 profile: dict[str, dict[str, float]], ablation_runs: Sequence[BatchRun] = ()) -> dict[str, Any]:
    """Rows -> stats -> goals -> ``out`` (markdown) + the two PNGs next to it. Returns the stats and goals."""
    s = meta["settings"]
    methods, levels = tuple(s["methods"]), tuple(s["levels"])
    rows = load_rows(work, data, methods, levels, meta.get("success_thresholds"))
    if meta.get("diagnose", True):
        diagnose_gctr(rows, data)
    stats = summarise(rows, methods, levels)
    goals = evaluate_goals(stats, methods, levels)
    out.parent.mkdir(parents=True, exist_ok=True)
    plot_rotation_cdf(rows, methods, levels, out.parent / CDF_PNG, meta["success_thresholds"]["rotation_deg"])
    plot_times(rows, methods, out.parent / TIME_PNG)
    plot_confidence_tradeoff({m: confidence_sweep([r for r in rows if r["method"] == m]) for m in methods},
                             out.parent / TRADEOFF_PNG, meta.get("min_confidence"),
                             "Confidence threshold trade-off (NaN confidence: never refuses)")
    write_rows_csv(work / "rows.csv", rows)
    ablations = []
    for run in ablation_runs:
        abl = group_stats(load_rows(work, data, (run.method,), (run.level,)))
        base_method = next(m for name, m, _, _ in ABLATIONS if name == run.method)
        ablations.append((run.method, run.level, abl, stats.get((base_method, run.level))))
    out.write_text(render_report(meta, rows, stats, goals, runs, profile, ablations))
    return {"stats": stats, "goals": goals, "rows": rows}


# ============================================================================================ main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m data_scripts.bench_compare",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="1 pair per model/scene and level, 1 real pair per group, -j 2")
    p.add_argument("--out", type=Path, default=None,
                   help="report, PNGs next to it (default bench/RESULTS.md; --quick: <work>/RESULTS.md)")
    p.add_argument("--work", type=Path, default=None,
                   help="pairs, configs and batch outputs (default bench/work/compare-<full|quick>)")
    p.add_argument("--methods", help=f"comma-separated subset of {','.join(METHODS)} (default: all whose optional "
                                     "package is installed)")
    p.add_argument("--levels", help=f"comma-separated subset of {','.join(ALL_LEVELS)}")
    p.add_argument("--pairs-per-model", type=int, default=None, help="default 10 (full) / 1 (quick)")
    p.add_argument("--seed", type=int, default=0,
                   help="generator seed: 0 = the report set (default), 1 = the tuning set (work folder gets -seed1)")
    p.add_argument("--models", help="comma-separated model files for the generator (default: the 3 shipped models)")
    p.add_argument("--n-source", type=int, default=None, help="source points per pair (generator default 20000)")
    p.add_argument("-j", "--workers", type=int, default=None, help="workers per batch: default 1 (full) / 2 (quick)")
    p.add_argument("--profile-pairs", type=int, default=None, help="pairs per level for the stage profile")
    p.add_argument("--report-only", action="store_true", help="re-render the report from the runs in --work")
    p.add_argument("--no-diagnose", action="store_true",
                   help="skip gctr's failure diagnostics (engine score of the truth vs the answer)")
    return p


def _log(msg: str) -> None:
    print(f"[bench_compare] {msg}", file=sys.stderr, flush=True)


def _rel(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    try:
        settings = settings_from_args(args)
    except BenchError as err:
        print(f"bench_compare: error: {err}", file=sys.stderr)
        return 2
    suffix = f"-seed{settings.seed}" if settings.seed != 0 else ""
    work = args.work if args.work is not None else REPO_ROOT / "bench" / "work" / f"compare-{settings.mode}{suffix}"
    data = work / "data"
    meta_path = work / "run.json"
    if args.out is None:
        args.out = work / "RESULTS.md" if settings.mode == "quick" else REPO_ROOT / "bench" / "RESULTS.md"

    if args.report_only:
        if not meta_path.is_file():
            print(f"bench_compare: error: {meta_path} not found (run the benchmark first)", file=sys.stderr)
            return 2
        saved = json.loads(meta_path.read_text())
        meta, runs = saved["meta"], [BatchRun(**r) for r in saved["runs"]]
        ablation_runs = [BatchRun(**r) for r in saved.get("ablations", [])]
        result = write_report(meta, runs, work, data, args.out, saved.get("profile", {}), ablation_runs)
        _print_summary(result, args.out)
        return 0

    from gctr_cli.config import Config

    t0 = time.monotonic()
    code_at_start = code_state()
    work.mkdir(parents=True, exist_ok=True)
    (work / "results").mkdir(exist_ok=True)
    command = "python -m data_scripts.bench_compare" + (" " + shlex.join(argv) if argv else "")
    with one_core(settings.workers == 1) as pinned_cpu, LoadSampler() as sampler:
        try:
            generate_command = ensure_data(settings, data)
        except BenchError as err:
            print(f"bench_compare: error: {err}", file=sys.stderr)
            return 1
        base_rss = baseline_rss(work)
        try:
            runs, ablation_runs = run_batches(settings, work, data)
        except BenchError as err:
            print(f"bench_compare: error: {err}", file=sys.stderr)
            return 1
        _log("stage profile")
        profile = stage_profile(data, settings.levels, settings.methods, settings.profile_pairs)
    meta = {
        "command": command,
        "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "settings": {**asdict(settings), "methods": list(settings.methods), "levels": list(settings.levels)},
        "machine": machine_info(),
        "load_samples": sampler.samples,
        "generate_command": shlex.join([Path(generate_command[0]).name, *generate_command[1:]]).replace(
            str(data), _rel(data)),
        "success_thresholds": Config().success.model_dump(),
        "min_confidence": Config().engine.min_confidence,
        "diagnose": not args.no_diagnose,
        "baseline_rss_mb": base_rss,
        "code_state": describe_code(code_at_start, code_state()),
        "total_wall_s": time.monotonic() - t0,
        "work_rel": _rel(work),
        "pinned_cpu": pinned_cpu,
        "batch_order": BATCH_ORDER,
    }
    meta_path.write_text(json.dumps({"meta": meta, "runs": [asdict(r) for r in runs],
                                     "ablations": [asdict(r) for r in ablation_runs], "profile": profile}, indent=1))
    result = write_report(meta, runs, work, data, args.out, profile, ablation_runs)
    _print_summary(result, args.out)
    return 0


def _print_summary(result: dict[str, Any], out: Path) -> None:
    for g in result["goals"]:
        print(f"{'MET    ' if g['met'] else 'NOT MET'}  {g['goal']}: {g['measured']}")
    print(f"report: {out}")


if __name__ == "__main__":
    sys.exit(main())
