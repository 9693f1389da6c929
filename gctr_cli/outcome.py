"""The outcome record of one pair and the output rows it becomes (``transforms.csv``, ``tm_errors.csv``).

The bottom of the batch layer: no gctr imports, numpy only. Every other batch module (running one
pair, the executors, the output folder, the summary) speaks in :class:`PairOutcome` and the column
tuples defined here.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

__all__ = [
    "ERRORS_COLUMNS",
    "MATRIX_COLUMNS",
    "PairOutcome",
    "SNAPSHOT_LOGGER",
    "TRANSFORMS_COLUMNS",
    "exc_message",
    "failed_outcome",
    "with_warnings",
]

MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(4) for j in range(4))
TRANSFORMS_COLUMNS = (
    ("pair_id", "source", "target", "status", "message", "scale")
    + MATRIX_COLUMNS
    + ("fitness", "confidence", "inlier_rmse", "runtime_s", "seed")
)
ERRORS_COLUMNS = ("pair_id", "rot_err_deg", "trans_err", "trans_err_rel", "scale_err", "tm_err", "success")

#: logger of snapshot problems: reported as batch warnings, never in the pair's message
SNAPSHOT_LOGGER = "gctr_cli.snapshots"


def fmt_number(x: float | None) -> str:
    """Full-precision text of a number (``repr``, round-trips exactly); empty for None."""
    return "" if x is None else repr(float(x))


def fmt_optional(x: float | None) -> str:
    """Like :func:`fmt_number`, but also empty for NaN (a value the method does not compute)."""
    return "" if x is None or math.isnan(float(x)) else repr(float(x))


def one_line(message: str) -> str:
    """Messages go into one CSV cell on one physical line."""
    return re.sub(r"\s*[\r\n]+\s*", " | ", str(message).strip())


def exc_message(exc: BaseException) -> str:
    """``Type: text`` of an exception (just ``Type`` when it has no text)."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@dataclass(frozen=True)
class PairOutcome:
    """What happened to one pair; carries its ``transforms.csv`` and ``tm_errors.csv`` rows.

    ``failure`` says where a failed pair failed: ``"input"`` (a point cloud could not be used),
    ``"ground_truth"`` (the gt file is missing, malformed or not a similarity), ``"register"`` (the
    engine raised or reported failure), ``"worker"`` (the worker process died), ``"timeout"`` or
    ``"output"`` (its result could not be written to the output folder). ``transform`` is set only
    for ``ok`` pairs; ``errors``/``success`` only when the pair also has ground truth.
    ``confidence`` is the engine's confidence in its answer (NaN or None when the method has none).
    """

    pair_id: str
    source: str
    target: str
    status: str
    message: str
    seed: int
    runtime_s: float
    transform: np.ndarray | None = None
    scale: float | None = None
    fitness: float | None = None
    inlier_rmse: float | None = None
    errors: Any = None  # gctr_cli.metrics.TransformErrors
    success: bool | None = None
    failure: str = ""
    warnings: tuple[str, ...] = ()
    confidence: float | None = None
    #: PNG bytes of the pair's snapshot (``run_pair(..., snapshot=True)``); written by the batch process
    snapshot_png: bytes | None = field(default=None, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def transforms_row(self) -> list[str]:
        cells = [""] * 16 if self.transform is None else [fmt_number(v) for v in np.asarray(self.transform).ravel()]
        return [
            self.pair_id,
            self.source,
            self.target,
            self.status,
            one_line(self.message),
            fmt_number(self.scale) if self.transform is not None else "",
            *cells,
            fmt_number(self.fitness),
            fmt_optional(self.confidence),
            fmt_optional(self.inlier_rmse),  # NaN without inliers
            fmt_number(self.runtime_s),
            str(self.seed),
        ]

    @property
    def errors_row(self) -> list[str] | None:
        if self.errors is None or self.transform is None:
            return None
        e = self.errors
        return [
            self.pair_id,
            fmt_number(e.rot_err_deg),
            fmt_number(e.trans_err),
            fmt_number(e.trans_err_rel),
            fmt_number(e.scale_err),
            fmt_number(e.tm_err),
            "true" if self.success else "false",
        ]


def failed_outcome(spec: Any, seed: int, message: str, failure: str, runtime_s: float, **kw: Any) -> PairOutcome:
    """A failed outcome of the pair ``spec`` (a :class:`gctr_cli.manifest.PairSpec`)."""
    return PairOutcome(
        pair_id=spec.pair_id,
        source=str(spec.source),
        target=str(spec.target),
        status="failed",
        message=message,
        seed=seed,
        runtime_s=runtime_s,
        failure=failure,
        **kw,
    )


def with_warnings(outcome: PairOutcome, records: list[tuple[str, str]]) -> PairOutcome:
    """Attach the ``(logger, message)`` warnings logged while the pair ran; gctr's own (e.g.
    "dropped 5 non-finite points") also go into the message, snapshot problems do not."""
    ours = [msg for name, msg in records if name.startswith("gctr_cli") and name != SNAPSHOT_LOGGER]
    message = "; ".join([m for m in [outcome.message] if m] + [f"warning: {m}" for m in ours])
    return replace(outcome, warnings=tuple(msg for _, msg in records), message=message)
