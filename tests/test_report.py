"""OUTDIR/report.html: contents, self-containment, resume, and a render in a real headless browser."""

from __future__ import annotations

import functools
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import read_csv

from data_scripts import fake_engine
from gctr_cli import batch, cli
from gctr_cli.batch import run_batch
from gctr_cli.report import COLUMNS, render_report


class _Page(HTMLParser):
    """Collects the pairs table (rows in document order) and every URL-bearing attribute."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[dict[str, str]] = []
        self.cells: list[list[str]] = []
        self.urls: list[str] = []
        self.table_attrs: dict[str, str] = {}
        self.headers: list[str] = []
        self.ids: set[str] = set()
        self._in_pairs = self._in_body = self._in_cell = False
        self._text = ""

    def handle_starttag(self, tag, attrs):
        a = {k: v or "" for k, v in attrs}
        if "id" in a:
            self.ids.add(a["id"])
        for k in ("src", "href"):
            if k in a:
                self.urls.append(a[k])
        if tag == "table" and a.get("id") == "pairs":
            self.table_attrs = a
            self._in_pairs = True
        if tag == "th" and "data-key" in a:
            self.headers.append(a["data-key"])
        if tag == "tbody" and self._in_pairs:
            self._in_body = True
        if self._in_body and tag == "tr":
            self.rows.append(a)
            self.cells.append([])
        if self._in_body and tag == "td":
            self._in_cell, self._text = True, ""

    def handle_endtag(self, tag):
        if tag == "tbody":
            self._in_body = False
        if tag == "table":
            self._in_pairs = False
        if tag == "td" and self._in_cell:
            self.cells[-1].append(self._text.strip())
            self._in_cell = False

    def handle_data(self, data):
        if self._in_cell:
            self._text += data


def parse(text: str) -> _Page:
    page = _Page()
    page.feed(text)
    return page


def column(page: _Page, key: str) -> list[str]:
    i = [c[0] for c in COLUMNS].index(key)
    return [cells[i + len(cells) - len(COLUMNS)] for cells in page.cells]  # after the snapshot column, if any


def assert_self_contained(text: str, page: _Page) -> None:
    assert not re.search(r"(?i)\b(https?|ftp|wss?):", text), "the report must not reference the network"
    assert "//" not in "".join(u for u in page.urls if not u.startswith("data:"))
    assert "<link" not in text and "@import" not in text and "<script src" not in text
    for url in page.urls:
        assert url.startswith("snapshots/") or url.startswith("data:"), url


@pytest.fixture
def failing_set(four_pairs):
    ds = four_pairs
    ds.add_pair("raises", n=fake_engine.RAISE_N)
    (ds.root / "bad").mkdir()
    (ds.root / "bad" / "x<script>.ply").write_bytes(b"")
    ds.add_raw("html_in_message", "bad/x<script>.ply", ds.rows[0]["target"], ds.rows[0]["gt"])
    return ds


def test_report_has_every_pair_summary_and_plot(failing_set, fast_config, tmp_path):
    out = tmp_path / "out"
    summary = run_batch(failing_set.specs(), fast_config, out, workers=2, register_fn=fake_engine.register)
    text = (out / "report.html").read_text()
    page = parse(text)
    ids = [r["pair_id"] for r in read_csv(out / "transforms.csv")[1]]
    assert sorted(r["data-pair"] for r in page.rows) == sorted(ids) and len(page.rows) == 7
    assert [r["data-pair"] for r in page.rows] == [p.pair_id for p in failing_set.specs()]  # the manifest's order
    assert "snapshot</th>" not in text and "class=\"thumb" not in text  # no snapshots asked for: no column
    assert all(len(cells) == len(COLUMNS) for cells in page.cells)  # a cell under every header, no more
    assert "gctr refuses rather than guess" in text and "not how precise it is" in text
    assert page.headers == [c[0] for c in COLUMNS]
    status = dict(zip(column(page, "pair_id"), column(page, "status")))
    assert status["raises"] == "failed" and status["ply_ply"] == "ok"
    msgs = dict(zip(column(page, "pair_id"), column(page, "message")))
    assert msgs["raises"] == "ValueError: degenerate input: the source cloud is planar"
    # a failed pair with ground truth is no success, as the summary counts it (the cell was blank)
    success = dict(zip(column(page, "pair_id"), column(page, "success")))
    assert success["raises"] == success["html_in_message"] == "false" and success["no_gt"] == ""
    assert "x<script>.ply: file is empty" in msgs["html_in_message"]  # shown as text...
    assert "x&lt;script&gt;.ply" in text and "x<script>" not in text  # ...escaped in the source
    # summary cards and the error distribution (pairs with ground truth exist)
    assert f'<div class="v">{summary.n_pairs}</div><div class="k">pairs</div>' in text
    assert '<div class="v">2</div><div class="k">failed</div>' in text
    assert f"success ({summary.n_success}/{summary.n_gt} with ground truth)" in text
    assert "error-plot" in page.ids and text.count('<svg class="ecdf"') == 3
    # the fake engine reports a confidence: the threshold trade-off plot is there (tests/test_report_confidence.py)
    assert "tradeoff-plot" in page.ids and text.count("<svg") == 4
    assert "snapshots/" not in text  # no snapshots were asked for
    assert_self_contained(text, page)
    assert not list(out.glob(".report*"))  # written atomically, no temporary left


def test_report_without_ground_truth_and_after_resume(dataset, fast_config, tmp_path):
    for i in range(4):
        dataset.add_pair(f"p{i}", with_gt=False)
    out = tmp_path / "out"
    rows = list(dataset.rows)
    dataset.rows = rows[:2]
    run_batch(dataset.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    assert len(parse((out / "report.html").read_text()).rows) == 2
    dataset.rows = rows
    run_batch(dataset.specs(), fast_config, out, workers=1, register_fn=fake_engine.register, resume=True,
              snapshots=True)
    text = (out / "report.html").read_text()
    page = parse(text)
    assert sorted(r["data-pair"] for r in page.rows) == ["p0", "p1", "p2", "p3"]  # earlier rows too
    assert "error-plot" not in page.ids and "<svg" not in text
    assert "2 pairs done by an earlier run" in text
    # thumbnails link to the snapshots of the pairs that have one (only the resumed run made them)
    thumbs = sorted(u for u in page.urls if u.startswith("snapshots/"))
    assert thumbs == ["snapshots/p2.png"] * 2 + ["snapshots/p3.png"] * 2  # <a href> and <img src>
    assert all((out / u).exists() for u in thumbs)
    assert_self_contained(text, page)


def test_report_after_resume_with_a_smaller_manifest_counts_the_runs_pairs(four_pairs, fast_config, tmp_path):
    """A nightly job whose manifest lost pairs (files deleted) printed "6/6, 100%" and exited 0, while the report
    counted every row of the folder ("8 pairs, 1 failed, 87.5%", blaming a pair whose files were gone) and
    said "resumed 8" of 6. The report counts the run's manifest, as stdout and the exit code do; the other
    rows are listed apart and named as not counted."""
    out = tmp_path / "out"
    four_pairs.add_raw("broken", "nowhere.ply", four_pairs.rows[0]["target"], four_pairs.rows[0]["gt"])
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    rows = list(four_pairs.rows)
    four_pairs.rows = rows[:2]
    summary = run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register,
                        resume=True)
    assert (summary.n_pairs, summary.n_failed, summary.n_resumed) == (2, 0, 2)  # stdout's summary
    text = (out / "report.html").read_text()
    assert [r["data-pair"] for r in parse(text).rows] == ["ply_ply", "pcd_xyz"]
    assert '<div class="v">2</div><div class="k">pairs</div>' in text
    assert '<div class="v">0</div><div class="k">failed</div>' in text
    assert "success (2/2 with ground truth)" in text and "2 pairs done by an earlier run" in text
    assert ("4 rows of transforms.csv for pairs that are not in the manifest of this run (earlier runs), listed "
            "apart at the end") in text
    other = text[text.index('<table id="other-pairs">'):]
    assert [pid for pid in ("xyz_ply", "ply_pcd_utm", "no_gt", "broken") if f'data-pair="{pid}"' in other] == [
        "xyz_ply", "ply_pcd_utm", "no_gt", "broken"]
    # without a run's summary (the report rendered from the folder alone) every row counts
    alone = render_report(out)
    assert len(parse(alone).rows) == 6 and '<table id="other-pairs">' not in alone
    assert '<div class="v">1</div><div class="k">failed</div>' in alone


def test_a_report_that_cannot_be_written_leaves_no_out_of_date_one(four_pairs, fast_config, tmp_path, monkeypatch,
                                                                  caplog):
    """A full disk at the end of a resumed night left the previous night's report ("4 pairs, 100%") in place
    and the summary still printed its path; the old report is removed, and the warning says so."""
    out = tmp_path / "out"
    rows = list(four_pairs.rows)
    four_pairs.rows = rows[:2]
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    assert (out / "report.html").is_file()

    def no_space(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("gctr_cli.report.write_report", no_space)
    four_pairs.rows = rows
    with caplog.at_level("WARNING", logger="gctr_cli.batch"):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register, resume=True)
    assert not (out / "report.html").exists()
    assert f"could not write {out / 'report.html'}: OSError: [Errno 28] No space left on device; removed the " \
           "earlier one, which is out of date" in caplog.text


def test_a_stopped_run_rewrites_the_report_of_what_it_recorded(four_pairs, fast_config, tmp_path):
    """A resumed run stopped by SIGTERM or Ctrl-C after recording pairs left the earlier run's report, which
    showed fewer rows than transforms.csv: the report is written of the rows recorded so far."""
    out = tmp_path / "out"
    rows = list(four_pairs.rows)
    four_pairs.rows = rows[:2]
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    four_pairs.rows = rows

    def stop(outcome):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register, resume=True,
                  on_outcome=stop)
    recorded = [r["pair_id"] for r in read_csv(out / "transforms.csv")[1]]
    assert len(recorded) == 3
    text = (out / "report.html").read_text()
    # the two pairs still to do are rows too: the table and its filter agree with the cards
    # (they counted them as failed while the table showed 3 of 3 rows and "failed (0)")
    report_rows = parse(text).rows
    missing = [p for p in (r["pair_id"] for r in rows) if p not in recorded]
    assert len(missing) == 2
    assert [r["data-pair"] for r in report_rows] == recorded + missing
    assert [r["data-status"] for r in report_rows[3:]] == ["failed", "failed"]
    assert "no result recorded: the run was stopped before this pair" in text
    assert f'failed ({sum(r["data-status"] == "failed" for r in report_rows)})' in text
    assert '<div class="v">5</div><div class="k">pairs</div>' in text  # the manifest's: 2 still to do
    assert '<div class="v">2</div><div class="k">failed</div>' in text  # "no result recorded"
    assert ("2 pairs of the manifest (the run was stopped before them): counted as failed; rerun with --resume to "
            "finish") in text


def test_cli_prints_the_report_path(four_pairs, tmp_path, monkeypatch):
    monkeypatch.setattr(batch, "run_batch", functools.partial(batch.run_batch, register_fn=fake_engine.register))
    out = tmp_path / "out"
    res = CliRunner().invoke(cli.main, ["batch", str(four_pairs.manifest()), "-o", str(out), "-j", "1"],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert f"report: {out}/report.html" in res.stdout


def test_cli_prints_no_report_path_when_the_report_was_not_written(four_pairs, tmp_path, monkeypatch):
    """The summary printed ``report: OUTDIR/report.html`` whenever such a file existed, an earlier run's too."""
    monkeypatch.setattr(batch, "run_batch", functools.partial(batch.run_batch, register_fn=fake_engine.register))
    out = tmp_path / "out"
    args = ["batch", str(four_pairs.manifest()), "-o", str(out), "-j", "1"]
    assert CliRunner().invoke(cli.main, args, catch_exceptions=False).exit_code == 0

    def no_space(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("gctr_cli.report.write_report", no_space)
    real_unlink = Path.unlink

    def unlink(self, *a, **k):
        if self.name == "report.html":
            raise PermissionError(13, "Permission denied")
        return real_unlink(self, *a, **k)

    monkeypatch.setattr(Path, "unlink", unlink)
    res = CliRunner().invoke(cli.main, [*args, "--resume"], catch_exceptions=False)
    assert res.exit_code == 0 and (out / "report.html").exists()  # the old one could not be removed either
    assert "report:" not in res.stdout
    assert "; the earlier one there is out of date" in res.stderr


def test_report_problems_never_fail_the_batch(four_pairs, fast_config, tmp_path, monkeypatch, caplog):
    import gctr_cli.report

    def broken(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(gctr_cli.report, "write_report", broken)
    summary = run_batch(four_pairs.specs(), fast_config, tmp_path / "out", workers=1, register_fn=fake_engine.register)
    assert summary.n_ok == 5
    assert "could not write" in caplog.text and "disk full" in caplog.text


def test_render_report_of_a_folder(four_pairs, fast_config, tmp_path):
    """``render_report`` works from the files alone (e.g. on a copied results folder)."""
    out = tmp_path / "out"
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    page = parse(render_report(out))
    assert len(page.rows) == 5


# ----------------------------------------------------------------------------------------------------
# a real browser
# ----------------------------------------------------------------------------------------------------

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--mute-audio"]


def chromium(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    profile = tmp_path / "chromium-profile"
    return subprocess.run([CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args],
                          capture_output=True, text=True, timeout=90, cwd=tmp_path)


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make test installs it: make browser-deps)")
def test_report_renders_and_sorts_in_headless_chromium(failing_set, fast_config, tmp_path):
    pytest.importorskip("PIL.Image")
    import numpy as np
    from PIL import Image

    out = tmp_path / "out"
    run_batch(failing_set.specs(), fast_config, out, workers=2, register_fn=fake_engine.register, snapshots=True)
    url = (out / "report.html").resolve().as_uri()

    # 1. a screenshot: the page renders (not blank), with the plot and the table
    shot = tmp_path / "report.png"
    res = chromium(tmp_path, f"--screenshot={shot}", "--window-size=1200,900", "--hide-scrollbars", url)
    assert shot.exists(), res.stderr[-2000:]
    with Image.open(shot) as im:
        assert im.size == (1200, 900)
        img = np.asarray(im.convert("RGB")).astype(int)
    assert (img.min(-1) < 200).mean() > 0.02  # text, cards, plot lines
    saturated = img.max(-1) - img.min(-1) > 60
    assert saturated.sum() > 500  # coloured figures (green/red counts, blue curves, red thresholds)

    # 2. the DOM after the script ran: every row is there; the fragment sorts and filters
    res = chromium(tmp_path, "--dump-dom", url + "#sort=-runtime_s")
    page = parse(res.stdout)
    assert page.table_attrs.get("data-ready") == "true", res.stderr[-2000:]
    assert page.table_attrs.get("data-sort") == "-runtime_s"
    assert len(page.rows) == 7
    times = [float(t) for t in column(page, "runtime_s")]
    assert times == sorted(times, reverse=True)

    res = chromium(tmp_path, "--dump-dom", url + "#sort=pair_id&status=failed")
    page = parse(res.stdout)
    assert page.table_attrs.get("data-sort") == "pair_id"
    assert column(page, "pair_id") == sorted(column(page, "pair_id"), key=str.lower)
    hidden = {r["data-pair"] for r in page.rows if "hidden" in r.get("class", "").split()}
    visible = {r["data-pair"] for r in page.rows} - hidden
    assert visible == {"raises", "html_in_message"}

    # rotation error, descending: empty cells (failed pairs) stay last
    res = chromium(tmp_path, "--dump-dom", url + "#sort=-rot_err_deg")
    page = parse(res.stdout)
    errs = column(page, "rot_err_deg")
    filled = [e for e in errs if e]
    assert errs[: len(filled)] == filled and len(filled) == 4
    assert [float(e) for e in filled] == sorted((float(e) for e in filled), reverse=True)
    # a text column: empty cells stay last too (the ok pairs' empty messages came first)
    res = chromium(tmp_path, "--dump-dom", url + "#sort=message")
    messages = column(parse(res.stdout), "message")
    assert messages[:2] == sorted(messages[:2], key=str.lower) and all(messages[:2]) and not any(messages[2:])
    # the snapshot thumbnails are there and point to existing files
    thumbs = {u for u in page.urls if u.startswith("snapshots/")}
    assert len(thumbs) == 7 and all((out / u).exists() for u in thumbs)
