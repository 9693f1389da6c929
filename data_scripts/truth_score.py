"""How the verdict judges the ground truth itself: can the engine accept the right answer at all?

The engine accepts an answer when its confidence — the lead of its score (surface agreement less
conflicts, at the verdict's tight tolerances) over the best distinct rival, or over 0, divided by
``verdict.full_margin`` — reaches ``min_confidence``. A right answer scores about what the *ground
truth* scores (its refinement may fit the noise slightly better: up to 0.01 more on the report set's
NCLT windows), so a pair whose truth scores ``x`` can be accepted at about confidence
``x / full_margin`` at best, whatever the search finds. This tool
scores the ground truth of every pair with the engine's own verdict test
(:func:`gctr_cli.engine.gctr.verdict_agreement`, same preparation and seed as ``register``) and
reports, per level and model, how many pairs' truth could reach the threshold at all: where it cannot,
the pairs are limited by what the verdict's objective can see in the data (noise, overlap), not by the
search, and only an objective change can help them.

Usage::

    python -m data_scripts.truth_score --data bench/work/data-seed1 --levels scene -j 2
    python -m data_scripts.truth_score --data DIR --match nclt --csv /tmp/truth.csv

The rows carry the generator's ``overlap_src`` (share of the source in the overlap) when the manifest
has it. Tune on the tuning sets (seeds 1, 2, 3), never on the report set (seed 0).
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import sys
from pathlib import Path
from typing import Any

from data_scripts.bench_engine import (
    ALL_LEVELS,
    BenchError,
    add_pair_tool_arguments,
    load_tasks,
    resolve_config,
    write_tool_outputs,
)

#: columns of ``--csv``
CSV_FIELDS = ["pair_id", "level", "model", "overlap_src", "score", "source_on", "target_on", "source_beside",
              "target_beside", "best_confidence", "acceptable", "error"]


def truth_row(task: dict[str, Any]) -> dict[str, Any]:
    """The verdict's agreement with the ground truth of one pair (a bench_engine task)."""
    from gctr_cli.config import config_from_dict
    from gctr_cli.engine.gctr import verdict_agreement
    from gctr_cli.engine.preprocess import DegenerateCloudError
    from gctr_cli.io import MatrixError, PointCloudError, load_point_cloud, read_matrix

    config = config_from_dict(task["config"], "<truth_score config>")
    row: dict[str, Any] = {"pair_id": task["pair_id"], "level": task["level"], "model": task["model"],
                           "overlap_src": (task.get("meta", {}).get("overlap_src") or "").strip()}
    try:
        a = verdict_agreement(load_point_cloud(task["source"]), load_point_cloud(task["target"]),
                              read_matrix(task["gt"]), config.engine, int(task["seed"]))
    except (DegenerateCloudError, PointCloudError, MatrixError) as err:  # the message names the file
        return {**row, "error": str(err)}
    best = min(1.0, max(0.0, a.score / config.engine.verdict.full_margin))
    return {**row, "score": a.score, "source_on": a.source, "target_on": a.target,
            "source_beside": a.conflict_source, "target_beside": a.conflict_target, "best_confidence": best,
            "acceptable": best >= config.engine.min_confidence, "error": ""}


def render(rows: list[dict[str, Any]], data: Path, min_confidence: float) -> str:
    """Markdown: per level and model, the truth's scores and how many pairs it could be accepted on;
    then every pair whose truth cannot reach the threshold."""
    scored = [r for r in rows if not r["error"]]
    out = [f"# Ground truth under the verdict: {data} ({len(rows)} pairs)", "",
           f"A right answer scores about what the truth scores, so a pair can be accepted only if its truth's "
           f"best confidence (score / full_margin) reaches about min_confidence {min_confidence:g}.", "",
           "| level | model | pairs | truth score median (min–max) | on / beside, source | on / beside, target "
           "| truth reaches threshold |", "|---|---|---:|---|---|---|---:|"]
    groups = sorted({(r["level"], r["model"]) for r in scored}, key=lambda g: (ALL_LEVELS.index(g[0])
                                                                              if g[0] in ALL_LEVELS else 99, g[1]))
    for level, model in groups:
        sel = [r for r in scored if (r["level"], r["model"]) == (level, model)]
        med = {k: statistics.median(r[k] for r in sel)
               for k in ("score", "source_on", "source_beside", "target_on", "target_beside")}
        low, high = min(r["score"] for r in sel), max(r["score"] for r in sel)
        out.append(f"| {level} | {model} | {len(sel)} | {med['score']:+.3f} ({low:+.3f} – {high:+.3f}) | "
                   f"{med['source_on']:.2f} / {med['source_beside']:.2f} | {med['target_on']:.2f} / "
                   f"{med['target_beside']:.2f} | {sum(r['acceptable'] for r in sel)} |")
    refused = sorted((r for r in scored if not r["acceptable"]), key=lambda r: r["pair_id"])
    out += ["", f"Pairs whose truth cannot reach the threshold: {len(refused)}", ""]
    if refused:
        out += ["| pair | overlap_src | truth score | best confidence |", "|---|---:|---:|---:|"]
        out += [f"| {r['pair_id']} | {r['overlap_src'] or '–'} | {r['score']:+.3f} | {r['best_confidence']:.2f} |"
                for r in refused]
    errors = [r for r in rows if r["error"]]
    if errors:
        out += ["", "Pairs that could not be scored:", ""] + [f"- {r['pair_id']}: {r['error']}" for r in errors]
    return "\n".join(out) + "\n"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m data_scripts.truth_score", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_pair_tool_arguments(p, "pair")
    p.add_argument("--match", default="", help="only pairs whose id contains this text (e.g. nclt)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    levels = [lv.strip() for lv in args.levels.split(",") if lv.strip()]
    manifest = args.data / "pairs.csv"
    if not levels:
        print(f"truth_score: error: --levels {args.levels!r} names no level", file=sys.stderr)
        return 2
    try:
        config, config_dict = resolve_config(args.config, args.overrides)
        tasks = [t for t in load_tasks(manifest, levels, False, config, config_dict) if args.match in t["pair_id"]]
    except BenchError as err:
        print(f"truth_score: error: {err}", file=sys.stderr)
        return 2
    if not tasks:
        print(f"truth_score: error: {manifest}: no pair of level(s) {args.levels} matches {args.match!r}",
              file=sys.stderr)
        return 2
    with multiprocessing.get_context("spawn").Pool(max(1, args.jobs)) as pool:
        rows = list(pool.imap(truth_row, tasks))
    for row in rows:
        if row["error"]:  # in the report too; on stderr so that a run's log shows it (as settle_margin)
            print(f"truth_score: error: {row['pair_id']}: {row['error']}", file=sys.stderr)
    report = render(rows, args.data, config.engine.min_confidence)
    write_tool_outputs(report, rows, args.out, args.csv, CSV_FIELDS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
