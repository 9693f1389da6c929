"""PNG snapshots: batch --snapshots (local pool), input-only pictures of failed pairs, gctr show."""

from __future__ import annotations

import functools
import logging
import subprocess
import textwrap

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import PYTHON, bumpy_surface, read_csv, rotation, write_cloud

from data_scripts import fake_engine
from gctr_cli import batch, cli, outcome, snapshots
from gctr_cli.batch import run_batch, run_pair
from gctr_cli.geometry import apply, to_matrix
from gctr_cli.io import write_matrix
from gctr_cli.snapshots import SNAPSHOT_SIZE_PX, render_snapshot

Image = pytest.importorskip("PIL.Image")


def load_rgb(path_or_bytes) -> np.ndarray:
    import io

    src = io.BytesIO(path_or_bytes) if isinstance(path_or_bytes, bytes) else path_or_bytes
    with Image.open(src) as im:
        return np.asarray(im.convert("RGB")).astype(int)


def colours(img: np.ndarray) -> tuple[int, int]:
    """(orange-ish, blue-ish) pixel counts: the source and target colours (axes and text are grey)."""
    r, b = img[..., 0], img[..., 2]
    saturated = img.max(-1) - img.min(-1) > 50
    return int((saturated & (r > b + 40)).sum()), int((saturated & (b > r + 40)).sum())


def halves(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The picture without its title band, split into the input row and the registered row."""
    h = img.shape[0]
    return img[int(0.1 * h): h // 2], img[h // 2:]


def test_render_snapshot_size_colours_and_rows():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20000, 3))  # more than MAX_POINTS: subsampled
    T = np.eye(4)
    T[:3, 3] = [5.0, 0, 0]
    tgt = rng.normal(size=(5000, 3)) + T[:3, 3]  # other samples of the same shape: both colours show
    img = load_rgb(render_snapshot(src, tgt, T, title="t"))
    assert img.shape[:2] == (SNAPSHOT_SIZE_PX[1], SNAPSHOT_SIZE_PX[0])
    top, bottom = halves(img)
    for part in (top, bottom):
        orange, blue = colours(part)
        assert orange > 500 and blue > 500
    # no transform: the bottom row is a note, no clouds
    img = load_rgb(render_snapshot(src, None, None, note="not registered: reason"))
    top, bottom = halves(img)
    assert colours(top)[0] > 500 and colours(top)[1] < 50  # only the source was loaded
    assert colours(bottom) == (0, 0)
    assert snapshots.subsample(src, 100).shape == (100, 3)
    assert snapshots.subsample(src[:50], 100).shape == (50, 3)


def test_batch_snapshots_for_ok_and_failed_pairs(dataset, fast_config, tmp_path):
    ds = dataset
    ds.add_pair("ply_pcd", exts=(".ply", ".pcd"))
    ds.add_pair("xyz_ply", exts=(".xyz", ".ply"), with_gt=False)
    ds.add_pair("raises", n=fake_engine.RAISE_N)
    ds.add_raw("no_source", "clouds/missing.ply", ds.rows[0]["target"])
    ds.add_raw("nothing", "clouds/missing.ply", "clouds/missing2.ply")
    out = tmp_path / "out"
    run_batch(ds.specs(), fast_config, out, workers=2, register_fn=fake_engine.register, snapshots=True)

    rows = {r["pair_id"]: r for r in read_csv(out / "transforms.csv")[1]}
    pngs = {p.stem: p for p in (out / "snapshots").glob("*.png")}
    # every pair with at least one readable cloud has its picture; nothing else is in the folder
    assert sorted(pngs) == sorted(set(rows) - {"nothing"})
    assert not list((out / "snapshots").glob(".*"))
    for pid, path in pngs.items():
        img = load_rgb(path)
        assert img.shape[:2] == (SNAPSHOT_SIZE_PX[1], SNAPSHOT_SIZE_PX[0]), pid
        top, bottom = halves(img)
        if rows[pid]["status"] == "ok":
            # registered row drawn (the test clouds coincide point for point once registered, so the
            # source, drawn last, covers the target there)
            assert min(colours(top)) > 100 and colours(bottom)[0] > 100, pid
        else:  # a failed pair: its input only
            assert colours(bottom) == (0, 0), pid
    assert rows["raises"]["status"] == "failed" and min(colours(halves(load_rgb(pngs["raises"]))[0])) > 100
    assert colours(halves(load_rgb(pngs["no_source"]))[0])[0] < 50  # target only
    # the snapshot changes nothing else: same rows as a run without it
    run_batch(ds.specs(), fast_config, tmp_path / "plain", workers=1, register_fn=fake_engine.register)
    plain = {r["pair_id"]: r for r in read_csv(tmp_path / "plain" / "transforms.csv")[1]}
    strip = lambda r: {k: v for k, v in r.items() if k != "runtime_s"}  # noqa: E731
    assert {k: strip(v) for k, v in rows.items()} == {k: strip(v) for k, v in plain.items()}
    assert not (tmp_path / "plain" / "snapshots").exists()


def test_a_snapshot_failure_never_fails_the_pair(four_pairs, fast_config, monkeypatch, caplog):
    def broken(*a, **k):
        raise RuntimeError("no fonts today")

    monkeypatch.setattr(snapshots, "snapshot_of_outcome", broken)
    spec = four_pairs.specs()[0]
    with caplog.at_level(logging.WARNING):
        out = run_pair(spec, fast_config, fake_engine.register, snapshot=True)
    assert out.ok and out.snapshot_png is None and out.message == ""
    assert "snapshot failed: RuntimeError: no fonts today" in caplog.text
    # in a worker, the warning is reported but kept out of the pair's message
    marked = outcome.with_warnings(out, [(outcome.SNAPSHOT_LOGGER, "snapshot failed: x")])
    assert marked.message == "" and marked.warnings == ("snapshot failed: x",)


def test_gctr_show(tmp_path):
    rng = np.random.default_rng(5)
    T = to_matrix(1.5, rotation([1, 2, 3], 30.0), [1.0, 2.0, 3.0])
    src = write_cloud(tmp_path / "a.pcd", bumpy_surface(rng, 3000))
    tgt = write_cloud(tmp_path / "b.xyz", apply(T, bumpy_surface(rng, 4000)))
    write_matrix(tmp_path / "T.txt", T)
    runner = CliRunner()
    view = tmp_path / "views" / "view.png"
    res = runner.invoke(cli.main, ["show", str(src), str(tgt), "--matrix", str(tmp_path / "T.txt"),
                                   "-o", str(view)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert res.stdout.strip() == f"wrote {view}"
    img = load_rgb(view)
    assert img.shape[:2] == (SNAPSHOT_SIZE_PX[1], SNAPSHOT_SIZE_PX[0])
    assert min(colours(halves(img)[1])) > 100  # the registered row is drawn

    res = runner.invoke(cli.main, ["show", str(src), str(tgt), "-o", str(tmp_path / "in.png")])
    assert res.exit_code == 0 and colours(halves(load_rgb(tmp_path / "in.png"))[1]) == (0, 0)

    (tmp_path / "bad.txt").write_text("1 2 3\n")
    res = runner.invoke(cli.main, ["show", str(src), str(tgt), "-m", str(tmp_path / "bad.txt"), "-o",
                                   str(tmp_path / "x.png")])
    assert res.exit_code == 2 and "bad.txt" in res.stderr
    res = runner.invoke(cli.main, ["show", str(tmp_path / "nope.ply"), str(tgt), "-o", str(tmp_path / "x.png")])
    assert res.exit_code == 2 and "nope.ply: file does not exist" in res.stderr
    assert not (tmp_path / "x.png").exists()


def test_cli_batch_snapshots_flag(dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(batch, "run_batch", functools.partial(batch.run_batch, register_fn=fake_engine.register))
    dataset.add_pair("a")
    dataset.add_pair("b", exts=(".xyz", ".pcd"))
    out = tmp_path / "out"
    res = CliRunner().invoke(cli.main, ["batch", str(dataset.manifest()), "-o", str(out), "-j", "1",
                                        "--snapshots"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "matrices/, config.yaml, snapshots/" in res.stdout
    assert sorted(p.name for p in (out / "snapshots").glob("*.png")) == ["a.png", "b.png"]


def test_show_help_is_lazy():
    code = textwrap.dedent(
        """
        import sys
        from gctr_cli.cli import main
        try:
            main(["show", "--help"])
        except SystemExit as e:
            assert e.code == 0
        print("HEAVY:", [m for m in ("numpy", "matplotlib", "open3d", "distributed") if m in sys.modules])
        """
    )
    out = subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "HEAVY: []" in out.stdout and "--matrix" in out.stdout


def test_write_png_is_atomic(tmp_path):
    target = tmp_path / "a" / "b.png"
    snapshots.write_png(target, b"\x89PNG data")
    assert target.read_bytes() == b"\x89PNG data"
    assert [p.name for p in target.parent.iterdir()] == ["b.png"]


def test_a_title_the_font_cannot_draw_gives_no_warning(recwarn):
    """A pair id in a script DejaVu Sans lacks (CJK) printed four multi-line matplotlib warnings per pair."""
    rng = np.random.default_rng(0)
    png = render_snapshot(rng.random((200, 3)), rng.random((200, 3)), np.eye(4), title="扫描_1: ok")
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert [str(w.message) for w in recwarn if "Glyph" in str(w.message)] == []
