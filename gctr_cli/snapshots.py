"""PNG snapshots of one pair: the two clouds before and after registration, in three orthogonal views.

Rendering is headless: matplotlib's Agg canvas is used directly (no pyplot, no display, no global
backend switch), so it works in batch workers, on cluster nodes and in CI. Each cloud is subsampled
to at most ``max_points`` points (evenly spaced indices: deterministic and cheap), so a snapshot
takes a fraction of a second and little memory whatever the size of the clouds.

Layout (``SNAPSHOT_SIZE_PX`` pixels): the top row shows the input clouds in their own coordinates
(top x-y, front x-z and side y-z views); the bottom row shows the target with the source mapped by
the estimated transform. Without a transform (a failed pair, or ``gctr show`` without ``--matrix``)
the bottom row is replaced by a note saying why. Source and target have fixed, distinct colours.
"""

from __future__ import annotations

import io
import logging
import textwrap
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gctr_cli.fsutil import atomic_write
from gctr_cli.geometry import apply

__all__ = [
    "MAX_POINTS",
    "SNAPSHOT_SIZE_PX",
    "SOURCE_COLOR",
    "TARGET_COLOR",
    "render_snapshot",
    "snapshot_of_outcome",
    "subsample",
    "write_png",
]

logger = logging.getLogger(__name__)

#: width, height in pixels of every snapshot
SNAPSHOT_SIZE_PX = (1200, 800)
_DPI = 100
#: points drawn per cloud and view
MAX_POINTS = 3000
SOURCE_COLOR = "#d95f02"  # orange
TARGET_COLOR = "#1f78b4"  # blue
#: (title, horizontal axis, vertical axis) of the three orthogonal views
VIEWS = (("top (x-y)", 0, 1), ("front (x-z)", 0, 2), ("side (y-z)", 1, 2))
_AXIS_NAMES = "xyz"


def subsample(points: np.ndarray | None, max_points: int = MAX_POINTS) -> np.ndarray | None:
    """At most ``max_points`` rows of ``points`` at evenly spaced indices (deterministic)."""
    if points is None:
        return None
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) > max_points > 0:
        idx = np.linspace(0, len(pts) - 1, max_points).round().astype(np.int64)
        pts = pts[idx]
    return pts


def _draw_view(ax: Any, clouds: Sequence[tuple[np.ndarray | None, str, str]], h: int, v: int) -> None:
    for pts, color, label in clouds:
        if pts is not None and len(pts):
            ax.plot(pts[:, h], pts[:, v], linestyle="none", marker="o", markersize=0.9, markeredgewidth=0,
                    color=color, alpha=0.65, label=label)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(_AXIS_NAMES[h], fontsize=8, labelpad=1)
    ax.set_ylabel(_AXIS_NAMES[v], fontsize=8, labelpad=1)
    ax.locator_params(nbins=5)
    ax.tick_params(labelsize=6, length=2, pad=1)
    ax.ticklabel_format(useOffset=True, style="sci", scilimits=(-3, 4))
    ax.xaxis.get_offset_text().set_fontsize(6)
    ax.yaxis.get_offset_text().set_fontsize(6)
    ax.grid(True, linewidth=0.3, alpha=0.5)


def render_snapshot(
    source: np.ndarray | None,
    target: np.ndarray | None,
    transform: np.ndarray | None = None,
    *,
    title: str = "",
    note: str = "",
    max_points: int = MAX_POINTS,
) -> bytes:
    """PNG bytes of a snapshot of ``source`` (orange) and ``target`` (blue).

    ``transform`` (4x4, source -> target) draws the bottom "registered" row; without it the bottom
    row shows ``note`` (e.g. why the registration failed). A cloud that is ``None`` (could not be
    loaded) is left out. ``title`` goes on top.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    src = subsample(source, max_points)
    tgt = subsample(target, max_points)

    w, h = SNAPSHOT_SIZE_PX
    fig = Figure(figsize=(w / _DPI, h / _DPI), dpi=_DPI)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 3, left=0.05, right=0.99, top=0.86, bottom=0.06, hspace=0.32, wspace=0.22)

    n_src = "not loaded" if source is None else f"{len(source):,} points"
    n_tgt = "not loaded" if target is None else f"{len(target):,} points"
    for col, (name, hx, vy) in enumerate(VIEWS):
        ax = fig.add_subplot(grid[0, col])
        _draw_view(ax, [(tgt, TARGET_COLOR, "target"), (src, SOURCE_COLOR, "source")], hx, vy)
        ax.set_title(f"input: {name}", fontsize=9)

    if transform is not None and src is not None:
        T = np.asarray(transform, dtype=np.float64)
        moved = apply(T, src)
        for col, (name, hx, vy) in enumerate(VIEWS):
            ax = fig.add_subplot(grid[1, col])
            _draw_view(ax, [(tgt, TARGET_COLOR, "target"), (moved, SOURCE_COLOR, "source")], hx, vy)
            ax.set_title(f"registered: {name}", fontsize=9)
    else:
        ax = fig.add_subplot(grid[1, :])
        ax.set_axis_off()
        text = note or "no transform: input only"
        wrapped = "\n".join(textwrap.wrap(text, 110)[:8])
        ax.text(0.5, 0.55, wrapped, ha="center", va="center", fontsize=11, color="#444444",
                transform=ax.transAxes, wrap=True)

    handles = [
        Line2D([], [], marker="o", linestyle="", color=SOURCE_COLOR, label=f"source ({n_src})"),
        Line2D([], [], marker="o", linestyle="", color=TARGET_COLOR, label=f"target ({n_tgt})"),
    ]
    fig.legend(handles=handles, loc="upper right", fontsize=9, frameon=False, ncol=2,
               bbox_to_anchor=(0.99, 0.995))
    if title:
        fig.text(0.01, 0.975, textwrap.shorten(title, 120, placeholder="..."), ha="left", va="top",
                 fontsize=11, fontweight="bold")

    buf = io.BytesIO()
    with warnings.catch_warnings():  # a pair id in a script the font lacks (CJK): boxes, not 4 warnings a pair
        warnings.filterwarnings("ignore", message="Glyph .* missing from", category=UserWarning)
        fig.savefig(buf, format="png", dpi=_DPI, metadata={"Software": None})
    return buf.getvalue()


def snapshot_of_outcome(outcome: Any, source: np.ndarray | None, target: np.ndarray | None,
                        max_points: int = MAX_POINTS) -> bytes:
    """The snapshot of a batch pair (a :class:`gctr_cli.batch.PairOutcome`) and its loaded clouds.

    An ``ok`` pair shows before and after; a failed pair shows its input and the failure message.
    """
    if outcome.ok and outcome.transform is not None:
        scale = f", scale {outcome.scale:.4g}" if outcome.scale is not None else ""
        fit = f", fitness {outcome.fitness:.3f}" if outcome.fitness is not None else ""
        title = f"{outcome.pair_id}: ok{scale}{fit}"
        return render_snapshot(source, target, outcome.transform, title=title, max_points=max_points)
    title = f"{outcome.pair_id}: failed"
    return render_snapshot(source, target, None, title=title, note=f"not registered: {outcome.message}",
                           max_points=max_points)


def write_png(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename); parents are created."""
    atomic_write(path, data)
