"""Whole-process time of ``gctr register`` against the equivalent Open3D script (issue 10, item 3).

    python -m data_scripts.bench_process                      # make bench-process -> bench/PROCESS.md
    python -m data_scripts.bench_process --reps 3 --out /tmp/p.md --source a.ply --target b.ply

What runs, each as a fresh process pinned to one core (``taskset -c CPU``) with one BLAS/OpenMP thread,
``--reps`` times (after one untimed warm-up run of each, so every run finds the files in the page cache):

* ``gctr register SOURCE TARGET -o MATRIX`` (the console script of this checkout);
* ``python data_scripts/open3d_register.py SOURCE TARGET MATRIX`` — Open3D's tutorial recipe with scale
  (read, FPFH + RANSAC, scaled ICP, write the matrix);
* ``gctr --help`` and ``python -c pass`` (interpreter start-up), for reference.

Columns: median and minimum wall time; **import time** = the sum of the top-level cumulative times of
``python -X importtime`` for the same command, minus the modules ``python -c pass`` imports too (median
of the repetitions; ``-X importtime`` itself adds a little); for gctr, **engine** = the ``runtime_s`` it
prints (the ``register`` call: GCTR engine only, files already loaded) and **overhead** = wall − engine
(start-up, imports, reading, validation, printing, writing). The goal of the issue: gctr's median wall
time ≤ 0.5 × the Open3D script's.

Without ``--source/--target`` the pair is generated (seeded): 20 000 points of the shipped bunny as the
source and 20 000 other points moved by a similarity (scale 1.5) with 0.3 % noise as the target, binary
PLY, with the ground truth, so that both matrices are also checked.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

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


def run(cmd: list[str], cpu: int) -> tuple[float, str, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(pinned(cmd, cpu), capture_output=True, text=True, env=environment(), cwd=REPO_ROOT)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stderr[-2000:]}")
    return wall, proc.stdout, proc.stderr


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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m data_scripts.bench_process", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", type=Path)
    p.add_argument("--target", type=Path)
    p.add_argument("--gt", type=Path, help="ground-truth matrix of --source/--target (checks both answers)")
    p.add_argument("--reps", type=int, default=7, help="timed runs of each command (default 7)")
    p.add_argument("--cpu", type=int, default=0, help="core the processes are pinned to (default 0)")
    p.add_argument("--work", type=Path, default=REPO_ROOT / "bench" / "work" / "process")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "PROCESS.md")
    args = p.parse_args(argv)
    if (args.source is None) != (args.target is None):
        p.error("give both --source and --target, or neither")
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    if args.source is None:
        args.source, args.target, args.gt = make_pair(work / "pair")
    src, tgt = str(args.source.resolve()), str(args.target.resolve())
    py = sys.executable
    gctr = str(Path(py).with_name("gctr"))
    commands = {
        "gctr register": [gctr, "register", src, tgt, "-o", str(work / "gctr.txt")],
        "Open3D script": [py, str(REPO_ROOT / "data_scripts" / "open3d_register.py"), src, tgt,
                          str(work / "open3d.txt")],
        "gctr --help": [gctr, "--help"],
        "python -c pass": [py, "-c", "pass"],
    }
    as_module = {  # the same commands with -X importtime (the console script is `python -m gctr_cli`)
        "gctr register": [py, "-X", "importtime", "-m", "gctr_cli", *commands["gctr register"][1:]],
        "Open3D script": [py, "-X", "importtime", *commands["Open3D script"][1:]],
        "gctr --help": [py, "-X", "importtime", "-m", "gctr_cli", "--help"],
        "python -c pass": [py, "-X", "importtime", "-c", "pass"],
    }
    # gctr register once more, timed from inside: external wall - in-process = interpreter start-up + exit
    clocked = [py, "-c", "import sys, time; t0 = time.perf_counter(); from gctr_cli.cli import main; "
               f"sys.argv = {['gctr', *commands['gctr register'][1:]]!r}\n"
               "try:\n    main()\nexcept SystemExit:\n    pass\n"
               "print(f'@@inprocess {time.perf_counter() - t0}', file=sys.stderr)"]
    start_exit: list[float] = []
    inside: list[float] = []  # in-process time outside the engine: imports + files + config + printing
    packages: list[dict[str, float]] = []
    walls: dict[str, list[float]] = {k: [] for k in commands}
    imports: dict[str, list[float]] = {k: [] for k in commands}
    engine: list[float] = []
    modules: dict[str, set[str]] = {}
    for cmd in commands.values():
        run(cmd, args.cpu)  # warm-up: page cache, .pyc files
    # import time without -X importtime's own cost: a fresh interpreter importing what the command imports
    ours = sorted(m for m in imported(run(as_module["gctr register"], args.cpu)[2]) if m.startswith("gctr_cli"))
    probes = {"gctr register": ours, "Open3D script": ["numpy", "open3d"], "gctr --help": ["gctr_cli.cli"],
              "python -c pass": []}
    probe_s: dict[str, list[float]] = {k: [] for k in commands}
    for rep in range(args.reps):
        for name, cmd in commands.items():
            wall, out, _ = run(cmd, args.cpu)
            walls[name].append(wall)
            if name == "gctr register":
                engine.append(float(field(r"^runtime_s: (\S+)", out, "runtime_s")))
            _, _, err = run(as_module[name], args.cpu)
            imports[name].append(sum(importtime(err).values()))
            modules[name] = imported(err)
            if name == "gctr register":
                packages.append(self_time_by_package(err))
            _, out, _ = run([py, "-c", "import time; t0 = time.perf_counter()\n"
                             + "".join(f"import {m}\n" for m in probes[name])
                             + "print(time.perf_counter() - t0)"], args.cpu)
            probe_s[name].append(float(out))
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

    def importtime_s(name: str) -> float:
        return statistics.median(imports[name]) - startup_import

    med = {k: statistics.median(v) for k, v in walls.items()}
    ratio = med["gctr register"] / med["Open3D script"]
    heavy = sorted(m for m in modules["gctr register"] - startup
                   if any(m == h or m.startswith(h + ".") for h in HEAVY_MODULES))
    accuracy = []
    if args.gt is not None:
        from gctr_cli.io import load_point_cloud, read_matrix
        from gctr_cli.metrics import transform_errors

        T_gt, cloud = read_matrix(args.gt), load_point_cloud(args.target)
        diag = float(np.linalg.norm(cloud.max(0) - cloud.min(0)))
        for name, f in (("gctr register", "gctr.txt"), ("Open3D script", "open3d.txt")):
            e = transform_errors(read_matrix(work / f), T_gt, diag)
            accuracy.append(f"| {name} | {e.rot_err_deg:.3g} | {e.trans_err_rel:.3g} | {e.scale_err:.3g} |")

    L = ["# Whole-process time: `gctr register` vs the Open3D script", "",
         f"Generated by `python -m data_scripts.bench_process --reps {args.reps} --cpu {args.cpu}` "
         "(`make bench-process`) "
         f"on {datetime.now(UTC):%Y-%m-%d %H:%M UTC}; {platform.processor() or platform.machine()}, "
         f"Python {platform.python_version()}, load average before the run {os.getloadavg()[0]:.2f} "
         "(other processes share the machine: compare the columns, not the absolute values). "
         f"Pair: `{_rel(args.source)}` ({_points(args.source)} points) → `{_rel(args.target)}` "
         f"({_points(args.target)} points). Every process pinned to one core (`taskset -c {args.cpu}`), one "
         "BLAS/OpenMP thread; median of the repetitions after a warm-up run.", "",
         "| command | wall median (s) | wall min (s) | imports (s) | imports, -X importtime (s) | engine (s) | "
         "overhead (s) |",
         "|---|---:|---:|---:|---:|---:|---:|"]
    for name in commands:
        eng = statistics.median(engine) if name == "gctr register" else None
        L.append(f"| `{name}` | {med[name]:.3f} | {min(walls[name]):.3f} | {import_s(name):.3f} | "
                 f"{importtime_s(name):.3f} | "
                 + (f"{eng:.3f} | {med[name] - eng:.3f} |" if eng is not None else "– | – |"))
    eng_med = statistics.median(engine)
    se = statistics.median(start_exit)
    rest = statistics.median(inside) - import_s("gctr register")
    names = sorted({k for d in packages for k in d}, key=lambda k: -statistics.median(d.get(k, 0.0) for d in packages))
    by_package = ", ".join(f"{k} {statistics.median(d.get(k, 0.0) for d in packages):.3f}" for k in names[:6])
    L += ["", "`gctr register`'s wall time split (medians, s): "
          f"engine {eng_med:.3f} · imports {import_s('gctr register'):.3f} · interpreter start-up + exit {se:.3f} "
          f"(wall outside `main()`, measured from inside) · the rest (reading and checking the files, the "
          f"config, printing, writing the matrix) {rest:.3f} (in-process time minus engine, same run, "
          f"{statistics.median(inside):.3f}, minus imports; separate processes, so ± the noise of the machine).", "",
          f"Import self time by package (s): {by_package}.", ""]
    L += ["- imports = a fresh interpreter (same core) timing `import` of what the command imports: for gctr "
          f"register the {len(ours)} gctr_cli modules it loads (with everything they pull in), for the Open3D "
          "script `numpy, open3d`, for `gctr --help` `gctr_cli.cli`; imports, -X importtime = the top-level "
          "cumulative times of `python -X importtime` on the command itself minus those of `python -c pass` "
          f"({startup_import:.3f} s; the instrumentation inflates them); interpreter start-up alone: "
          f"{med['python -c pass']:.3f} s wall.",
          "- engine = the `runtime_s` gctr prints (the registration call on loaded arrays); overhead = wall − engine.",
          f"- **gctr register / Open3D script = {ratio:.2f}** (goal ≤ 0.50: {'met' if ratio <= 0.5 else 'NOT met'}). "
          f"gctr's process overhead is {med['gctr register'] - statistics.median(engine):.2f} s, the Open3D "
          f"script's imports alone {import_s('Open3D script'):.2f} s.",
          f"- heavy modules in `gctr register`'s import set ({', '.join(HEAVY_MODULES)}): "
          + (", ".join(heavy) if heavy else "none"),
          f"- modules imported by `gctr register` beyond start-up: {len(modules['gctr register'] - startup)}; "
          f"by `gctr --help`: {len(modules['gctr --help'] - startup)}.", ""]
    if accuracy:
        L += ["Both answers against the ground truth:", "",
              "| command | rotation (deg) | translation / diagonal | scale error |", "|---|---:|---:|---:|",
              *accuracy, ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(L))
    print("\n".join(L))
    return 0


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
