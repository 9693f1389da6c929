"""Stage 4b: the search again from each half of the source, when the first search left the answer in doubt.

Two scans that overlap by 25–50% usually share a *slab* at one end of each (two crops sliding along a
direction, two fragments of a room): thin along the direction they slide and as wide as the clouds
across it. The overlap hypotheses of :mod:`~gctr_cli.engine.search` draw their triangles in compact
regions, and few of them fit entirely into such a slab, so on these pairs no hypothesis finds the truth
(measured: 16–17 of the 18–19 failed low-overlap pairs of each tuning set had no right candidate at all).
Run from the source's half that contains the slab — the source split at its median along one of its
three principal axes — the same search finds it: on the 19 failed low-overlap pairs of tuning seed 1,
one of the six halves gave the right transform on 17 (``docs/how-it-works.md``).

:func:`half_candidates` runs the overlap search (the whole plan) on each half and returns the candidates
in the coordinates of the whole source, their surface agreement re-measured on the whole clouds, so that
the verdict compares them with the first search's on equal terms. It costs about six searches, so the
engine runs it only when the first verdict's confidence is below ``source_halves_below``.
"""

from __future__ import annotations

import time

import numpy as np

from gctr_cli.config import EngineConfig
from gctr_cli.engine.prepare import PreparedCloud, StageTimer, prepare_cloud
from gctr_cli.engine.preprocess import normalise
from gctr_cli.engine.search import Candidate, search, search_plan
from gctr_cli.engine.verdict import Agreement, surface_agreement

#: spawn keys of the halves' generators (the first search spawns keys 0, 1, 2, ... of the pair's seed)
HALF_SPAWN_KEY = 1000


def source_halves(points: np.ndarray) -> list[np.ndarray]:
    """Six boolean masks over ``points`` (N, 3): each side of the median along each principal axis."""
    centred = points - np.median(points, axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    masks = []
    for a in range(3):
        proj = centred @ axes[:, a]
        cut = np.median(proj)
        masks += [proj <= cut, proj >= cut]
    return masks


def _rescored(T: np.ndarray, to_whole: np.ndarray, src: PreparedCloud, tgt: PreparedCloud,
              cfg: EngineConfig) -> tuple[np.ndarray, Agreement]:
    """A half's transform in the whole source's normalised coordinates, with its agreement on the whole clouds."""
    T_whole = T @ to_whole
    return T_whole, surface_agreement(T_whole, src.surface, tgt.surface, cfg.inlier_distance_ratio,
                                      cfg.verdict.max_normal_angle_deg)


def half_candidates(source_n: np.ndarray, src: PreparedCloud, tgt: PreparedCloud, bounds_n: tuple[float, float],
                    cfg: EngineConfig, seed: int, timer: StageTimer) -> list[Candidate]:
    """The overlap search's candidates from each half of the source (:func:`source_halves`).

    ``source_n`` is the whole source in normalised coordinates (what ``src`` was prepared from),
    ``bounds_n`` the scale bounds in those units; the candidates map the whole normalised source onto
    the normalised target, like the first search's.
    """
    plan = search_plan(cfg)
    out: list[Candidate] = []
    for k, mask in enumerate(source_halves(source_n)):
        rng_src, *rng_plan = [np.random.default_rng(s) for s in
                              np.random.SeedSequence(seed, spawn_key=(HALF_SPAWN_KEY + k,)).spawn(1 + len(plan))]
        half = normalise(source_n[mask])
        prepared = prepare_cloud(half.points, cfg, rng_src, timer)
        if len(prepared.salient) < 4:
            continue
        # half-normalised x_h = (x - centre) / size: a transform T_h of the half is T_h @ to_whole on the whole
        to_whole = np.linalg.inv(half.to_original())
        bounds_h = (bounds_n[0] * half.size, bounds_n[1] * half.size)
        for c in search(prepared, tgt, plan, rng_plan, bounds_h, cfg, timer):
            t = time.perf_counter()
            T, agreement = _rescored(c.transform, to_whole, src, tgt, cfg)
            alternatives = tuple(_rescored(T_alt, to_whole, src, tgt, cfg) for T_alt, _ in c.alternatives)
            timer.add("scoring", t)
            out.append(Candidate(transform=T, n_inliers=c.n_inliers, iterations=c.iterations, agreement=agreement,
                                 overlap=c.overlap, alternatives=alternatives))
    return out
