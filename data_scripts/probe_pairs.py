"""Pairs outside the benchmark: does the engine refuse what it cannot resolve?

Two kinds of pair that users have and the benchmark's levels do not cover, drawn from the shipped
models (``data/models``: bunny, dragon, redkitchen):

* ``sparse``: two independent random subsets of ``n`` points of one model (a sparse
  structure-from-motion model, a thinned scan; the benchmark's sparsest cloud has about 2,500 points,
  and its verdict samples 800 points a cloud);
* ``unrelated``: a random ``n``-point subset of one model, cropped to a ball holding 50-100% of it,
  against a random ``n``-point subset of *another* model — a manifest that pairs the wrong files.
  Every answer is wrong, so every ``ok`` is a silent wrong answer;
* ``mirrored``: a random ``n``-point subset of one model, cropped the same way and reflected through a
  random plane (a cloud exported with a flipped axis, from a left-handed coordinate system), against
  another ``n``-point subset of the same model. No rotation aligns a mirror image, so every ``ok`` is
  a silent wrong answer too.

Both clouds get Gaussian noise (a share of the model's bounding-box diagonal), and the source is moved
by a random similarity (scale 0.5-2). Everything is drawn from ``--offset``, the kind, the models, the
size and the repetition, so a run is reproducible; use one offset to tune and another to check
(``--offset 0`` and, for unrelated pairs, ``--offset 1000`` have been used for tuning).

Usage::

    python -m data_scripts.probe_pairs --kind sparse --offset 50000 --sizes 300,500,800,1200 --reps 8 \\
        --noise 0,0.002 -j 2 [--set engine.min_confidence=0.2] [--csv rows.csv]
    python -m data_scripts.probe_pairs --kind unrelated --offset 50000 --sizes 1000,2000 --reps 8 -j 2
    python -m data_scripts.probe_pairs --kind mirrored --offset 50000 --sizes 2000,8000 --reps 4 -j 2

A pair is right when it meets the benchmark's criterion (rotation < 5°, translation < 5% of the target
diagonal, scale within 5%). The report counts, per size: right and accepted, accepted but wrong
(*silent wrong*), refused though right, refused and wrong, and the confidence threshold's trade-off.
"""

from __future__ import annotations

import argparse
import functools
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


def _diagonal(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(0) - points.min(0)))


def _noisy_and_similarity(rng: np.random.Generator, a: np.ndarray, b: np.ndarray, noise_a: float,
                          noise_b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``a`` and ``b`` with Gaussian noise of the given standard deviations, and a random similarity
    (scale 0.5-2, any rotation, a unit-normal shift), drawn from ``rng`` in that order."""
    from scipy.spatial.transform import Rotation

    from gctr_cli.geometry import to_matrix

    a = a + rng.normal(0.0, noise_a, a.shape)
    b = b + rng.normal(0.0, noise_b, b.shape)
    T = to_matrix(float(rng.uniform(0.5, 2.0)), Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 1, 3))
    return a, b, T


def sparse_pair(model_points: np.ndarray, n: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source, target, true source->target similarity): two random ``n``-point subsets of the model with
    Gaussian noise of ``noise`` x its bounding-box diagonal, the source moved by a random similarity."""
    from gctr_cli.geometry import apply

    rng = np.random.default_rng(seed)
    sigma = noise * _diagonal(model_points)
    a = model_points[rng.choice(len(model_points), n, replace=False)]
    b = model_points[rng.choice(len(model_points), n, replace=False)]
    a, b, T = _noisy_and_similarity(rng, a, b, sigma, sigma)
    return apply(np.linalg.inv(T), a), b, T


def _cropped_subset(rng: np.random.Generator, points: np.ndarray, n: int) -> np.ndarray:
    """A random ``n``-point subset of ``points`` cropped to a ball (round one of its points) holding 50-100%
    of it, drawn from ``rng`` in that order."""
    a = points[rng.choice(len(points), min(n, len(points)), replace=False)]
    distance = np.linalg.norm(a - a[rng.integers(len(a))], axis=1)
    return a[distance <= np.quantile(distance, rng.uniform(0.5, 1.0))]


def unrelated_pair(source_model: np.ndarray, target_model: np.ndarray, n: int, noise: float,
                   seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source, target, the similarity the source was moved by): a random ``n``-point subset of
    ``source_model`` cropped to a ball holding 50-100% of it, and a random ``n``-point subset of another
    model; noise as in :func:`sparse_pair`. No transform aligns them."""
    from gctr_cli.geometry import apply

    rng = np.random.default_rng(seed)
    a = _cropped_subset(rng, source_model, n)
    b = target_model[rng.choice(len(target_model), min(n, len(target_model)), replace=False)]
    a, b, T = _noisy_and_similarity(rng, a, b, noise * _diagonal(source_model), noise * _diagonal(target_model))
    return apply(T, a), b, T


def mirrored_pair(model_points: np.ndarray, n: int, noise: float,
                  seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source, target, the similarity the source was moved by): a random ``n``-point subset of the model
    cropped to a ball holding 50-100% of it and *reflected* through a random plane (a cloud from a
    left-handed coordinate system, a flipped axis), against another ``n``-point subset of the same model;
    noise as in :func:`sparse_pair`. No similarity (a proper rotation) aligns them."""
    from gctr_cli.geometry import apply

    rng = np.random.default_rng(seed)
    a = _cropped_subset(rng, model_points, n)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    a = a - 2.0 * np.outer((a - a.mean(axis=0)) @ normal, normal)
    b = model_points[rng.choice(len(model_points), min(n, len(model_points)), replace=False)]
    sigma = noise * _diagonal(model_points)
    a, b, T = _noisy_and_similarity(rng, a, b, sigma, sigma)
    return apply(T, a), b, T


@functools.cache
def _model(name: str) -> np.ndarray:
    """A shipped model's points (read once per worker process, not once per pair)."""
    from gctr_cli.io import load_point_cloud

    return np.asarray(load_point_cloud(REPO_ROOT / "data" / "models" / f"{name}.ply"), dtype=np.float64)


def run_one(task: tuple[str, str, int, float, int, int, dict[str, Any]]) -> dict[str, Any]:
    """Register one probe pair (``kind``, ``models``: "bunny" or "dragon>bunny", ...); its outcome as a row."""
    from gctr_cli.config import config_from_dict
    from gctr_cli.engine import register
    from gctr_cli.metrics import transform_errors

    kind, models, n, noise, rep, offset, config = task
    if kind == "sparse":
        source, target, T = sparse_pair(_model(models), n, noise, offset + 1000 * n + rep)
    elif kind == "mirrored":
        source, target, T = mirrored_pair(_model(models), n, noise, offset + 1000 * n + rep + 200_000)
    else:
        a, b = models.split(">")
        pair_index = 3 * MODELS.index(a) + MODELS.index(b)
        seed = offset + 1000 * n + rep + 100_000 * pair_index
        source, target, T = unrelated_pair(_model(a), _model(b), n, noise, seed)
    result = register(source, target, config_from_dict(config, f"<{kind} probe>").engine, seed=rep)
    err = transform_errors(result.transform, T, float(np.linalg.norm(target.max(0) - target.min(0))),
                           source.mean(axis=0))
    right = kind == "sparse" and err.success(5.0, 0.05, 0.05)
    outcome = ("right" if right else "silent wrong") if result.status == "ok" else (
        "refused right" if right else "refused wrong")
    evidence = result.evidence or {}
    return {"kind": kind, "model": models, "n": n, "noise": noise, "rep": rep, "status": result.status,
            "outcome": outcome, "refusal": result.refusal, "confidence": round(result.confidence, 4),
            "score": round(evidence.get("score", float("nan")), 4),
            "mirror_score": round(evidence.get("mirror_score", float("nan")), 4),
            "rot_err_deg": round(err.rot_err_deg, 3) if kind == "sparse" else "",
            "scale_err": round(err.scale_err, 5) if kind == "sparse" else "", "message": result.message}


def report(rows: list[dict[str, Any]], title: str, provenance: list[str], threshold: float) -> str:
    """Markdown: outcomes per size (all models and noise levels), the confidence threshold's trade-off,
    then the silent wrong pairs."""
    kinds = ("right", "silent wrong", "refused right", "refused wrong")
    lines = [f"# Probe pairs: {title}", "", *provenance, "",
             "| points per cloud | pairs | " + " | ".join(kinds) + " |", "|---:|---:|" + "---:|" * len(kinds)]
    for n in sorted({r["n"] for r in rows}) + ["all"]:
        sel = [r for r in rows if n == "all" or r["n"] == n]
        lines.append(f"| {n} | {len(sel)} | " + " | ".join(str(sum(r['outcome'] == k for r in sel)) for k in kinds)
                     + " |")
    # the trade-off offline (a pair refused for another reason than its confidence counts as refused)
    swept = [{"would_succeed": r["outcome"] in ("right", "refused right"), "refusal": r["refusal"],
              "confidence": r["confidence"]} for r in rows]
    lines += ["", "Confidence threshold (all pairs; the configured one marked):", "",
              *sweep_table({"gctr": confidence_sweep(swept, sweep_thresholds(threshold))}, threshold)]
    wrong = [r for r in rows if r["outcome"] == "silent wrong"]
    if wrong:
        lines += ["", "Silent wrong:", ""]
        lines += [f"- {r['model']} n={r['n']} noise={r['noise']} rep={r['rep']}: confidence {r['confidence']}"
                  + (f", {r['rot_err_deg']}° and {r['scale_err']:.1%} in scale off" if r["kind"] == "sparse" else "")
                  for r in wrong]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kind", choices=("sparse", "unrelated", "mirrored"), default="sparse",
                   help="sparse: two subsets of one model; unrelated: subsets of two different models; mirrored: "
                        "a reflected subset of one model against another subset of it")
    p.add_argument("--offset", type=int, required=True,
                   help="seed offset of the draws (0, and 1000 for unrelated pairs, were used for tuning)")
    p.add_argument("--sizes", help="points per cloud, comma-separated (default: sparse 300,500,800,1200; "
                                   "unrelated 1000,2000; mirrored 2000,8000)")
    p.add_argument("--reps", type=int, default=8, help="pairs per model (pair), size and noise level")
    p.add_argument("--noise", help="noise levels, share of the model's diagonal (default: sparse 0,0.002; "
                                   "unrelated and mirrored 0.002)")
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
    sizes = args.sizes or {"sparse": "300,500,800,1200", "unrelated": "1000,2000", "mirrored": "2000,8000"}[args.kind]
    noises = args.noise or ("0,0.002" if args.kind == "sparse" else "0.002")
    models = [f"{a}>{b}" for a in MODELS for b in MODELS if a != b] if args.kind == "unrelated" else list(MODELS)
    try:
        size_values = [int(n) for n in sizes.split(",")]
        noise_values = [float(z) for z in noises.split(",")]
    except ValueError as err:
        p.error(f"--sizes and --noise take comma-separated numbers ({err})")
    if args.reps < 1 or min(size_values) < 10 or not all(0 <= z < 0.1 for z in noise_values):
        p.error("--reps must be at least 1, --sizes at least 10 points, --noise in [0, 0.1)")
    tasks = [(args.kind, m, n, z, rep, args.offset, config) for m in models for n in size_values
             for z in noise_values for rep in range(args.reps)]
    with multiprocessing.get_context("spawn").Pool(max(args.jobs, 1)) as pool:
        rows = pool.map(run_one, tasks, chunksize=1)
    title = (f"{args.kind}, offset {args.offset}, noise {noises}"
             + (f", {' '.join(args.overrides)}" if args.overrides else ""))
    command = "python -m data_scripts.probe_pairs " + " ".join(argv if argv is not None else sys.argv[1:])
    what = {"sparse": "two subsets of one model",
            "unrelated": "a cropped subset of one model against a subset of another: every ok is wrong",
            "mirrored": "a cropped, reflected subset of one model against another subset of it: every ok is wrong"
            }[args.kind]
    provenance = [f"- Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}", f"- Command: `{command}`",
                  f"- Code: {code_state()}",
                  f"- Pairs: {len(rows)}, {what} ({', '.join(models)}; sizes {sizes}; {args.reps} per model, size "
                  "and noise level); right = rotation < 5°, translation < 5% of the target diagonal, scale "
                  "within 5%"]
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
