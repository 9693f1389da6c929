"""Whole-process time of ``gctr register`` against the equivalent Open3D script, and of every comparison
method run through ``gctr register -c CONFIG`` (issue 10, item 3 and engine speed reporting).

    python -m data_scripts.bench_process                      # make bench-process -> bench/PROCESS.md
    python -m data_scripts.bench_process --reps 1 --out /tmp/p.md           # smoke run
    python -m data_scripts.bench_process --methods icp,cpd --reps 3 --source a.ply --target b.ply

What runs, each as a fresh process pinned to one core (``taskset -c CPU``) with one BLAS/OpenMP thread,
``--reps`` times, every timed run right after an untimed run of the same command (``--no-warm``: only one
warm-up run of each at the start). Some machines page out file pages that have not been read for a while
(Linux DAMON reclaim: on the machine of the committed report, pages idle for about 60 s); interleaved with
the other commands, a command then re-reads part of its libraries from disk on some repetitions and not on
others (the same ``gctr register`` took 0.46-0.88 s). The warm-up right before each timed run gives every
command the same, hot page cache; the report says whether DAMON reclaim was on:

* ``gctr register SOURCE TARGET -o MATRIX`` (the console script of this checkout, method ``gctr``, built-in
  defaults);
* for every comparison method of ``--methods`` (default: all of ``gctr_cli.methods.BASELINES``, i.e. icp,
  fpfh_ransac, fgr, cpd, kiss_matcher): ``gctr register -c WORK/method-NAME.yaml SOURCE TARGET -o MATRIX``
  where the config holds only ``method: NAME`` (the other keys take their defaults). A method whose
  optional package is not importable (kiss_matcher without ``pip install kiss-matcher``,
  ``make bench-deps``) is skipped with a note in the report. Its warm-up run is the ``python -X importtime
  -m gctr_cli register …`` variant, which also tells which packages it loads (Open3D is imported lazily);
* ``python data_scripts/open3d_register.py SOURCE TARGET MATRIX`` — Open3D's tutorial recipe with scale
  (read, FPFH + RANSAC, scaled ICP, write the matrix);
* ``gctr --help`` and ``python -c pass`` (interpreter start-up), for reference.

The report prints every command line exactly as run. Columns: median and minimum wall time; ``×
Open3D script`` = median wall / the Open3D script's median wall; **imports** = a fresh interpreter on the
same core timing the imports the command makes (its gctr_cli modules and the other top-level packages it
loads); **imports, -X importtime** = the sum of the top-level cumulative times of ``python -X importtime``
for the same command, minus the modules ``python -c pass`` imports too (median of the repetitions;
``-X importtime`` itself adds a little; not measured per repetition for the comparison methods, which
would run each of them twice more); for every ``gctr register`` row, **runtime_s** = the time the
command prints (the method's own registration call, files already loaded) and **overhead** = wall −
runtime_s (start-up, imports, reading, validation, printing, writing). The goal of the issue: gctr's
median wall time ≤ 0.5 × the Open3D script's.

Without ``--source/--target`` the pair is generated (seeded): 20 000 points of the shipped bunny as the
source and 20 000 other points moved by a similarity (scale 1.5) with 0.3 % noise as the target, binary
PLY, with the ground truth, so that every matrix is also checked (rotation, translation / target diagonal,
scale error; a method whose status is not ``ok`` is listed as failed). A comparison method that fails on
the pair (exit code 1) is still timed.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")
#: modules the register path must not load (tests/test_cli_imports.py checks the same list)
HEAVY_MODULES = ("open3d", "dask", "distributed", "matplotlib", "tqdm", "pandas", "gctr_cli.batch",
                 "gctr_cli.report", "gctr_cli.snapshots", "gctr_cli.baselines")


def make_pair(folder: Path, n: int = 20000, seed: int = 0) -> tuple[Path, Path, Path]:
    from scipy.spatial.transform import Rotation

    from gctr_cli.io import load_point_cloud, write_matrix, write_point_cloud

    bunny = load_point_cloud(REPO_ROOT / "data" / "models" / "bunny.ply")
    rng = np.random.default_rng(seed)
    idx = rng.permutation(len(bunny))
    T = np.eye(4)
    T[:3, :3] = 1.5 * Rotation.from_rotvec([0.3, 1.2, -0.4]).as_matrix()
    T[:3, 3] = [0.3, -0.2, 0.5]
    diag = float(np.linalg.norm(bunny.max(0) - bunny.min(0)))
    target = bunny[idx[-n:]] @ T[:3, :3].T + T[:3, 3] + rng.normal(scale=0.003 * diag * 1.5, size=(n, 3))
    folder.mkdir(parents=True, exist_ok=True)
    paths = folder / "source.ply", folder / "target.ply", folder / "gt.txt"
    write_point_cloud(paths[0], bunny[idx[:n]])
    write_point_cloud(paths[1], target)
    write_matrix(paths[2], T)
    return paths


def environment() -> dict[str, str]:
    env = dict(os.environ)
    for var in THREAD_VARS:
        env[var] = "1"
    return env


def pinned(cmd: list[str], cpu: int) -> list[str]:
    return ["taskset", "-c", str(cpu), *cmd] if shutil.which("taskset") else cmd


def run(cmd: list[str], cpu: int, ok_codes: tuple[int, ...] = (0,)) -> tuple[float, str, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(pinned(cmd, cpu), capture_output=True, text=True, env=environment(), cwd=REPO_ROOT)
    wall = time.perf_counter() - t0
    if proc.returncode not in ok_codes:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stderr[-2000:]}")
    return wall, proc.stdout, proc.stderr


def damon_state(admin: Path = Path("/sys/kernel/mm/damon/admin/kdamonds")) -> str:
    """Whether a DAMON reclaim daemon is running (it pages out file pages idle for a while, so a command
    interleaved with others may find its libraries partly evicted), with its minimum idle age."""
    running = []
    for kd in sorted(admin.glob("[0-9]*")) if admin.is_dir() else []:
        try:
            if (kd / "state").read_text().strip() != "on":
                continue
            ctx = kd / "contexts" / "0"
            aggr_us = int((ctx / "monitoring_attrs" / "intervals" / "aggr_us").read_text())
            min_age = int((ctx / "schemes" / "0" / "access_pattern" / "age" / "min").read_text())
            action = (ctx / "schemes" / "0" / "action").read_text().strip()
            running.append(f"{action} after {min_age * aggr_us / 1e6:.0f} s idle")
        except (OSError, ValueError):
            running.append("on")
    return "on (" + "; ".join(running) + ")" if running else "off or not available"


def importtime(stderr: str) -> dict[str, float]:
    """Top-level module -> cumulative import seconds, from ``-X importtime`` output."""
    out: dict[str, float] = {}
    for line in stderr.splitlines():
        m = re.match(r"import time:\s+(\d+) \|\s+(\d+) \|( *)(\S+)", line)
        if m and len(m.group(3)) == 1:  # one space: imported by the script itself, not by another module
            out[m.group(4)] = out.get(m.group(4), 0.0) + int(m.group(2)) / 1e6
    return out


def self_time_by_package(stderr: str) -> dict[str, float]:
    """Top-level package -> summed self import seconds (where the import time goes)."""
    out: dict[str, float] = {}
    for m in re.finditer(r"^import time:\s+(\d+) \|\s+\d+ \| *(\S+)", stderr, re.M):
        package = m.group(2).split(".")[0]
        out[package] = out.get(package, 0.0) + int(m.group(1)) / 1e6
    return out


def field(pattern: str, text: str, what: str) -> str:
    """Group 1 of the first (multi-line mode) match of ``pattern`` in a command's output; exits when absent."""
    m = re.search(pattern, text, re.M)
    if m is None:
        raise SystemExit(f"bench_process: no {what} in the output:\n{text[-2000:]}")
    return m.group(1)


def imported(stderr: str) -> set[str]:
    return {m.group(1) for m in re.finditer(r"^import time:\s+\d+ \|\s+\d+ \| *(\S+)", stderr, re.M)}


GCTR = "gctr register"
OPEN3D = "Open3D script"
NOT_MEASURED = "–"


def method_label(method: str) -> str:
    """Row name of a comparison method run through ``gctr register -c``."""
    return f"gctr register, method {method}"


def parse_methods(text: str) -> list[str]:
    """``--methods``: comma-separated comparison methods of the registry (empty = none), in the given order."""
    from gctr_cli.methods import BASELINES

    names = list(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    unknown = [m for m in names if m not in BASELINES]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown comparison method(s) {', '.join(unknown)}; "
                                         f"choose from {', '.join(BASELINES)}")
    return names


def build_parser() -> argparse.ArgumentParser:
    from gctr_cli.methods import BASELINES

    p = argparse.ArgumentParser(prog="python -m data_scripts.bench_process", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", type=Path)
    p.add_argument("--target", type=Path)
    p.add_argument("--gt", type=Path, help="ground-truth matrix of --source/--target (checks every answer)")
    p.add_argument("--methods", type=parse_methods, default=list(BASELINES), metavar="M1,M2",
                   help="comparison methods timed through `gctr register -c` (default: all, "
                        f"{','.join(BASELINES)}; '' = none)")
    p.add_argument("--reps", type=int, default=7, help="timed runs of each command (default 7)")
    p.add_argument("--no-warm", dest="warm", action="store_false",
                   help="no untimed run of a command right before each of its timed runs (only one warm-up "
                        "run of each at the start)")
    p.add_argument("--cpu", type=int, default=0, help="core the processes are pinned to (default 0)")
    p.add_argument("--work", type=Path, default=REPO_ROOT / "bench" / "work" / "process")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "PROCESS.md")
    return p


def _cell(x: float | None) -> str:
    return NOT_MEASURED if x is None else f"{x:.3f}"


def table_row(name: str, walls: list[float], reference_s: float, imports_s: float | None,
              importtime_s: float | None, runtimes: list[float] | None) -> str:
    """One row of the timing table: median / min wall, × the reference (the Open3D script's median wall),
    imports, imports by -X importtime, and for gctr register rows runtime_s and overhead = wall − runtime_s."""
    med = statistics.median(walls)
    runtime = statistics.median(runtimes) if runtimes else None
    return (f"| `{name}` | {med:.3f} | {min(walls):.3f} | {med / reference_s:.2f} | {_cell(imports_s)} | "
            f"{_cell(importtime_s)} | {_cell(runtime)} | {_cell(None if runtime is None else med - runtime)} |")


TABLE_HEADER = ["| command | wall median (s) | wall min (s) | × Open3D script | imports (s) | "
                "imports, -X importtime (s) | runtime_s (s) | overhead (s) |",
                "|---|---:|---:|---:|---:|---:|---:|---:|"]
ACCURACY_HEADER = ["| command | status | rotation (deg) | translation / diagonal | scale error | within the "
                   "success thresholds |",
                   "|---|---|---:|---:|---:|---|"]


def accuracy_line(name: str, status: str, errors: Any = None, message: str = "", success: Any = None) -> str:
    """One row of the ground-truth table; ``errors`` is a ``TransformErrors`` (None: no matrix to check),
    ``success`` the config's ``SuccessConfig`` (rotation_deg, translation_rel, scale; None: not judged)."""
    if errors is None:
        why = f" ({message.replace('|', '/')})" if message else ""
        return f"| {name} | {status}{why} | {NOT_MEASURED} | {NOT_MEASURED} | {NOT_MEASURED} | no |"
    within = NOT_MEASURED if success is None else "yes" if (
        errors.rot_err_deg < success.rotation_deg and errors.trans_err_rel < success.translation_rel
        and errors.scale_err < success.scale) else "**no**"
    return (f"| {name} | {status} | {errors.rot_err_deg:.3g} | {errors.trans_err_rel:.3g} | "
            f"{errors.scale_err:.3g} | {within} |")


def command_lines(commands: dict[str, list[str]], cpu: int, configs: dict[str, Path]) -> list[str]:
    """The exact command lines of the report (as run: pinned, one thread) and the method configs' contents."""
    env = " ".join(f"{v}=1" for v in THREAD_VARS)
    out = [f"Every command ran from `{REPO_ROOT}` with `{env}` in its environment:", ""]
    out += [f"- `{name}`: `{shlex.join(pinned(cmd, cpu))}`" for name, cmd in commands.items()]
    if configs:
        out += ["", "Config of each comparison method (all other keys take their defaults): "
                + "; ".join(f"`{_rel(path)}` = `{path.read_text().strip()}`" for path in configs.values()) + "."]
    return out + [""]


def main(argv: list[str] | None = None) -> int:
    from gctr_cli.methods import is_available

    p = build_parser()
    args = p.parse_args(argv)
    argv_used = sys.argv[1:] if argv is None else list(argv)
    if (args.source is None) != (args.target is None):
        p.error("give both --source and --target, or neither")
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    if args.source is None:
        args.source, args.target, args.gt = make_pair(work / "pair")
    src, tgt = str(args.source.resolve()), str(args.target.resolve())
    py = sys.executable
    gctr = str(Path(py).with_name("gctr"))
    methods = [m for m in args.methods if is_available(m)]
    skipped = [m for m in args.methods if m not in methods]
    configs: dict[str, Path] = {}
    for m in methods:
        configs[method_label(m)] = work / f"method-{m}.yaml"
        configs[method_label(m)].write_text(f"method: {m}\n")
    matrices = {GCTR: work / "gctr.txt", **{method_label(m): work / f"method-{m}.txt" for m in methods},
                OPEN3D: work / "open3d.txt"}
    for f in matrices.values():
        f.unlink(missing_ok=True)  # a failed method writes none: never check a stale one
    commands = {
        GCTR: [gctr, "register", src, tgt, "-o", str(matrices[GCTR])],
        **{name: [gctr, "register", "-c", str(cfg), src, tgt, "-o", str(matrices[name])]
           for name, cfg in configs.items()},
        OPEN3D: [py, str(REPO_ROOT / "data_scripts" / "open3d_register.py"), src, tgt, str(matrices[OPEN3D])],
        "gctr --help": [gctr, "--help"],
        "python -c pass": [py, "-c", "pass"],
    }
    registering = [GCTR, *configs]  # rows that print runtime_s
    ok_codes = {name: (0, 1) for name in configs}  # a comparison method may fail on the pair: still timed
    as_module = {  # the same commands with -X importtime (the console script is `python -m gctr_cli`)
        GCTR: [py, "-X", "importtime", "-m", "gctr_cli", *commands[GCTR][1:]],
        **{name: [py, "-X", "importtime", "-m", "gctr_cli", *commands[name][1:]] for name in configs},
        OPEN3D: [py, "-X", "importtime", *commands[OPEN3D][1:]],
        "gctr --help": [py, "-X", "importtime", "-m", "gctr_cli", "--help"],
        "python -c pass": [py, "-X", "importtime", "-c", "pass"],
    }
    # gctr register once more, timed from inside: external wall - in-process = interpreter start-up + exit
    clocked = [py, "-c", "import sys, time; t0 = time.perf_counter(); from gctr_cli.cli import main; "
               f"sys.argv = {['gctr', *commands[GCTR][1:]]!r}\n"
               "try:\n    main()\nexcept SystemExit:\n    pass\n"
               "print(f'@@inprocess {time.perf_counter() - t0}', file=sys.stderr)"]
    start_exit: list[float] = []
    inside: list[float] = []  # in-process time outside the engine: imports + files + config + printing
    packages: list[dict[str, float]] = []
    walls: dict[str, list[float]] = {k: [] for k in commands}
    imports: dict[str, list[float]] = {k: [] for k in commands}
    runtimes: dict[str, list[float]] = {k: [] for k in registering}
    status: dict[str, tuple[str, str]] = {}  # last run's status and message
    modules: dict[str, set[str]] = {}
    for name, cmd in commands.items():  # warm-up: page cache, .pyc files
        if name in configs:  # the -X importtime variant: which packages the method loads (some lazily)
            modules[name] = imported(run(as_module[name], args.cpu, ok_codes[name])[2])
        else:
            run(cmd, args.cpu)
    # import time without -X importtime's own cost: a fresh interpreter importing what the command imports
    register_modules = imported(run(as_module[GCTR], args.cpu)[2])
    ours = sorted(m for m in register_modules if m.startswith("gctr_cli"))
    probes = {GCTR: ours, OPEN3D: ["numpy", "open3d"], "gctr --help": ["gctr_cli.cli"], "python -c pass": []}
    for name in configs:  # its gctr_cli modules + the top-level packages gctr register does not load
        probes[name] = sorted({*ours, *(m for m in modules[name] if m.startswith("gctr_cli"))}) + sorted(
            {m.split(".")[0] for m in modules[name] - register_modules if not m.startswith("gctr_cli")})
    probe_s: dict[str, list[float]] = {k: [] for k in commands}
    for rep in range(args.reps):
        for name, cmd in commands.items():
            if args.warm:  # the same hot page cache for every command (see the module docstring)
                run(cmd, args.cpu, ok_codes.get(name, (0,)))
            wall, out, _ = run(cmd, args.cpu, ok_codes.get(name, (0,)))
            walls[name].append(wall)
            if name in registering:
                runtimes[name].append(float(field(r"^runtime_s: (\S+)", out, "runtime_s")))
                m = re.search(r"^message: (.*)$", out, re.M)
                status[name] = field(r"^status: (\S+)", out, "status"), m.group(1) if m else ""
            if name not in configs:  # per repetition for the reference rows only (it runs the command again)
                _, _, err = run(as_module[name], args.cpu)
                imports[name].append(sum(importtime(err).values()))
                modules[name] = imported(err)
                if name == GCTR:
                    packages.append(self_time_by_package(err))
            _, out, _ = run([py, "-c", "import time; t0 = time.perf_counter()\n"
                             + "".join(f"try:\n    import {m}\nexcept ImportError:\n    pass\n"
                                       for m in probes[name])
                             + "print(time.perf_counter() - t0)"], args.cpu)
            probe_s[name].append(float(out))
        if args.warm:
            run(clocked, args.cpu)
        wall, out, err = run(clocked, args.cpu)
        inprocess = float(field(r"@@inprocess (\S+)", err, "@@inprocess line"))
        start_exit.append(wall - inprocess)
        inside.append(inprocess - float(field(r"^runtime_s: (\S+)", out, "runtime_s")))
        print(f"[bench_process] repetition {rep + 1}/{args.reps}: " + ", ".join(
            f"{k} {walls[k][-1]:.2f} s" for k in commands), file=sys.stderr, flush=True)
    startup = modules["python -c pass"]
    startup_import = statistics.median(imports["python -c pass"])

    def import_s(name: str) -> float:
        return statistics.median(probe_s[name])

    def importtime_s(name: str) -> float | None:
        return statistics.median(imports[name]) - startup_import if imports[name] else None

    med = {k: statistics.median(v) for k, v in walls.items()}
    ratio = med[GCTR] / med[OPEN3D]
    heavy = sorted(m for m in modules[GCTR] - startup
                   if any(m == h or m.startswith(h + ".") for h in HEAVY_MODULES))
    accuracy = []
    if args.gt is not None:
        from gctr_cli.config import Config
        from gctr_cli.io import load_point_cloud, read_matrix
        from gctr_cli.metrics import transform_errors

        success = Config().success
        T_gt, cloud = read_matrix(args.gt), load_point_cloud(args.target)
        diag = float(np.linalg.norm(cloud.max(0) - cloud.min(0)))
        for name, f in matrices.items():
            st, message = status.get(name, (NOT_MEASURED, ""))
            if st in ("ok", NOT_MEASURED) and f.is_file():
                accuracy.append(accuracy_line(name, st, transform_errors(read_matrix(f), T_gt, diag), success=success))
            else:
                accuracy.append(accuracy_line(name, st if st != "ok" else "no matrix", None, message))

    command = "python -m data_scripts.bench_process" + (" " + shlex.join(argv_used) if argv_used else "")
    L = ["# Whole-process time: `gctr register` (GCTR engine and comparison methods) vs the Open3D script", "",
         f"Generated by `{command}` (`make bench-process`) "
         f"on {datetime.now(UTC):%Y-%m-%d %H:%M UTC}; {platform.processor() or platform.machine()}, "
         f"Python {platform.python_version()}, load average before the run {os.getloadavg()[0]:.2f} "
         "(other processes share the machine: compare the columns, not the absolute values). "
         f"Pair: `{_rel(args.source)}` ({_points(args.source)} points) → `{_rel(args.target)}` "
         f"({_points(args.target)} points). Every process pinned to one core (`taskset -c {args.cpu}`), one "
         f"BLAS/OpenMP thread; median of {args.reps} repetition(s), "
         + ("each right after an untimed run of the same command (the same hot page cache for every command)"
            if args.warm else "after one warm-up run of each command")
         + f"; page-out of idle file pages (Linux DAMON reclaim): {damon_state()}.", "",
         *TABLE_HEADER]
    for name in commands:
        L.append(table_row(name, walls[name], med[OPEN3D], import_s(name), importtime_s(name), runtimes.get(name)))
    eng_med = statistics.median(runtimes[GCTR])
    se = statistics.median(start_exit)
    rest = statistics.median(inside) - import_s(GCTR)
    names = sorted({k for d in packages for k in d}, key=lambda k: -statistics.median(d.get(k, 0.0) for d in packages))
    by_package = ", ".join(f"{k} {statistics.median(d.get(k, 0.0) for d in packages):.3f}" for k in names[:6])
    L += ["", "`gctr register`'s wall time split (medians, s): "
          f"engine {eng_med:.3f} · imports {import_s(GCTR):.3f} · interpreter start-up + exit {se:.3f} "
          f"(wall outside `main()`, measured from inside) · the rest (reading and checking the files, the "
          f"config, printing, writing the matrix) {rest:.3f} (in-process time minus engine, same run, "
          f"{statistics.median(inside):.3f}, minus imports; separate processes, so ± the noise of the machine).", "",
          f"Import self time by package (s): {by_package}.", ""]
    L += ["- imports = a fresh interpreter (same core) timing `import` of what the command imports: for gctr "
          f"register the {len(ours)} gctr_cli modules it loads (with everything they pull in), for a comparison "
          "method the same plus its own gctr_cli modules and the top-level packages its warm-up run loaded beyond "
          "gctr register's (e.g. `yaml` for the config, `open3d`), for the Open3D "
          "script `numpy, open3d`, for `gctr --help` `gctr_cli.cli`; imports, -X importtime = the top-level "
          "cumulative times of `python -X importtime` on the command itself minus those of `python -c pass` "
          f"({startup_import:.3f} s; the instrumentation inflates them; {NOT_MEASURED} for the comparison methods: "
          f"not repeated for them); interpreter start-up alone: {med['python -c pass']:.3f} s wall.",
          "- runtime_s = the time `gctr register` prints (the method's registration call on loaded arrays: the GCTR "
          "engine, or the comparison method named by `method:` in the config); overhead = wall − runtime_s.",
          f"- **gctr register / Open3D script = {ratio:.2f}** (goal ≤ 0.50: {'met' if ratio <= 0.5 else 'NOT met'}). "
          f"gctr's process overhead is {med[GCTR] - eng_med:.2f} s, the Open3D "
          f"script's imports alone {import_s(OPEN3D):.2f} s.",
          f"- heavy modules in `gctr register`'s import set ({', '.join(HEAVY_MODULES)}): "
          + (", ".join(heavy) if heavy else "none"),
          f"- modules imported by `gctr register` beyond start-up: {len(modules[GCTR] - startup)}; "
          f"by `gctr --help`: {len(modules['gctr --help'] - startup)}."]
    L += [f"- comparison method `{m}` skipped: its package `{_requires(m)}` is not importable "
          "(`make bench-deps` installs it)." for m in skipped]
    if not args.methods:
        L.append("- no comparison method timed (`--methods ''`).")
    L.append("")
    if accuracy:
        L += ["Every answer against the ground truth (`gctr_cli.metrics.transform_errors`; translation relative "
              "to the target's bounding-box diagonal; status = what `gctr register` printed in the last run; success "
              f"thresholds of the default config: rotation < {success.rotation_deg:g}°, translation < "
              f"{success.translation_rel:g} × diagonal, scale error < {success.scale:g}):", "",
              *ACCURACY_HEADER, *accuracy, ""]
    L += ["### Command lines", "", *command_lines(commands, args.cpu, configs)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(L))
    print("\n".join(L))
    return 0


def _requires(method: str) -> str:
    from gctr_cli.methods import REGISTRY

    return REGISTRY[method].requires or method


def _rel(path: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)


def _points(path: Path) -> int:
    from gctr_cli.io import load_point_cloud

    return len(load_point_cloud(path))


if __name__ == "__main__":
    sys.exit(main())
