"""Scale benchmark of the batch layer (issue 12): many pairs through both executors with a stand-in engine.

What it measures, per run (``gctr_cli.batch.run_batch`` in this process, like ``gctr batch``):

* **rows exactly once**: ``transforms.csv`` has one row per pair id, no more, no less;
* **memory of the batch process** (not its workers): resident set size sampled every 0.25 s; reported
  before the first row and when 10%, 50% and 90% of the rows are written — flat means the batch
  process does not grow with the number of pairs (outcomes are streamed to disk, submissions are
  bounded) — and after the end (the summary and report.html read every row once), with its peak;
* **per-pair overhead**: ``(wall time x workers - engine time) / pairs``, the time a worker slot spends
  on a pair outside the register call (loading two small clouds, pipes or the dask scheduler, the
  batch process's fsynced rows and matrix file), and the engine's share of the slots' time;
* **speed-up** of 2 workers over 1 with an engine that burns ``--work-ms`` of CPU per pair.

The engine is :func:`data_scripts.fake_engine.busy_register` (the batch tests' fake engine plus a busy
loop): Umeyama on index correspondences of two 200-point clouds (every pair uses the same two files);
no Open3D, so the numbers are the batch layer's own. Usage (defaults: 10,000 pairs at -j2 for the scale
runs; 300 pairs of 100 ms of work at -j1 and -j2 for the speed-up)::

    python -m data_scripts.bench_batch --out bench/BATCH.md
    python -m data_scripts.bench_batch --pairs 1000 --speedup-pairs 100 --out /tmp/BATCH.md   # quick
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
ENGINE = "data_scripts.fake_engine:busy_register"


class RssSampler:
    """Samples this process's resident set size (MiB) and the number of rows written so far."""

    def __init__(self, transforms: Path, period_s: float = 0.25) -> None:
        self.transforms = transforms
        self.period_s = period_s
        self.samples: list[tuple[int, float]] = []  # (rows written, rss MiB)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def rss_mib() -> float:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
        return float("nan")

    def _rows(self) -> int:
        try:
            with open(self.transforms, "rb") as fh:
                return max(0, sum(chunk.count(b"\n") for chunk in iter(lambda: fh.read(1 << 20), b"")) - 1)
        except OSError:
            return 0

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.samples.append((self._rows(), self.rss_mib()))

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append((self._rows(), self.rss_mib()))

    def at_fraction(self, n_total: int, frac: float) -> float:
        for rows, rss in self.samples:
            if rows >= frac * n_total:
                return rss
        return self.samples[-1][1] if self.samples else float("nan")


def make_pairs(root: Path, n: int):
    """``n`` pairs (ids p000000...) of the same two 200-point clouds with ground truth."""
    from gctr_cli.geometry import apply, to_matrix
    from gctr_cli.io import save_point_cloud, write_matrix
    from gctr_cli.manifest import PairSpec

    rng = np.random.default_rng(1)
    src = rng.uniform(-1, 1, (200, 3))
    c, s_ = np.cos(0.3), np.sin(0.3)
    T = to_matrix(1.5, np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]), [2.0, -1.0, 0.5])
    tgt = apply(T, src)
    root.mkdir(parents=True, exist_ok=True)
    save_point_cloud(root / "src.ply", src)
    save_point_cloud(root / "tgt.ply", tgt)
    write_matrix(root / "gt.txt", T)
    return [PairSpec(pair_id=f"p{i:06d}", source=root / "src.ply", target=root / "tgt.ply", gt=root / "gt.txt")
            for i in range(n)]


def run_one(pairs, outdir: Path, executor: str, workers: int, work_ms: float) -> dict:
    from gctr_cli.batch import run_batch
    from gctr_cli.config import config_from_dict

    shutil.rmtree(outdir, ignore_errors=True)
    os.environ["GCTR_BENCH_WORK_MS"] = str(work_ms)  # inherited by pool workers and LocalCluster workers
    config = config_from_dict({"seed": 1, "batch": {"workers": workers, "time_limit_s": 600}})
    rss0 = RssSampler.rss_mib()
    t0 = time.monotonic()
    with RssSampler(outdir / "transforms.csv") as sampler:
        summary = run_batch(pairs, config, outdir, workers=workers, executor=executor,
                            register_fn=ENGINE)
    wall = time.monotonic() - t0
    with open(outdir / "transforms.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    ids = [r["pair_id"] for r in rows]
    engine_s = sum(float(r["runtime_s"]) for r in rows)
    n = len(pairs)
    return {
        "executor": executor, "workers": workers, "pairs": n, "work_ms": work_ms, "wall_s": wall,
        "exactly_once": len(ids) == n and set(ids) == {p.pair_id for p in pairs},
        "all_ok": summary.n_ok == n,
        "pairs_per_s": n / wall, "engine_s": engine_s,
        "overhead_ms": (wall * workers - engine_s) / n * 1000.0,
        "engine_share": engine_s / (wall * workers),
        "rss_start": rss0, "rss_10": sampler.at_fraction(n, 0.1), "rss_50": sampler.at_fraction(n, 0.5),
        "rss_90": sampler.at_fraction(n, 0.9),
        "rss_end": sampler.samples[-1][1], "rss_peak": max(r for _, r in sampler.samples),
    }


def fmt_table(results: list[dict]) -> str:
    head = ("| executor | -j | pairs | engine work / pair | wall (s) | pairs/s | rows exactly once | overhead / pair "
            "(ms) | engine share | batch RSS MiB at 0, 10, 50, 90% of the rows; after summary + report (peak) |")
    lines = [head, "|" + "---|" * 10]
    for r in results:
        lines.append(
            f"| {r['executor']} | {r['workers']} | {r['pairs']:,} | {r['work_ms']:g} ms | {r['wall_s']:.1f} | "
            f"{r['pairs_per_s']:.0f} | {'yes' if r['exactly_once'] and r['all_ok'] else 'NO'} | "
            f"{r['overhead_ms']:.2f} | {100 * r['engine_share']:.0f}% | {r['rss_start']:.0f}, {r['rss_10']:.0f}, "
            f"{r['rss_50']:.0f}, {r['rss_90']:.0f}; {r['rss_end']:.0f} ({r['rss_peak']:.0f}) |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=10_000, help="pairs of the scale runs (work 0 ms)")
    ap.add_argument("--scale-workers", default="2", help="comma-separated -j values of the scale runs")
    ap.add_argument("--speedup-pairs", type=int, default=300, help="pairs of the -j1 / -j2 speed-up runs")
    ap.add_argument("--work-ms", type=float, default=100.0, help="CPU burnt per pair in the speed-up runs")
    ap.add_argument("--executors", default="local,dask", help="comma-separated: local, dask")
    ap.add_argument("--work", type=Path, default=REPO / "bench" / "work" / "batch-scale", help="scratch folder")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "BATCH.md", help="Markdown report")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))  # workers import data_scripts.fake_engine:busy_register

    executors = [e.strip() for e in args.executors.split(",") if e.strip()]
    pairs = make_pairs(args.work / "data", max(args.pairs, args.speedup_pairs))
    scale, speed = [], []
    scale_workers = [int(j) for j in args.scale_workers.split(",") if j.strip()]
    for ex in executors:
        for j in scale_workers:
            r = run_one(pairs[: args.pairs], args.work / f"out-{ex}-{j}", ex, j, 0.0)
            print(fmt_table([r]).splitlines()[-1], flush=True)
            scale.append(r)
    for ex in executors:
        for j in (1, 2):
            r = run_one(pairs[: args.speedup_pairs], args.work / f"speed-{ex}-{j}", ex, j, args.work_ms)
            print(fmt_table([r]).splitlines()[-1], flush=True)
            speed.append(r)

    try:
        from data_scripts.common import machine_info

        machine = ", ".join(f"{k} {v}" for k, v in machine_info().items())
    except Exception:  # noqa: BLE001
        machine = "?"
    speedups = []
    for ex in executors:
        one = next(r for r in speed if r["executor"] == ex and r["workers"] == 1)
        two = next(r for r in speed if r["executor"] == ex and r["workers"] == 2)
        speedups.append(f"- {ex}: -j2 is {one['wall_s'] / two['wall_s']:.2f}x faster than -j1 "
                        f"({one['wall_s']:.1f} s -> {two['wall_s']:.1f} s for {one['pairs']:,} pairs of "
                        f"{args.work_ms:g} ms)")
    cmd = "python -m data_scripts.bench_batch " + " ".join(argv if argv is not None else sys.argv[1:])
    text = f"""# Batch layer at scale (stand-in engine)

Command: `{cmd.strip()}` ({time.strftime('%Y-%m-%d')}). Machine: {machine}.
The engine is `data_scripts/fake_engine.py:busy_register` (Umeyama on 200-point clouds plus a CPU busy loop),
so the numbers are the batch layer's own: loading the two clouds, the pipe or the dask scheduler, and the
batch process's fsynced rows and matrix file. Overhead per pair = (wall x workers - engine time) / pairs.
The dask runs start their own LocalCluster (-j worker processes, one thread each); its start-up (a few
seconds) is in the wall time. Other processes shared the machine's cores during the runs.

## Scale: {args.pairs:,} pairs, no engine work

{fmt_table(scale)}

## Speed-up: {args.speedup_pairs:,} pairs, {args.work_ms:g} ms of engine work each

{fmt_table(speed)}

{chr(10).join(speedups)}
"""
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    bad = [r for r in scale + speed if not (r["exactly_once"] and r["all_ok"])]
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
