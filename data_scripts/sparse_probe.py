"""Sparse pairs: does the engine refuse what it cannot resolve, on clouds of a few hundred points?

The benchmark's sparsest cloud has about 2,500 points (``hard``'s target), and its verdict samples
800 points a cloud. Users also register sparse clouds (a sparse structure-from-motion model, a
thinned scan). This probe draws two independent random subsets of ``n`` points from each shipped model
(``data/models``: bunny, dragon, redkitchen), adds Gaussian noise (a share of the model's bounding-box
diagonal), moves the source by a random similarity (scale 0.5-2) and registers the pair with the
engine. Everything is drawn from ``--offset``, the size and the repetition, so a run is reproducible;
use one offset to tune and another to check (``--offset 0`` has been used for tuning).

Usage::

    python -m data_scripts.sparse_probe --offset 50000 --sizes 300,500,800,1200 --reps 8 \\
        --noise 0,0.002 -j 2 [--set engine.min_confidence=0.2] [--csv rows.csv]

A pair is right when it meets the benchmark's criterion (rotation < 5°, translation < 5% of the target
diagonal, scale within 5%). The report counts, per size: right and accepted, accepted but wrong
(*silent wrong*), refused though right, refused and wrong.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from data_scripts.bench_engine import BenchError, code_state, resolve_config
from data_scripts.common import confidence_sweep, sweep_table, sweep_thresholds

REPO_ROOT = Path(__file__).resolve().parents[1]
MODELS = ("bunny", "dragon", "redkitchen")


def sparse_pair(model_points: np.ndarray, n: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source, target, true source->target similarity): two random ``n``-point subsets of the model with
    Gaussian noise of ``noise`` x its bounding-box diagonal, the source moved by a random similarity."""
    from scipy.spatial.transform import Rotation

    from gctr_cli.geometry import apply, to_matrix

    rng = np.random.default_rng(seed)
    diagonal = float(np.linalg.norm(model_points.max(0) - model_points.min(0)))
    a = model_points[rng.choice(len(model_points), n, replace=False)]
    b = model_points[rng.choice(len(model_points), n, replace=False)]
    a = a + rng.normal(0.0, noise * diagonal, a.shape)
    b = b + rng.normal(0.0, noise * diagonal, b.shape)
    T = to_matrix(float(rng.uniform(0.5, 2.0)), Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 1, 3))
    return apply(np.linalg.inv(T), a), b, T


def run_one(task: tuple[str, int, float, int, int, dict[str, Any]]) -> dict[str, Any]:
    """Register one sparse pair; its outcome as a row."""
    from gctr_cli.config import config_from_dict
    from gctr_cli.engine import register
    from gctr_cli.io import load_point_cloud
    from gctr_cli.metrics import transform_errors

    model, n, noise, rep, offset, config = task
    points = np.asarray(load_point_cloud(REPO_ROOT / "data" / "models" / f"{model}.ply"), dtype=np.float64)
    source, target, T = sparse_pair(points, n, noise, offset + 1000 * n + rep)
    result = register(source, target, config_from_dict(config, "<sparse probe>").engine, seed=rep)
    err = transform_errors(result.transform, T, float(np.linalg.norm(target.max(0) - target.min(0))),
                           source.mean(axis=0))
    right = err.success(5.0, 0.05, 0.05)
    outcome = ("right" if right else "silent wrong") if result.status == "ok" else (
        "refused right" if right else "refused wrong")
    return {"model": model, "n": n, "noise": noise, "rep": rep, "status": result.status, "outcome": outcome,
            "confidence": round(result.confidence, 4), "rot_err_deg": round(err.rot_err_deg, 3),
            "scale_err": round(err.scale_err, 5), "message": result.message}


def report(rows: list[dict[str, Any]], title: str, provenance: list[str], threshold: float) -> str:
    """Markdown: outcomes per size (all models and noise levels), the confidence threshold's trade-off,
    then the silent wrong pairs."""
    kinds = ("right", "silent wrong", "refused right", "refused wrong")
    lines = [f"# Sparse probe ({title})", "", *provenance, "",
             "| points per cloud | pairs | " + " | ".join(kinds) + " |", "|---:|---:|" + "---:|" * len(kinds)]
    for n in sorted({r["n"] for r in rows}) + ["all"]:
        sel = [r for r in rows if n == "all" or r["n"] == n]
        lines.append(f"| {n} | {len(sel)} | " + " | ".join(str(sum(r['outcome'] == k for r in sel)) for k in kinds)
                     + " |")
    # the trade-off offline: a pair refused for another reason than its confidence counts as refused
    swept = [{"would_succeed": r["outcome"] in ("right", "refused right"),
              "confidence": r["confidence"] if r["status"] == "ok" or "confidence" in r["message"] else 0.0}
             for r in rows]
    lines += ["", "Confidence threshold (all pairs; the configured one marked):", "",
              *sweep_table({"gctr": confidence_sweep(swept, sweep_thresholds(threshold))}, threshold)]
    wrong = [r for r in rows if r["outcome"] == "silent wrong"]
    if wrong:
        lines += ["", "Silent wrong:", ""]
        lines += [f"- {r['model']} n={r['n']} noise={r['noise']} rep={r['rep']}: confidence {r['confidence']}, "
                  f"{r['rot_err_deg']}° and {r['scale_err']:.1%} in scale off" for r in wrong]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--offset", type=int, required=True, help="seed offset of the draws (0 was used for tuning)")
    p.add_argument("--sizes", default="300,500,800,1200", help="points per cloud, comma-separated")
    p.add_argument("--reps", type=int, default=8, help="pairs per model, size and noise level")
    p.add_argument("--noise", default="0,0.002", help="noise levels (share of the model's diagonal)")
    p.add_argument("-j", "--jobs", type=int, default=1, help="pairs in parallel")
    p.add_argument("-c", "--config", type=Path, help="config file (default: the built-in defaults)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="dotted config override, e.g. engine.min_confidence=0.2 (repeatable)")
    p.add_argument("--out", type=Path, help="markdown report (default: stdout)")
    p.add_argument("--csv", type=Path, help="one row per pair")
    args = p.parse_args(argv)
    try:
        _, config = resolve_config(args.config, args.overrides)
    except BenchError as err:
        p.error(str(err))
    tasks = [(m, int(n), float(z), rep, args.offset, config) for m in MODELS for n in args.sizes.split(",")
             for z in args.noise.split(",") for rep in range(args.reps)]
    with multiprocessing.get_context("spawn").Pool(max(args.jobs, 1)) as pool:
        rows = pool.map(run_one, tasks, chunksize=1)
    title = f"offset {args.offset}, noise {args.noise}" + (f", {' '.join(args.overrides)}" if args.overrides else "")
    command = "python -m data_scripts.sparse_probe " + " ".join(argv if argv is not None else sys.argv[1:])
    provenance = [f"- Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}", f"- Command: `{command}`",
                  f"- Code: {code_state()}",
                  f"- Pairs: {len(rows)} ({', '.join(MODELS)}; sizes {args.sizes}; {args.reps} per model, size and "
                  "noise level); right = rotation < 5°, translation < 5% of the target diagonal, scale within 5%"]
    text = report(rows, title, provenance, float(config["engine"]["min_confidence"]))
    if args.out:
        args.out.write_text(text)
    else:
        print(text, end="")
    if args.csv:
        import csv

        with open(args.csv, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
