"""The summary of a batch: totals and median errors over the pairs of a manifest, from the output files.

Read by the CLI (the lines it prints) and by :mod:`gctr_cli.report`; computed from ``transforms.csv``
and ``tm_errors.csv`` alone, so after ``--resume`` it covers the pairs of earlier runs too.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gctr_cli.outcome import ERRORS_COLUMNS, TRANSFORMS_COLUMNS
from gctr_cli.outdir import ERRORS_FILE, TRANSFORMS_FILE, read_rows

__all__ = ["NO_RESULT", "BatchSummary", "summarize"]

#: the message of a manifest pair without a row (a run stopped before it)
NO_RESULT = "no result recorded"


@dataclass(frozen=True)
class BatchSummary:
    """Totals over all pairs of the manifest (including pairs finished by an earlier, resumed run).

    ``success_rate`` is over pairs with ground truth (a failed pair with gt counts as no success);
    ``None`` when no pair has ground truth. Medians are over the ``tm_errors.csv`` rows.
    """

    outdir: Path
    n_pairs: int
    n_ok: int
    n_failed: int
    n_run: int
    n_resumed: int
    n_gt: int
    n_success: int
    success_rate: float | None
    median_rot_err_deg: float | None
    median_trans_err: float | None
    median_trans_err_rel: float | None
    median_scale_err: float | None
    median_tm_err: float | None
    wall_time_s: float
    failures: tuple[tuple[str, str], ...] = field(default_factory=tuple)
    gt_ids: tuple[str, ...] = ()  # the pairs with ground truth (a failed one among them is no success)
    #: ``ok`` pairs that are no success by their ground truth: (pair id, rotation error in degrees, translation
    #: error / target diagonal, scale error), the wrong answers a CI log must name
    misses: tuple[tuple[str, float, float, float], ...] = ()
    pair_ids: tuple[str, ...] = ()  # the manifest's pairs, in its order
    report_written: bool = False  # OUTDIR/report.html was written of this summary (set by the batch)

    @property
    def all_ok(self) -> bool:
        return self.n_failed == 0


def _median(values: list[float]) -> float | None:
    values = [v for v in values if not math.isnan(v)]
    return float(statistics.median(values)) if values else None


def summarize(pairs: Sequence[Any], outdir: str | Path, *, wall_time_s: float = 0.0, n_run: int = 0,
              n_resumed: int = 0) -> BatchSummary:
    """Summarise the output files of ``outdir`` for the pairs of a manifest."""
    outdir = Path(outdir)
    rows = {r["pair_id"]: r for r in read_rows(outdir / TRANSFORMS_FILE, TRANSFORMS_COLUMNS)}
    errs = {r["pair_id"]: r for r in read_rows(outdir / ERRORS_FILE, ERRORS_COLUMNS)}
    n_ok = 0
    failures: list[tuple[str, str]] = []
    gt_ids = [p.pair_id for p in pairs if p.gt is not None]
    for p in pairs:
        row = rows.get(p.pair_id)
        if row is None:
            failures.append((p.pair_id, NO_RESULT))
        elif row["status"] == "ok":
            n_ok += 1
        else:
            failures.append((p.pair_id, row["message"]))
    err_rows = [errs[i] for i in gt_ids if i in errs and rows.get(i, {}).get("status") == "ok"]
    n_success = sum(r["success"] == "true" for r in err_rows)
    misses = tuple((r["pair_id"], float(r["rot_err_deg"]), float(r["trans_err_rel"]), float(r["scale_err"]))
                   for r in err_rows if r["success"] != "true")

    def med(key: str) -> float | None:
        return _median([float(r[key]) for r in err_rows])

    return BatchSummary(
        outdir=outdir,
        n_pairs=len(pairs),
        n_ok=n_ok,
        n_failed=len(failures),
        n_run=n_run,
        n_resumed=n_resumed,
        n_gt=len(gt_ids),
        n_success=n_success,
        success_rate=(n_success / len(gt_ids)) if gt_ids else None,
        median_rot_err_deg=med("rot_err_deg"),
        median_trans_err=med("trans_err"),
        median_trans_err_rel=med("trans_err_rel"),
        median_scale_err=med("scale_err"),
        median_tm_err=med("tm_err"),
        wall_time_s=wall_time_s,
        gt_ids=tuple(gt_ids),
        failures=tuple(failures),
        misses=misses,
        pair_ids=tuple(p.pair_id for p in pairs),
    )
