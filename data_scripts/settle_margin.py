"""How close the search's wrong candidates come to its early-stop thresholds (``outer.settle_alone``,
``outer.settle_full``).

The search stops after an overlap hypothesis whose candidate reaches surface agreement
``outer.settle_alone`` (default 0.52), or after the full-overlap hypothesis (the plan's first) when its
candidate reaches ``outer.settle_full``: the remaining hypotheses, and the rivals they would have
produced for the verdict, are skipped. That is only safe if no *wrong* candidate reaches the threshold.
This tool runs every hypothesis of the plan on every pair (``settle_alone`` and ``settle_full`` 1,
``settle_support`` 0;
each hypothesis keeps its own seeded generator, so its candidate is the one a normal run would get),
scores each candidate against the ground truth with the config's success thresholds, and reports:

* per level, the best agreement of a wrong-basin candidate, of an *imprecise* one (wrong by the success
  thresholds but under 10 degrees off: the right basin, which the verdict's ICP refines) and of a right
  one, each with its pair, hypothesis and rotation error;
* per threshold, how many candidates of each kind reach it, and at what kind of candidate the search
  would stop if ``settle_alone`` were that threshold, ``settle_full`` off (the pairs stopped at a
  wrong-basin candidate are listed: the ones that matter);
* the same for ``settle_full`` thresholds, with ``settle_alone`` at the config's value.

Re-run it whenever the search or its agreement changes, before touching either threshold. Usage::

    python -m data_scripts.settle_margin --data bench/work/data-seed1 -j 2 --out /tmp/margin-s1.md
    python -m data_scripts.settle_margin --data bench/work/data-seed2 --levels hard,part --csv /tmp/c.csv

Tune on the tuning sets (seeds 1 and 2), never on the report set (seed 0).
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing
import sys
from pathlib import Path
from typing import Any

from data_scripts.bench_engine import (
    BenchError,
    add_pair_tool_arguments,
    load_tasks,
    resolve_config,
    write_tool_outputs,
)

THRESHOLDS = (0.4, 0.45, 0.5, 0.52, 0.55, 0.6)
FULL_THRESHOLDS = (0.35, 0.4, 0.42, 0.45, 0.48, 0.5)
#: a wrong candidate closer than this to the truth (degrees) is "imprecise": right basin, refinement's job
IMPRECISE_DEG = 10.0
NEVER_SETTLE = ["engine.outer.settle_alone=1.0", "engine.outer.settle_full=1.0", "engine.outer.settle_support=0"]


def candidates_of(task: dict[str, Any]) -> list[dict[str, Any]]:
    """Every overlap hypothesis' candidate of one pair, in plan order, scored against the ground truth."""
    import numpy as np

    from gctr_cli.config import config_from_dict
    from gctr_cli.engine.gctr import run_search
    from gctr_cli.engine.prepare import StageTimer
    from gctr_cli.engine.preprocess import DegenerateCloudError, denormalise
    from gctr_cli.io import load_point_cloud, read_matrix
    from gctr_cli.metrics import transform_errors

    config = config_from_dict(task["config"], "<settle_margin config>")
    source, target = load_point_cloud(task["source"]), load_point_cloud(task["target"])
    T_gt = read_matrix(task["gt"])
    # the engine's own stages 1-4 with the same seed as `register` (the verdict is not needed here)
    try:
        run = run_search(source, target, config.engine, int(task["seed"]), StageTimer({}))
    except DegenerateCloudError:  # register gives up on such a pair before any candidate
        return []
    ns, nt, candidates = run.norm_source, run.norm_target, run.candidates
    diagonal = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0)))
    s = config.success
    rows = []
    for order, cand in enumerate(candidates):
        err = transform_errors(denormalise(cand.transform, ns, nt), T_gt, diagonal,
                               source_centre=source.mean(axis=0))
        rows.append({"pair_id": task["pair_id"], "level": task["level"], "order": order,
                     "overlap": cand.overlap, "agreement": cand.agreement.score,
                     "right": err.success(s.rotation_deg, s.translation_rel, s.scale),
                     "rot_err_deg": err.rot_err_deg})
    return rows


def candidates_or_error(task: dict[str, Any]) -> tuple[list[dict[str, Any]], str]:
    """:func:`candidates_of`, or no rows and a message naming the file when a cloud or the ground-truth
    matrix cannot be read: one broken pair must not stop the run."""
    from gctr_cli.io import MatrixError, PointCloudError

    try:
        return candidates_of(task), ""
    except (PointCloudError, MatrixError) as err:  # the message names the file
        return [], f"{task['pair_id']}: {err}"


def _best(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    return max(rows, key=lambda r: r["agreement"]) if rows else None


def kind(row: dict[str, Any]) -> str:
    """``right``; ``imprecise`` (wrong, but within ``IMPRECISE_DEG`` of the truth: the right basin, which
    the verdict's ICP refines); or ``wrong basin``."""
    if row["right"]:
        return "right"
    return "imprecise" if row["rot_err_deg"] < IMPRECISE_DEG else "wrong basin"


def settling_candidate(pair_rows: list[dict[str, Any]], threshold: float,
                       full: float = 1.0) -> dict[str, Any] | None:
    """The best candidate so far at the first hypothesis (in plan order) where it reaches ``threshold``
    (``full`` when that candidate is the full-overlap hypothesis', as the engine's ``settled``): the
    answer's basin if ``settle_alone`` were ``threshold`` and ``settle_full`` ``full``; ``None`` if no
    candidate reaches it."""
    from gctr_cli.engine.search import settle_threshold

    best: dict[str, Any] | None = None
    for r in sorted(pair_rows, key=lambda r: r["order"]):
        if best is None or r["agreement"] > best["agreement"]:
            best = r
        if best["agreement"] >= settle_threshold(best["overlap"], threshold, full):
            return best
    return None


def render(rows: list[dict[str, Any]], levels: list[str], data: Path, n_pairs: int, alone: float,
           errors: list[str] | None = None) -> str:
    """The markdown report (see the module docstring); ``alone`` is the ``settle_alone`` of the
    ``settle_full`` table (a row ``full t`` stops the full-overlap hypothesis at min(t, alone)); ``errors``
    lists the pairs that could not be read."""
    def fmt(r: dict[str, Any] | None) -> str:
        if r is None:
            return "–"
        return f"{r['agreement']:.3f} ({r['pair_id']}, hypothesis {r['order'] + 1}, {r['rot_err_deg']:.1f}°)"

    kinds = ("wrong basin", "imprecise", "right")
    by_pair: dict[str, list[dict[str, Any]]] = {}
    for r in sorted(rows, key=lambda r: (r["pair_id"], r["order"])):
        by_pair.setdefault(r["pair_id"], []).append(r)
    out = [f"# Settle margin: {data} ({n_pairs} pairs, every overlap hypothesis run)", "",
           f"Best agreement per kind of candidate (imprecise: wrong, but within {IMPRECISE_DEG:g}° of the truth).",
           "", "| level | pairs | candidates | right | best wrong-basin | best imprecise | best right |",
           "|---|---:|---:|---:|---|---|---|"]
    for level in [*levels, "all"]:
        sel = [r for r in rows if level == "all" or r["level"] == level]
        best = {k: fmt(_best([r for r in sel if kind(r) == k])) for k in kinds}
        out.append(f"| {level} | {len({r['pair_id'] for r in sel})} | {len(sel)} | {sum(r['right'] for r in sel)} | "
                   f"{best['wrong basin']} | {best['imprecise']} | {best['right']} |")
    out += ["", "Per threshold t: candidates of any hypothesis with agreement ≥ t, and where the search would stop "
                "with `settle_alone` = t and `settle_full` off (after the first hypothesis whose best candidate "
                "so far reaches t; "
                "`settle_support` ignored), by the kind of that best candidate; pairs that never reach t run every "
                "hypothesis.", "",
            "| t | wrong-basin candidates | imprecise candidates | stops at: right | imprecise | wrong basin |",
            "|---:|---:|---:|---:|---:|---:|"]

    def count(sel: list[dict[str, Any]], k: str, t: float) -> int:
        return sum(kind(r) == k and r["agreement"] >= t for r in sel)

    def stops_row(label: str, sel: list[dict[str, Any]], t: float, alone_t: float, full_t: float) -> str:
        stops = [stop for stop in (settling_candidate(rows_of, alone_t, full_t) for rows_of in by_pair.values())
                 if stop]
        wrong = [f"{r['pair_id']} ({r['agreement']:.3f}, hypothesis {r['order'] + 1}, {r['rot_err_deg']:.1f}°)"
                 for r in stops if kind(r) == "wrong basin"]
        return (f"| {label} | {count(sel, 'wrong basin', t)} | {count(sel, 'imprecise', t)} | "
                f"{sum(kind(r) == 'right' for r in stops)} | {sum(kind(r) == 'imprecise' for r in stops)} | "
                f"{len(wrong)}{': ' + ', '.join(wrong) if wrong else ''} |")

    out += [stops_row(f"{t}", rows, t, t, 1.0) for t in THRESHOLDS]
    full_rows = [r for r in rows if r["overlap"] >= 1.0]
    out += ["", f"Per threshold t of `settle_full` (the full-overlap hypothesis settles the search at t; "
                f"`settle_alone` = {alone}): candidates of the full-overlap hypothesis with agreement ≥ t, and "
                "where the search would stop.", "",
            "| settle_full | wrong-basin candidates | imprecise candidates | stops at: right | imprecise "
            "| wrong basin |",
            "|---|---:|---:|---:|---:|---:|"]
    out += [stops_row(f"full {t}", full_rows, t, alone, t) for t in FULL_THRESHOLDS]
    if errors:
        out += ["", "Pairs that could not be read:", ""] + [f"- {e}" for e in errors]
    return "\n".join(out) + "\n"


def read_rows(path: Path) -> list[dict[str, Any]]:
    """Candidate rows from a ``--csv`` file, with their types back."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [{"pair_id": r["pair_id"], "level": r["level"], "order": int(r["order"]),
                 "overlap": float(r["overlap"]), "agreement": float(r["agreement"]), "right": r["right"] == "True",
                 "rot_err_deg": float(r["rot_err_deg"])} for r in csv.DictReader(fh)]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m data_scripts.settle_margin", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_pair_tool_arguments(p, "candidate")
    p.add_argument("--from-csv", type=Path, help="render the report from the --csv of an earlier run (no engine run)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    levels = [lv.strip() for lv in args.levels.split(",") if lv.strip()]
    try:
        alone = resolve_config(args.config, args.overrides)[0].engine.outer.settle_alone
        config, config_dict = resolve_config(args.config, [*args.overrides, *NEVER_SETTLE])
        tasks = load_tasks(args.data / "pairs.csv", levels, False, config, config_dict,
                           check_files=not args.from_csv)  # --from-csv renders saved rows: no cloud is read
    except BenchError as err:
        print(f"settle_margin: error: {err}", file=sys.stderr)
        return 2
    errors: list[str] = []
    if args.from_csv:
        rows = read_rows(args.from_csv)
    else:
        with multiprocessing.get_context("spawn").Pool(max(1, args.jobs)) as pool:
            results = list(pool.imap(candidates_or_error, tasks))
        rows = [r for pair_rows, _ in results for r in pair_rows]
        errors = [e for _, e in results if e]
        for e in errors:
            print(f"settle_margin: error: {e}", file=sys.stderr)
    report = render(rows, levels, args.data, len(tasks), alone, errors)
    write_tool_outputs(report, rows, args.out, args.csv, list(rows[0]) if rows else ["pair_id"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
