"""How much true signal the triangle tensor of each overlap hypothesis carries, measured against ground truth.

A developer's tool for work on the search (stages 3-4). For each overlap hypothesis of the engine's plan
it draws the hypothesis' triangles as the engine does (same functions, same config; a fresh seeded draw),
matches them in descriptor space, and counts, with the ground truth mapping the source's salient points
onto the target's:

* ``inside``: source triangles whose three vertices all have a target salient point within
  ``--tolerance`` (normalised target units) under the truth — triangles that *could* match;
* ``sampled``: source triangles whose true counterpart (a target triangle with every vertex within the
  tolerance of the mapped source vertex, in the same order) is among the sampled target triangles —
  coverage of the sampling;
* ``in_knn``: source triangles whose true counterpart is among their ``tensor.knn`` descriptor
  neighbours — what the descriptor keeps of it;
* ``true_entries``: tensor entries (after the scale filter) whose three assignments are all true;
* ``median_rank``: median rank of the true counterpart among all target triangles by descriptor distance.

The power iteration can only amplify the true entries, so ``true_entries`` and ``in_knn`` are the
quantities a change to the salient points, the triangle sampling or the descriptor should raise. They
vary far less from seed to seed than end-to-end success counts (which move by about ±3 per 122 hard
pairs from the random stream alone), so a change can be judged on a dozen pairs in a minute.

Usage::

    python -m data_scripts.tensor_diagnostics --data bench/work/data-seed1 \\
        --pair part_bunny_1 --pair cross_bunny_0 [--config FILE] [--set '{"tensor": {"knn": 80}}']

(the data folder holds a ``pairs.csv`` written by ``make_benchmark generate``).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
from scipy.spatial import cKDTree

from gctr_cli.config import ConfigError, EngineConfig, config_from_dict, load_config
from gctr_cli.engine.prepare import PreparedCloud, StageTimer, prepare_cloud
from gctr_cli.engine.preprocess import normalise
from gctr_cli.engine.search import OverlapHypothesis, hypothesis_triangles, oriented, search_plan
from gctr_cli.engine.tensor import build_third_order, decode
from gctr_cli.io import load_point_cloud


@dataclass(frozen=True)
class HypothesisSignal:
    """Ground-truth statistics of one overlap hypothesis' tensor (see the module docstring)."""

    name: str
    n_source_salient: int
    n_target_salient: int
    source_triangles: int
    target_triangles: int
    inside: int
    sampled: int
    in_knn: int
    true_entries: int
    entries: int
    median_rank: float


def hypothesis_signal(src: PreparedCloud, tgt: PreparedCloud, hypothesis: OverlapHypothesis, T_n: np.ndarray,
                      prior: tuple[float, float], cfg: EngineConfig, rng: np.random.Generator,
                      tolerance: float) -> HypothesisSignal:
    """Draw one hypothesis' triangles and tensor as the engine does and count the true signal in it.
    ``src``, ``tgt``, ``hypothesis``, ``prior`` and ``T_n`` are in the order the search runs them
    (:func:`gctr_cli.engine.search.oriented`)."""
    S, Q = src.salient, tgt.salient
    m = hypothesis_triangles(src, tgt, hypothesis, prior, cfg, rng)
    src_tri, tgt_tri, f_src, f_tgt = m.src_tri, m.tgt_tri, m.f_src, m.f_tgt
    H = build_third_order(len(S), src_tri, f_src, len(Q), tgt_tri, f_tgt, cfg.tensor.knn, cfg.tensor.sigma,
                          eps=cfg.tensor.knn_eps, size_filter=m.size_filter)

    moved = S @ T_n[:3, :3].T + T_n[:3, 3]
    partner = np.linalg.norm(moved[:, None] - Q[None], axis=2) < tolerance  # (n1, n2) true assignments
    true_entries = 0
    if len(H.values):
        def ok(entry: np.ndarray) -> np.ndarray:
            return partner[decode(entry, H.n2)]
        true_entries = int(np.count_nonzero(ok(H.a) & ok(H.b) & ok(H.c)))
    inside = sampled = in_knn = 0
    ranks: list[int] = []
    if len(src_tri) and len(tgt_tri):
        inside = int(np.count_nonzero(partner[src_tri].any(axis=2).all(axis=1)))
        # counterpart[i, j]: target triangle j matches source triangle i vertex by vertex
        counterpart = np.ones((len(src_tri), len(tgt_tri)), dtype=bool)
        for v in range(3):
            counterpart &= partner[src_tri[:, v]][:, tgt_tri[:, v]]
        has = counterpart.any(axis=1)
        sampled = int(np.count_nonzero(has))
        k = min(cfg.tensor.knn, len(tgt_tri))
        _, idx = cKDTree(f_tgt).query(f_src, k=k, eps=cfg.tensor.knn_eps)
        idx = np.asarray(idx).reshape(len(src_tri), k)
        in_knn = int(np.count_nonzero(np.take_along_axis(counterpart, idx, axis=1).any(axis=1)))
        for i in np.flatnonzero(has):
            d = np.linalg.norm(f_tgt - f_src[i], axis=1)
            ranks.append(int(np.count_nonzero(d < d[counterpart[i]].min())))
    return HypothesisSignal(hypothesis.name, len(S), len(Q), len(src_tri), len(tgt_tri), inside, sampled, in_knn,
                            true_entries, len(H.values), float(np.median(ranks)) if ranks else float("nan"))


def pair_signal(source: np.ndarray, target: np.ndarray, T_gt: np.ndarray, cfg: EngineConfig, seed: int = 0,
                tolerance: float = 0.06) -> list[HypothesisSignal]:
    """:func:`hypothesis_signal` for every overlap hypothesis of the engine's plan on one pair."""
    root = np.random.SeedSequence(seed)
    plan = search_plan(cfg)
    rng_src, rng_tgt, *rng_hyp = [np.random.default_rng(s) for s in root.spawn(2 + len(plan))]
    ns, nt = normalise(source), normalise(target)
    timer = StageTimer({})
    src = prepare_cloud(ns.points, cfg, rng_src, timer)
    tgt = prepare_cloud(nt.points, cfg, rng_tgt, timer)
    ratio = ns.size / nt.size
    bounds_n = (cfg.scale_bounds[0] * ratio, cfg.scale_bounds[1] * ratio)
    T_n = np.linalg.inv(nt.to_original()) @ T_gt @ ns.to_original()  # truth in normalised coordinates
    out = []
    for h, rng in zip(plan, rng_hyp):
        prior = h.scale_prior(bounds_n)
        if prior[0] >= prior[1]:
            continue
        a, b, run_as, run_prior, swapped = oriented(src, tgt, h, prior)
        truth = np.linalg.inv(T_n) if swapped else T_n
        out.append(hypothesis_signal(a, b, run_as, truth, run_prior, cfg, rng, tolerance))
    return out


def format_table(pair_id: str, rows: list[HypothesisSignal]) -> str:
    """A markdown table of one pair's hypotheses."""
    lines = [f"### {pair_id}", "",
             "| hypothesis | salient src/tgt | triangles src/tgt | inside | sampled | in_knn | true entries | "
             "median rank |", "|---|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r.name} | {r.n_source_salient}/{r.n_target_salient} | {r.source_triangles}/"
                     f"{r.target_triangles} | {r.inside} | {r.sampled} | {r.in_knn} | {r.true_entries} of "
                     f"{r.entries} | {r.median_rank:.0f} |")
    return "\n".join(lines)


def _merged(base: dict, extra: dict) -> dict:
    """``base`` with ``extra``'s keys replaced, nested sections merged key by key."""
    out = dict(base)
    for key, value in extra.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", "data", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True,
              help="folder with a pairs.csv written by make_benchmark generate")
@click.option("--pair", "pairs", multiple=True, required=True, help="pair id (repeatable)")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="YAML config (default: the built-in defaults)")
@click.option("--set", "overrides", default="{}", show_default=True,
              help="JSON object of engine overrides, e.g. '{\"tensor\": {\"knn\": 80}}'")
@click.option("--tolerance", type=float, default=0.06, show_default=True,
              help="a salient point's true partner lies within this distance (normalised target units)")
@click.option("--seed", type=int, default=0, show_default=True)
def main(data: Path, pairs: tuple[str, ...], config_path: Path | None, overrides: str, tolerance: float,
         seed: int) -> None:
    """Print, per pair and overlap hypothesis, how much true signal the tensor carries (see the module doc)."""
    try:
        base = load_config(config_path) if config_path else config_from_dict({})
    except ConfigError as err:
        raise click.BadParameter(str(err), param_hint="--config") from None
    try:
        extra = json.loads(overrides)
    except json.JSONDecodeError as err:
        raise click.BadParameter(f"not a JSON object: {err}", param_hint="--set") from err
    if not isinstance(extra, dict):
        raise click.BadParameter("must be a JSON object", param_hint="--set")
    try:
        cfg = config_from_dict({**base.model_dump(), "engine": _merged(base.engine.model_dump(), extra)},
                               f"{config_path or 'the built-in defaults'} with --set {overrides}").engine
    except ConfigError as err:
        raise click.BadParameter(str(err), param_hint="--set") from None
    with open(data / "pairs.csv", newline="") as fh:
        rows = {r["pair_id"]: r for r in csv.DictReader(fh)}
    totals = np.zeros(3, dtype=int)
    for pid in pairs:
        if pid not in rows:
            raise click.BadParameter(f"pair {pid!r} is not in {data / 'pairs.csv'}", param_hint="--pair")
        row = rows[pid]
        source = np.asarray(load_point_cloud(data / row["source"]), dtype=float)
        target = np.asarray(load_point_cloud(data / row["target"]), dtype=float)
        T_gt = np.loadtxt(data / row["gt"])
        signal = pair_signal(source, target, T_gt, cfg, seed=seed, tolerance=tolerance)
        click.echo(format_table(pid, signal) + "\n")
        totals += [sum(r.sampled for r in signal), sum(r.in_knn for r in signal), sum(r.true_entries for r in signal)]
    click.echo(f"total over {len(pairs)} pairs: sampled {totals[0]}, in_knn {totals[1]}, true entries {totals[2]}")


if __name__ == "__main__":
    main()
