"""``OUTDIR/report.html``: a self-contained page summarising a batch run.

The page needs no network: CSS and the small sorting script are inline, the plots (cumulative error
distributions and the confidence-threshold trade-off) are inline SVG, and snapshot thumbnails are
relative links to ``snapshots/<pair_id>.png`` next to the report. It is built from the output files
(``transforms.csv``, ``tm_errors.csv``, ``config.yaml``), so after ``--resume`` it covers the pairs of
earlier runs too. Given the run's summary it counts the run's manifest, as the printed summary and the
exit code do, and lists the rows of other pair ids apart; without one it counts every row.

The pairs table sorts on a click on a column header (again: reverse). The page also honours a URL
fragment, e.g. ``report.html#sort=-rot_err_deg&status=failed`` (sort by rotation error, descending,
show failed pairs only), which makes a view shareable and scriptable; clicking updates it.
"""

from __future__ import annotations

import csv
import datetime as _dt
import html
import math
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any
from urllib.parse import quote

from gctr_cli.fsutil import atomic_write
from gctr_cli.io.errors import escaped

__all__ = ["COLUMNS", "render_report", "write_report"]

#: (key, header, type) of the pairs table; ``num`` columns sort numerically, empty cells last
COLUMNS: tuple[tuple[str, str, str, str], ...] = (
    ("pair_id", "pair", "text", "pair id (hover a cell for the file paths and the seed)"),
    ("status", "status", "text", "ok or failed"),
    ("message", "message", "text", "why a pair failed, or warnings"),
    ("rot_err_deg", "rot. err (°)", "num", "rotation error: geodesic angle to the ground truth, degrees"),
    ("trans_err_rel", "trans. err (× diag)", "num", "translation error relative to the target's bounding-box diagonal"),
    ("scale_err", "scale err", "num", "|s_est / s_gt - 1|"),
    ("tm_err", "TM err", "num", "Frobenius norm of T_est - T_gt: in the data's units and growing with the "
     "coordinates' distance from the origin, so compare it only between pairs of the same data"),
    ("success", "success", "text", "all errors below the success thresholds"),
    ("fitness", "fitness", "num", "fraction of source points with a target point within the inlier distance"),
    ("confidence", "confidence", "num", "how strongly the data single out the transform (0..1): its lead over "
     "the best distinct alternative; it says which alignment, not how precise; empty when the method computes none"),
    ("scale", "scale", "num", "estimated scale s"),
    ("runtime_s", "time (s)", "num", "registration time of the pair, seconds"),
)

_CSS = """
:root { --ok: #1a7f37; --bad: #c62828; --muted: #666; --line: #d8dde3; --head: #f3f5f7; }
* { box-sizing: border-box; }
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "Liberation Sans", sans-serif;
       margin: 0; color: #1b1f23; background: #fff; }
header { padding: 16px 24px 8px; border-bottom: 1px solid var(--line); }
h1 { font-size: 22px; margin: 0 0 4px; }
h2 { font-size: 17px; margin: 24px 0 8px; }
.meta { color: var(--muted); margin: 0; word-break: break-all; }
main { padding: 0 24px 32px; }
.cards { display: flex; flex-wrap: wrap; gap: 12px; margin-top: 16px; }
.card { border: 1px solid var(--line); border-radius: 6px; padding: 10px 14px; min-width: 150px; }
.card .v { font-size: 22px; font-weight: 600; }
.card .k { color: var(--muted); font-size: 12px; }
.card.bad .v { color: var(--bad); } .card.good .v { color: var(--ok); }
table.kv td { padding: 2px 16px 2px 0; vertical-align: top; }
table.kv td:first-child { color: var(--muted); white-space: nowrap; }
figure { margin: 8px 0; }
.plots { display: flex; flex-wrap: wrap; gap: 8px; }
.plots svg { font-family: inherit; fill: #1b1f23; max-width: 100%; height: auto; }
figcaption { color: var(--muted); font-size: 12px; }
.controls { margin: 8px 0; display: flex; gap: 16px; align-items: center; flex-wrap: wrap; }
.scroll { overflow-x: auto; }
#pairs { border-collapse: collapse; width: 100%; font-size: 13px; }
#pairs th, #pairs td { border-bottom: 1px solid var(--line); padding: 4px 6px; text-align: left;
  vertical-align: middle; }
#pairs th { background: var(--head); position: sticky; top: 0; cursor: pointer; user-select: none;
  white-space: nowrap; }
#pairs th.nosort { cursor: default; }
#pairs th[data-key]::after { content: " \\2195"; color: #aaa; font-size: 11px; }
#pairs th[aria-sort=ascending]::after { content: " \\25B2"; color: #333; }
#pairs th[aria-sort=descending]::after { content: " \\25BC"; color: #333; }
#pairs td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
#pairs td.msg { min-width: 150px; max-width: 280px; overflow-wrap: anywhere; }
#pairs tr.failed td { background: #fff5f5; }
#pairs tr.hidden { display: none; }
.st { font-weight: 600; } .st.ok { color: var(--ok); } .st.failed { color: var(--bad); }
.thumb img { display: block; width: 108px; height: 72px; object-fit: contain; border: 1px solid var(--line);
             background: #fff; }
.none { color: #aaa; }
footer { color: var(--muted); font-size: 12px; padding: 12px 24px; border-top: 1px solid var(--line); }
"""

_JS = """
(function () {
  var table = document.getElementById('pairs');
  if (!table) return;
  var tbody = table.tBodies[0];
  var heads = table.tHead.rows[0].cells;
  var filter = document.getElementById('status-filter');
  var shown = document.getElementById('shown');
  Array.prototype.forEach.call(tbody.rows, function (r, i) { r.setAttribute('data-i', i); });

  function value(row, i, num) {
    var c = row.cells[i];
    var v = c.hasAttribute('data-v') ? c.getAttribute('data-v') : c.textContent;
    if (v === '') return null;
    if (!num) return v.toLowerCase();
    var x = parseFloat(v);
    return isNaN(x) ? null : x;
  }
  function sortBy(key, desc) {
    var idx = -1, num = false;
    for (var i = 0; i < heads.length; i++) {
      heads[i].removeAttribute('aria-sort');
      if (heads[i].getAttribute('data-key') === key) { idx = i; num = heads[i].getAttribute('data-type') === 'num'; }
    }
    if (idx < 0) return false;
    var rows = Array.prototype.slice.call(tbody.rows);
    rows.sort(function (a, b) {
      var x = value(a, idx, num), y = value(b, idx, num), r;
      if (x === null || y === null) {
        r = (x === null) - (y === null);  // empty cells last, in both directions
        if (r) return r;
      } else {
        r = num ? (x < y ? -1 : x > y ? 1 : 0) : x.localeCompare(y, undefined, {numeric: true});
        if (r) return desc ? -r : r;
      }
      return a.getAttribute('data-i') - b.getAttribute('data-i');
    });
    rows.forEach(function (r) { tbody.appendChild(r); });
    heads[idx].setAttribute('aria-sort', desc ? 'descending' : 'ascending');
    table.setAttribute('data-sort', (desc ? '-' : '') + key);
    return true;
  }
  function applyFilter(status) {
    var n = 0;
    Array.prototype.forEach.call(tbody.rows, function (r) {
      var hide = status && status !== 'all' && r.getAttribute('data-status') !== status;
      r.className = r.className.replace(/\\s*hidden/g, '') + (hide ? ' hidden' : '');
      if (!hide) n++;
    });
    if (filter) filter.value = status || 'all';
    if (shown) shown.textContent = n;
    table.setAttribute('data-status-filter', status || 'all');
  }
  function fragment() {
    var h = {};
    location.hash.replace(/^#/, '').split('&').forEach(function (kv) {
      var p = kv.split('=');
      if (p[0]) h[decodeURIComponent(p[0])] = decodeURIComponent(p.slice(1).join('='));
    });
    return h;
  }
  function updateFragment() {
    var parts = [];
    var s = table.getAttribute('data-sort');
    if (s) parts.push('sort=' + encodeURIComponent(s));
    var f = table.getAttribute('data-status-filter');
    if (f && f !== 'all') parts.push('status=' + encodeURIComponent(f));
    history.replaceState(null, '', parts.length ? '#' + parts.join('&') : location.pathname + location.search);
  }
  function applyFragment() {
    var h = fragment();
    if (h.sort) {
      var desc = h.sort.charAt(0) === '-';
      sortBy(desc ? h.sort.slice(1) : h.sort, desc);
    }
    applyFilter(h.status || 'all');
  }
  Array.prototype.forEach.call(heads, function (th) {
    var key = th.getAttribute('data-key');
    if (!key) return;
    function activate() {
      var desc = table.getAttribute('data-sort') === key;  // second click: descending
      sortBy(key, desc);
      updateFragment();
    }
    th.addEventListener('click', activate);
    th.addEventListener('keydown', function (e) {
      if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); activate(); }
    });
  });
  if (filter) filter.addEventListener('change', function () { applyFilter(filter.value); updateFragment(); });
  window.addEventListener('hashchange', applyFragment);
  applyFragment();
  table.setAttribute('data-ready', 'true');
})();
"""


def _plural(n: int, word: str) -> str:
    return word if n == 1 else f"{word}s"


def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as fh:
        return [r for r in csv.DictReader(fh)]


def _float(text: str | None) -> float | None:
    try:
        x = float(text) if text not in (None, "") else None
    except ValueError:
        return None
    return x if x is not None and math.isfinite(x) else None


def _fmt(text: str | None, spec: str = ".4g") -> str:
    x = _float(text)
    return "" if x is None else format(x, spec)


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.1f}%"


def _num(x: float | None, spec: str = ".4g") -> str:
    return "n/a" if x is None else format(x, spec)


def _ecdf_svg(values: Sequence[float], n_total: int, label: str, threshold: float | None) -> str:
    """One inline SVG panel: the empirical CDF of ``values`` over ``n_total`` pairs, log-scale x axis."""
    W, H, L, R, T, B = 360, 240, 50, 14, 12, 44
    pw, ph = W - L - R, H - T - B
    vals = sorted(values)
    positive = [v for v in vals if v > 0] + ([threshold] if threshold and threshold > 0 else [])
    if positive:
        lo, hi = math.floor(math.log10(min(positive))), math.ceil(math.log10(max(positive)))
    else:
        lo, hi = -3, 0
    if hi - lo < 2:
        lo, hi = lo - 1, hi + 1
    floor = 10.0 ** lo

    def X(v: float) -> float:
        return L + (math.log10(max(v, floor)) - lo) / (hi - lo) * pw

    def Y(f: float) -> float:
        return T + (1.0 - f) * ph

    parts = [f'<svg class="ecdf" viewBox="0 0 {W} {H}" width="{W}" height="{H}" role="img" '
             f'aria-label="cumulative distribution of {_e(label)}">']
    parts.append(f'<rect x="{L}" y="{T}" width="{pw}" height="{ph}" fill="#fff" stroke="#999"/>')
    step = max(1, math.ceil((hi - lo) / 7))
    for d in range(lo, hi + 1, step):
        x = X(10.0 ** d)
        parts.append(f'<line x1="{x:.1f}" y1="{T}" x2="{x:.1f}" y2="{T + ph}" stroke="#e3e6ea"/>')
        parts.append(f'<text x="{x:.1f}" y="{T + ph + 15}" text-anchor="middle" font-size="10">10'
                     f'<tspan dy="-5" font-size="8">{d}</tspan></text>')
    for f in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = Y(f)
        parts.append(f'<line x1="{L}" y1="{y:.1f}" x2="{L + pw}" y2="{y:.1f}" stroke="#e3e6ea"/>')
        parts.append(f'<text x="{L - 5}" y="{y + 3.5:.1f}" text-anchor="end" font-size="10">{f:g}</text>')
    if vals and n_total > 0:
        pts = [f"M{L},{Y(0):.1f}"]
        for i, v in enumerate(vals, 1):
            x = X(v)
            pts.append(f"H{x:.1f}V{Y(i / n_total):.1f}")
        pts.append(f"H{L + pw}")
        parts.append(f'<path d="{"".join(pts)}" fill="none" stroke="#1f78b4" stroke-width="1.8"/>')
    if threshold:
        x = X(threshold)
        parts.append(f'<line x1="{x:.1f}" y1="{T}" x2="{x:.1f}" y2="{T + ph}" stroke="#c62828" '
                     'stroke-dasharray="5,3"/>')
        parts.append(f'<text x="{x - 4:.1f}" y="{T + ph - 6}" text-anchor="end" font-size="10" fill="#c62828">'
                     f'threshold {threshold:g}</text>')
    parts.append(f'<text x="{L + pw / 2:.1f}" y="{H - 6}" text-anchor="middle" font-size="11">{_e(label)}</text>')
    parts.append(f'<text transform="translate(13,{T + ph / 2:.1f}) rotate(-90)" text-anchor="middle" '
                 'font-size="11">fraction of pairs with gt</text>')
    parts.append("</svg>")
    return "".join(parts)


def _error_plot(err_rows: Sequence[dict[str, str]], n_gt: int, thresholds: Any) -> str | None:
    """Inline SVG of the cumulative error distributions (three panels); None without ground truth.

    Drawn by hand (no plotting library, milliseconds, crisp at any zoom). Each curve is over all
    pairs with ground truth, so failed pairs keep it below 1; errors of exactly 0 sit on the left edge.
    """
    if not err_rows or n_gt <= 0:
        return None
    panels = [
        ("rot_err_deg", "rotation error (deg)", getattr(thresholds, "rotation_deg", None)),
        ("trans_err_rel", "translation error (x target diagonal)", getattr(thresholds, "translation_rel", None)),
        ("scale_err", "scale error |s/s_gt - 1|", getattr(thresholds, "scale", None)),
    ]
    svgs = []
    for key, label, th in panels:
        vals = [v for v in (_float(r.get(key)) for r in err_rows) if v is not None]
        svgs.append(_ecdf_svg(vals, n_gt, label, th))
    return "\n".join(svgs)


def confidence_tradeoff(rows: Sequence[dict[str, str]], errs: dict[str, dict[str, str]],
                        t_min: float, n_steps: int = 101) -> tuple[list[float], list[int], list[int], int]:
    """What a confidence threshold ``t`` would do to the ok rows with ground truth and a confidence.

    For thresholds from ``t_min`` (the run's ``engine.min_confidence``) up to 1: ``wrong[i]`` ok rows
    that would remain silently wrong (success false, confidence >= t), ``refused[i]`` correct rows that
    would be refused (success true, confidence < t). Returns ``(thresholds, wrong, refused, n_rows)``;
    ``n_rows`` is 0 when no such row has a confidence (the plot is then left out). Failed rows have no
    matrix and no errors, so thresholds below ``t_min`` cannot be evaluated.
    """
    pts: list[tuple[float, bool]] = []
    for r in rows:
        e = errs.get(r.get("pair_id", ""))
        c = _float(r.get("confidence"))
        if r.get("status") == "ok" and e is not None and c is not None and e.get("success") in ("true", "false"):
            pts.append((c, e["success"] == "true"))
    t_min = min(max(float(t_min), 0.0), 1.0)
    ts = [t_min + (1.0 - t_min) * i / (n_steps - 1) for i in range(n_steps)] if t_min < 1.0 else [1.0]
    wrong = [sum(1 for c, ok in pts if not ok and c >= t) for t in ts]
    refused = [sum(1 for c, ok in pts if ok and c < t) for t in ts]
    return ts, wrong, refused, len(pts)


def _tradeoff_svg(ts: Sequence[float], wrong: Sequence[int], refused: Sequence[int], n_rows: int,
                  t_run: float) -> str:
    """Inline SVG: silently wrong vs wrongly refused rows against the confidence threshold."""
    W, H, L, R, T, B = 520, 270, 50, 14, 36, 44
    pw, ph = W - L - R, H - T - B
    t0 = ts[0]
    span = (ts[-1] - t0) or 1.0
    y_step = max(1, math.ceil(n_rows / 4))  # whole pairs on the y axis
    y_max = y_step * max(1, math.ceil(n_rows / y_step))

    def X(t: float) -> float:
        return L + (t - t0) / span * pw

    def Y(n: float) -> float:
        return T + (1.0 - n / y_max) * ph

    parts = [f'<svg class="tradeoff" viewBox="0 0 {W} {H}" width="{W}" height="{H}" role="img" '
             'aria-label="confidence threshold trade-off">']
    parts.append(f'<rect x="{L}" y="{T}" width="{pw}" height="{ph}" fill="#fff" stroke="#999"/>')
    for i in range(6):
        t = t0 + span * i / 5
        x = X(t)
        parts.append(f'<line x1="{x:.1f}" y1="{T}" x2="{x:.1f}" y2="{T + ph}" stroke="#e3e6ea"/>')
        parts.append(f'<text x="{x:.1f}" y="{T + ph + 15}" text-anchor="middle" font-size="10">{t:.2f}</text>')
    for n in range(0, y_max + 1, y_step):
        y = Y(n)
        parts.append(f'<line x1="{L}" y1="{y:.1f}" x2="{L + pw}" y2="{y:.1f}" stroke="#e3e6ea"/>')
        parts.append(f'<text x="{L - 5}" y="{y + 3.5:.1f}" text-anchor="end" font-size="10">{n}</text>')
    for values, colour, label, dy in ((wrong, "#c62828", "silently wrong (ok, not a success)", 0),
                                      (refused, "#1f78b4", "correct but refused", 13)):
        d = f"M{X(ts[0]):.1f},{Y(values[0]):.1f}" + "".join(  # counts: a step function of t
            f"H{X(t):.1f}V{Y(v):.1f}" for t, v in zip(ts[1:], values[1:]))
        parts.append(f'<path class="{"wrong" if dy == 0 else "refused"}" d="{d}" fill="none" stroke="{colour}" '
                     'stroke-width="1.8"/>')
        parts.append(f'<text x="{L + pw - 4}" y="{T - 19 + dy}" text-anchor="end" font-size="10" '
                     f'fill="{colour}">{_e(label)}</text>')
    x = X(t_run)
    parts.append(f'<line x1="{x:.1f}" y1="{T}" x2="{x:.1f}" y2="{T + ph}" stroke="#333" stroke-dasharray="5,3"/>')
    parts.append(f'<text class="run-threshold" x="{x + 4:.1f}" y="{T + 12}" font-size="10">run: '
                 f'min_confidence {t_run:g}</text>')
    parts.append(f'<text x="{L + pw / 2:.1f}" y="{H - 6}" text-anchor="middle" font-size="11">'
                 'confidence threshold t (refuse a pair when its confidence &lt; t)</text>')
    parts.append(f'<text transform="translate(13,{T + ph / 2:.1f}) rotate(-90)" text-anchor="middle" '
                 'font-size="11">pairs</text>')
    parts.append("</svg>")
    return "".join(parts)


def _load_config(outdir: Path) -> Any:
    try:
        from gctr_cli.config import load_config

        return load_config(outdir / "config.yaml") if (outdir / "config.yaml").exists() else None
    except Exception:  # noqa: BLE001 - the report is still useful without it
        return None


def _summary_from_rows(outdir: Path, rows: Sequence[dict[str, str]], err_ids: set[str]) -> Any:
    """The summary of every row of the folder (no run's manifest known): a pair has ground truth when it has
    an errors row or its recorded inputs (``.gctr-inputs.csv``) name one."""
    from gctr_cli.outdir import INPUTS_FILE
    from gctr_cli.summary import summarize

    with_gt = err_ids | {r["pair_id"] for r in _read_csv(outdir / INPUTS_FILE) if r.get("gt")}
    pairs = [SimpleNamespace(pair_id=r["pair_id"], gt=True if r["pair_id"] in with_gt else None) for r in rows]
    return summarize(pairs, outdir)


def render_report(outdir: str | Path, *, summary: Any = None, config: Any = None) -> str:
    """The HTML text of the report of ``outdir`` (see the module docstring).

    ``summary`` is the run's :class:`gctr_cli.summary.BatchSummary` (default: computed from the rows,
    counting as "with ground truth" only pairs that have a ``tm_errors.csv`` row); ``config`` the run's
    config (default: ``OUTDIR/config.yaml``).
    """
    from gctr_cli import __version__
    from gctr_cli.summary import NO_RESULT

    outdir = Path(outdir)
    rows = _read_csv(outdir / "transforms.csv")
    errs = {r["pair_id"]: r for r in _read_csv(outdir / "tm_errors.csv")}
    if config is None:
        config = _load_config(outdir)
    others: list[dict[str, str]] = []
    if summary is None:
        summary = _summary_from_rows(outdir, rows, set(errs))  # no manifest known: every row
    else:
        # the run's manifest is what the cards, the plots and the exit code count; rows of other pair ids
        # (earlier runs with another manifest: pairs since removed) are listed apart, not counted
        manifest = set(summary.pair_ids)
        others = [r for r in rows if r.get("pair_id") not in manifest]
        order = {pid: i for i, pid in enumerate(summary.pair_ids)}  # the manifest's order, not the finishing one
        rows = sorted((r for r in rows if r.get("pair_id") in manifest), key=lambda r: order[r["pair_id"]])
    thresholds = getattr(config, "success", None)

    s = summary
    recorded = {r.get("pair_id") for r in rows}
    # pairs of a stopped run that have no row yet: listed as the failed pairs the cards count them as
    rows = rows + [{"pair_id": pid, "status": "failed", "message": f"{NO_RESULT}: the run was stopped before "
                    "this pair; rerun with --resume to finish"}
                   for pid, msg in getattr(s, "failures", ()) if msg == NO_RESULT and pid not in recorded]
    ok_rows = [r for r in rows if r.get("status") == "ok"]
    err_rows = [errs[r["pair_id"]] for r in ok_rows if r["pair_id"] in errs]
    plot = _error_plot(err_rows, s.n_gt, thresholds)
    snap_dir = outdir / "snapshots"
    has_snapshots = snap_dir.is_dir() and any(snap_dir.glob("*.png"))

    out: list[str] = []
    w = out.append
    title = f"gctr batch report: {outdir.resolve().name or outdir}"
    w("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n")
    w("<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n")
    w(f"<title>{_e(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n")
    w("<header>\n")
    w(f"<h1>{_e(title)}</h1>\n")
    generated = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M:%S %Z")
    w(f"<p class=\"meta\">{_e(outdir.resolve())} &middot; generated {_e(generated)} by gctr {_e(__version__)}</p>\n")
    w("</header>\n<main>\n<section id=\"summary\">\n<h2>Summary</h2>\n<div class=\"cards\">\n")

    def card(value: str, key: str, cls: str = "") -> None:
        w(f"<div class=\"card {cls}\"><div class=\"v\">{_e(value)}</div><div class=\"k\">{_e(key)}</div></div>\n")

    card(str(s.n_pairs), _plural(s.n_pairs, "pair"))
    card(str(s.n_ok), "ok", "good" if s.n_ok else "")
    card(str(s.n_failed), "failed", "bad" if s.n_failed else "good")
    if s.success_rate is not None:
        card(_pct(s.success_rate), f"success ({s.n_success}/{s.n_gt} with ground truth)",
             "good" if s.success_rate >= 0.999 else "bad" if s.success_rate < 0.5 else "")
    else:
        card("n/a", "success (no ground truth)")
    card(f"{s.wall_time_s:.1f} s", f"wall time ({s.n_run} pair{'' if s.n_run == 1 else 's'} run)")
    w("</div>\n<table class=\"kv\">\n")
    kv: list[tuple[str, str]] = []
    if s.n_resumed:
        kv.append(("resumed", f"{s.n_resumed} {_plural(s.n_resumed, 'pair')} done by an earlier run"))
    n_missing = sum(1 for _pid, msg in getattr(s, "failures", ()) if msg == NO_RESULT)
    if n_missing:
        kv.append(("no result yet", f"{n_missing} {_plural(n_missing, 'pair')} of the manifest (the run was stopped "
                                    "before them): counted as failed; rerun with --resume to finish"))
    if others:
        kv.append(("not counted", f"{len(others)} {_plural(len(others), 'row')} of transforms.csv for pairs that "
                                  "are not in the manifest of this run (earlier runs), listed apart at the end"))
    if s.median_rot_err_deg is not None:
        kv.append(("median errors",
                   f"rotation {_num(s.median_rot_err_deg)}°, translation {_num(s.median_trans_err)} "
                   f"({_num(s.median_trans_err_rel)} × target diagonal), scale {_num(s.median_scale_err)}, "
                   f"TM {_num(s.median_tm_err)}"))
    if thresholds is not None:
        kv.append(("success means", f"rotation < {thresholds.rotation_deg:g}°, translation < "
                   f"{thresholds.translation_rel:g} × target diagonal, scale error < {thresholds.scale:g}"))
    if config is not None:
        kv.append(("method / seed", f"{getattr(config, 'method', '?')} / {getattr(config, 'seed', '?')}"))
    kv.append(("files", "transforms.csv, tm_errors.csv, matrices/, config.yaml"
               + (", snapshots/" if has_snapshots else "") + (", aligned/" if (outdir / "aligned").is_dir() else "")))
    for k, v in kv:
        w(f"<tr><td>{_e(k)}</td><td>{_e(v)}</td></tr>\n")
    w("</table>\n</section>\n")

    if plot is not None:
        w("<section id=\"errors\">\n<h2>Error distribution</h2>\n<figure>\n")
        w(f"<div id=\"error-plot\" class=\"plots\">\n{plot}\n</div>\n")
        w(f"<figcaption>Fraction of the {s.n_gt} pairs with ground truth whose error is below x (log scale); "
          "failed pairs never reach the curve; dashed: the success thresholds.</figcaption>\n"
          "</figure>\n</section>\n")

    t_run = getattr(getattr(config, "engine", None), "min_confidence", None)
    ts, wrong, refused, n_conf = confidence_tradeoff(rows, errs, t_run if t_run is not None else 0.0)
    if n_conf:
        t_shown = ts[0]
        w("<section id=\"confidence\">\n<h2>Confidence threshold</h2>\n<figure>\n")
        w(f"<div id=\"tradeoff-plot\" class=\"plots\">\n{_tradeoff_svg(ts, wrong, refused, n_conf, t_shown)}\n</div>\n")
        w(f"<figcaption>Over the {n_conf} ok pairs with ground truth and a confidence: at threshold t, red counts "
          f"the pairs that would still be reported ok although they are wrong (confidence &ge; t, not a success), "
          f"blue the correct pairs that would be refused (confidence &lt; t). At the run's threshold "
          f"{t_shown:g}: {wrong[0]} silently wrong, {refused[0]} refused. Failed rows have no matrix, so "
          f"thresholds below the run's <code>engine.min_confidence</code> cannot be evaluated: the plot starts "
          f"there.</figcaption>\n</figure>\n</section>\n")

    n_failed_rows = sum(1 for r in rows if r.get("status") != "ok")
    gt_ids = set(getattr(s, "gt_ids", ()) or ())
    w("<section id=\"pairs-section\">\n<h2>Pairs</h2>\n<div class=\"controls\">\n")
    w("<label>show <select id=\"status-filter\"><option value=\"all\">all pairs</option>"
      f"<option value=\"ok\">ok ({len(rows) - n_failed_rows})</option>"
      f"<option value=\"failed\">failed ({n_failed_rows})</option></select></label>\n")
    w(f"<span><span id=\"shown\">{len(rows)}</span> of {len(rows)} rows &middot; click a column header "
      "to sort</span>\n</div>\n")
    w("<p class=\"meta\">A <b>failed</b> pair has no matrix: either an input could not be used (the message names "
      "the file) or the evidence did not single out one alignment (<i>low confidence</i>, <i>ambiguous</i>): gctr "
      "refuses rather than guess. The <b>confidence</b> of an ok pair is its lead over the best distinct "
      "alternative: it tells which alignment, not how precise it is (the errors against ground truth do).</p>\n")
    w("<div class=\"scroll\">\n<table id=\"pairs\">\n<thead><tr>"
      + ("<th class=\"nosort\">snapshot</th>" if has_snapshots else ""))
    for key, label, typ, tip in COLUMNS:
        w(f"<th data-key=\"{key}\" data-type=\"{typ}\" tabindex=\"0\" scope=\"col\" title=\"{_e(tip)}\">"
          f"{_e(label)}</th>")
    w("</tr></thead>\n<tbody>\n")
    _pair_rows(w, rows, errs, gt_ids, snap_dir if has_snapshots else None)
    w("</tbody>\n</table>\n</div>\n</section>\n")
    if others:
        w("<section id=\"other-pairs-section\">\n<h2>Rows of pairs not in this run's manifest</h2>\n")
        w(f"<p class=\"meta\">{len(others)} {_plural(len(others), 'row')} of earlier runs in this folder whose pairs "
          "this run's manifest does not list (removed since, or another manifest's). They stay in the CSVs (and "
          "the matrices of ok ones in matrices/); the summary above does not count them.</p>\n")
        w("<div class=\"scroll\">\n<table id=\"other-pairs\">\n<thead><tr>"
          + ("<th>snapshot</th>" if has_snapshots else ""))
        for _key, label, _typ, tip in COLUMNS:
            w(f"<th scope=\"col\" title=\"{_e(tip)}\">{_e(label)}</th>")
        w("</tr></thead>\n<tbody>\n")
        _pair_rows(w, others, errs, set(), snap_dir if has_snapshots else None)
        w("</tbody>\n</table>\n</div>\n</section>\n")
    w("</main>\n")
    w("<footer>Matrices map the source onto the target: target &asymp; T &middot; [source; 1]. "
      "Sort by URL too: <code>report.html#sort=-rot_err_deg&amp;status=failed</code>.</footer>\n")
    w(f"<script>{_JS}</script>\n</body>\n</html>\n")
    return "".join(out)


def _pair_rows(w: Any, rows: Sequence[dict[str, str]], errs: dict[str, dict[str, str]], gt_ids: set[str],
               snap_dir: Path | None) -> None:
    """The ``<tr>`` of each row of ``transforms.csv`` (``gt_ids``: pairs whose failure counts as no success;
    ``snap_dir``: the snapshots folder, when the run made one; without it there is no snapshot column)."""
    for r in rows:
        pid = r.get("pair_id", "")
        status = r.get("status", "")
        e = errs.get(pid, {}) if status == "ok" else {}
        if status != "ok" and pid in gt_ids:
            e = {"success": "false"}  # a failed pair with ground truth is no success (as the summary counts it)
        cells = {**{k: r.get(k, "") for k in ("pair_id", "status", "message", "fitness", "confidence", "scale",
                                              "runtime_s")},
                 **{k: e.get(k, "") for k in ("rot_err_deg", "trans_err_rel", "scale_err", "tm_err", "success")}}
        cls = "ok" if status == "ok" else "failed"
        w(f"<tr class=\"{cls}\" data-status=\"{_e(cls)}\" data-pair=\"{_e(pid)}\">")
        if snap_dir is not None and (snap_dir / f"{pid}.png").exists():
            href = "snapshots/" + quote(f"{pid}.png")
            w(f"<td class=\"thumb\"><a href=\"{_e(href)}\"><img src=\"{_e(href)}\" loading=\"lazy\" width=\"108\" "
              f"height=\"72\" alt=\"snapshot of {_e(pid)}\"></a></td>")
        elif snap_dir is not None:
            w("<td class=\"thumb none\">&ndash;</td>")
        for key, _label, typ, _tip in COLUMNS:
            raw = cells.get(key, "")
            if key == "pair_id" and not r.get("source"):  # a pair of a stopped run that has no row yet
                w(f"<td>{_e(raw)}</td>")
            elif key == "pair_id":
                tip = f"source: {r.get('source', '')}\ntarget: {r.get('target', '')}\nseed: {r.get('seed', '')}"
                w(f"<td title=\"{_e(tip)}\">{_e(raw)}</td>")
            elif key == "status":
                w(f"<td class=\"st {cls}\">{_e(raw)}</td>")
            elif key == "message":
                w(f"<td class=\"msg\">{_e(raw)}</td>")
            elif typ == "num":
                x = _float(raw)
                w(f"<td class=\"num\" data-v=\"{'' if x is None else repr(x)}\">{_e(_fmt(raw))}</td>")
            else:
                w(f"<td>{_e(raw)}</td>")
        w("</tr>\n")


def write_report(outdir: str | Path, *, summary: Any = None, config: Any = None) -> Path:
    """Write ``OUTDIR/report.html`` atomically (temporary file, fsync, rename); return its path."""
    outdir = Path(outdir)
    text = render_report(outdir, summary=summary, config=config)
    path = outdir / "report.html"
    atomic_write(path, escaped(text))  # a folder name that is not UTF-8 (a Latin-1 share) as \xe9, not failing
    return path
