"""Tests for gctr_cli.manifest: reading, writing and building pair manifests."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from gctr_cli.manifest import ManifestError, PairSpec, build_manifest, read_manifest, write_manifest


@pytest.fixture
def tmp_path(tmp_path: Path) -> Path:
    """Resolved tmp_path, so comparisons with resolved manifest paths also hold where /tmp is a symlink."""
    return tmp_path.resolve()


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, newline="")
    return path


def assert_error(exc_info, path: Path, *keywords: str) -> None:
    msg = str(exc_info.value)
    assert path.name in msg, msg
    for kw in keywords:
        assert kw in msg, f"{kw!r} not in {msg!r}"


# ----------------------------------------------------------------------------------------------------
# read_manifest
# ----------------------------------------------------------------------------------------------------


def test_read_resolves_relative_to_manifest_folder(tmp_path, monkeypatch):
    m = write(
        tmp_path / "runs" / "pairs.csv",
        "pair_id,source,target,gt\n"
        "a,../data/a_src.ply,../data/a_tgt.ply,gt/a.txt\n"
        "b,sub/b_src.pcd,/abs/b_tgt.xyz,\n",
    )
    monkeypatch.chdir(tmp_path.parent)  # must not depend on the working directory
    pairs = read_manifest(m)
    assert pairs == [
        PairSpec("a", tmp_path / "data/a_src.ply", tmp_path / "data/a_tgt.ply", tmp_path / "runs/gt/a.txt"),
        PairSpec("b", tmp_path / "runs/sub/b_src.pcd", Path("/abs/b_tgt.xyz"), None),
    ]
    assert all(p.source.is_absolute() and p.target.is_absolute() for p in pairs)


def test_read_relative_manifest_path(tmp_path, monkeypatch):
    write(tmp_path / "m.csv", "pair_id,source,target\nx,s.ply,t.ply\n")
    monkeypatch.chdir(tmp_path)
    (pair,) = read_manifest("m.csv")
    assert pair.source == tmp_path.resolve() / "s.ply" and pair.gt is None


def test_read_lenient_formatting(tmp_path):
    m = write(
        tmp_path / "loose.csv",
        "\ufeff Pair_ID , Source ,notes, TARGET \r\n"
        "\r\n"
        "  p1 ,  s1.ply , anything here ,t1.ply  \r\n"
        ",,,\r\n"
        '"p,2","dir with space/s 2.ply",x,"t,2.ply"\r\n'
        "\r\n",
    )
    pairs = read_manifest(m)
    assert [p.pair_id for p in pairs] == ["p1", "p,2"]
    assert pairs[0].source == tmp_path / "s1.ply" and pairs[0].target == tmp_path / "t1.ply"
    assert pairs[1].source == tmp_path / "dir with space/s 2.ply" and pairs[1].target == tmp_path / "t,2.ply"
    assert all(p.gt is None for p in pairs)


def test_read_does_not_check_file_existence(tmp_path):
    m = write(tmp_path / "m.csv", "pair_id,source,target,gt\nghost,nope.ply,nope2.ply,nope.txt\n")
    (pair,) = read_manifest(m)
    assert not pair.source.exists() and pair.gt == tmp_path / "nope.txt"


def test_pairspec_is_frozen(tmp_path):
    p = PairSpec("a", tmp_path / "s.ply", tmp_path / "t.ply", None)
    with pytest.raises(AttributeError):
        p.pair_id = "b"  # type: ignore[misc]


def test_missing_manifest(tmp_path):
    m = tmp_path / "missing.csv"
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "does not exist")


@pytest.mark.parametrize("content", ["", "\n\n  \n"])
def test_empty_manifest(tmp_path, content):
    m = write(tmp_path / "empty.csv", content)
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "is empty")


def test_manifest_is_directory(tmp_path):
    d = tmp_path / "dir.csv"
    d.mkdir()
    with pytest.raises(ManifestError) as ei:
        read_manifest(d)
    assert_error(ei, d, "not a regular file")


def test_manifest_not_utf8(tmp_path):
    m = tmp_path / "latin.csv"
    m.write_bytes(b"pair_id,source,target\n\xe9,\xff,\xfe\n")
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "not UTF-8")


def test_header_only(tmp_path):
    m = write(tmp_path / "header_only.csv", "pair_id,source,target,gt\n\n")
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "no data rows")


@pytest.mark.parametrize("missing", ["pair_id", "source", "target"])
def test_missing_required_column(tmp_path, missing):
    cols = [c for c in ("pair_id", "source", "target", "gt") if c != missing]
    m = write(tmp_path / "cols.csv", ",".join(cols) + "\n" + ",".join("v" for _ in cols) + "\n")
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, f"missing required column '{missing}'", "line 1")


def test_duplicate_column(tmp_path):
    m = write(tmp_path / "dupcol.csv", "pair_id,source,target,source\na,b,c,d\n")
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "duplicate column", "source")


def test_duplicate_pair_id(tmp_path):
    m = write(tmp_path / "dup.csv",
              "pair_id,source,target\nscan1,a.ply,b.ply\nscan2,c.ply,d.ply\n\nscan1,e.ply,f.ply\n")
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "duplicate pair_id 'scan1'", "line 2", "line 5")


@pytest.mark.parametrize(
    "row, keyword",
    [
        (",a.ply,b.ply", "empty 'pair_id' cell"),
        ("p,,b.ply", "empty 'source' cell"),
        ("p,a.ply,   ", "empty 'target' cell"),
        ("p,a.ply", "empty 'target' cell"),  # short row
    ],
)
def test_empty_cells(tmp_path, row, keyword):
    m = write(tmp_path / "cells.csv", f"pair_id,source,target\nok,x.ply,y.ply\n{row}\n")
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, keyword, "line 3")


@pytest.mark.parametrize(
    "pair_id, keyword",
    [("a/b", "'/'"), ("a\\b", "'\\'"), ("..", "is '..'"), (".", "is '.'"), ("a\x00b", "NUL"), ("a\tb", "control")],
)
def test_unsafe_pair_id(tmp_path, pair_id, keyword):
    m = write(tmp_path / "unsafe.csv", f'pair_id,source,target\n"{pair_id}",a.ply,b.ply\n')
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "line 2", keyword, "unsafe as a file name")


def test_all_row_problems_reported_together(tmp_path):
    m = write(tmp_path / "many.csv", "pair_id,source,target\na,,b\nc/d,e,f\na2,x,y\na2,z,w\n")
    with pytest.raises(ManifestError) as ei:
        read_manifest(m)
    assert_error(ei, m, "3 problem(s)", "line 2", "line 3", "line 5", "duplicate pair_id 'a2'")


def test_safe_unusual_pair_ids_accepted(tmp_path):
    m = write(tmp_path / "ok.csv", "pair_id,source,target\nbun000-bun045 (v2),a.ply,b.ply\n.hidden,c.ply,d.ply\n")
    assert [p.pair_id for p in read_manifest(m)] == ["bun000-bun045 (v2)", ".hidden"]


# ----------------------------------------------------------------------------------------------------
# write_manifest
# ----------------------------------------------------------------------------------------------------


def test_write_read_round_trip(tmp_path):
    out = tmp_path / "out" / "pairs.csv"
    pairs = [
        PairSpec("a", tmp_path / "out/data/a.ply", tmp_path / "out/data/a_t.ply", tmp_path / "out/gt/a.txt"),
        PairSpec("b,c", tmp_path / "elsewhere/b s.ply", tmp_path / "out/b.pcd", None),
    ]
    write_manifest(out, pairs)
    lines = out.read_text().splitlines()
    assert lines[0] == "pair_id,source,target,gt"
    assert lines[1] == "a,data/a.ply,data/a_t.ply,gt/a.txt"  # relative inside the manifest folder
    assert lines[2] == f'"b,c",{tmp_path / "elsewhere/b s.ply"},b.pcd,'  # absolute outside it
    assert read_manifest(out) == pairs
    assert [p.name for p in out.parent.iterdir()] == ["pairs.csv"]  # no temp file left


def test_write_without_gt_has_no_gt_column(tmp_path):
    out = tmp_path / "nogt.csv"
    write_manifest(out, [PairSpec("a", tmp_path / "a.ply", tmp_path / "b.ply", None)])
    assert out.read_text() == "pair_id,source,target\na,a.ply,b.ply\n"


def test_write_relative_to_other_folder(tmp_path):
    out = tmp_path / "m.csv"
    pairs = [PairSpec("a", tmp_path / "data/a.ply", tmp_path / "data/b.ply", None)]
    write_manifest(out, pairs, relative_to=tmp_path / "data")
    assert out.read_text().splitlines()[1] == "a,a.ply,b.ply"


@pytest.mark.parametrize(
    "pairs, keyword",
    [
        ([], "without pairs"),
        ([PairSpec("a/b", Path("/s.ply"), Path("/t.ply"), None)], "'/'"),
        ([PairSpec("a", Path("/s.ply"), Path("/t.ply"), None)] * 2, "duplicate pair_id 'a'"),
    ],
)
def test_write_rejects_bad_pairs(tmp_path, pairs, keyword):
    out = tmp_path / "bad.csv"
    with pytest.raises(ManifestError) as ei:
        write_manifest(out, pairs)
    assert_error(ei, out, keyword)
    assert not out.exists()


# ----------------------------------------------------------------------------------------------------
# build_manifest
# ----------------------------------------------------------------------------------------------------


def empty_folders(tmp_path: Path) -> tuple[Path, Path]:
    """Two new empty folders ``a`` (source) and ``b`` (target) under ``tmp_path``."""
    src, tgt = tmp_path / "a", tmp_path / "b"
    src.mkdir()
    tgt.mkdir()
    return src, tgt


@pytest.fixture
def folders(tmp_path):
    src, tgt, gt = tmp_path / "src", tmp_path / "tgt", tmp_path / "gt"
    for d in (src, tgt, gt):
        d.mkdir()
    for name in ("s01.ply", "s02.PCD", "s03.xyz", "only_src.ply", "notes.md", ".hidden.ply"):
        (src / name).write_text("x")
    for name in ("s01.pcd", "s02.ply", "s03.pts", "only_tgt.txt", "readme.json"):
        (tgt / name).write_text("x")
    (tgt / "s04.ply").mkdir()  # a folder with a cloud-like name is not a file
    for name in ("s01.txt", "s03.txt", "unused.txt"):
        (gt / name).write_text("x")
    return src, tgt, gt


def test_build_matches_stems(folders, caplog):
    src, tgt, gt = folders
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        pairs = build_manifest(src, tgt, gt)
    assert [p.pair_id for p in pairs] == ["s01", "s02", "s03"]
    assert pairs[0] == PairSpec("s01", src / "s01.ply", tgt / "s01.pcd", gt / "s01.txt")
    assert pairs[1].source == src / "s02.PCD" and pairs[1].target == tgt / "s02.ply" and pairs[1].gt is None
    assert pairs[2].gt == gt / "s03.txt"
    text = caplog.text
    assert "only_src" in text and "only_tgt" in text  # unmatched stems listed
    assert "s02" in text  # missing ground truth listed
    assert f"1 ground-truth file(s) in {gt} match no pair: unused.txt" in text


def test_a_ground_truth_extension_in_capitals_pairs_as_a_cloud_extension_does(folders, caplog):
    """``s02.TXT`` is ``s02``'s ground truth, as ``s02.PCD`` is its source; beside ``s01.txt`` an
    ``s01.TXT`` (a case-sensitive file system) loses to the exact name, with a warning."""
    src, tgt, gt = folders
    (gt / "s02.TXT").write_text("x")
    (gt / "s01.TXT").write_text("x")
    (gt / "s03.Txt").write_text("x")
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        pairs = build_manifest(src, tgt, gt)
    assert [p.gt for p in pairs] == [gt / "s01.txt", gt / "s02.TXT", gt / "s03.txt"]
    assert (f"2 ground-truth file(s) in {gt} ignored, their stem has one already: s01.TXT (beside s01.txt), "
            "s03.Txt (beside s03.txt)") in caplog.text


def test_a_broken_or_folder_ground_truth_is_kept_so_its_pair_fails_loudly(folders, caplog):
    """A broken link ``s03.txt`` or a folder ``s02.txt`` in the ground-truth folder was left out, so the pair had
    no ground truth and a ``--min-success`` gate passed it unmeasured (found by an audit); a folder named like a
    cloud showed only as an unmatched stem of the other side."""
    src, tgt, gt = folders
    (gt / "s03.txt").unlink()
    (gt / "s03.txt").symlink_to(gt / "gone.txt")
    (gt / "s02.txt").mkdir()
    (src / "s04.ply").write_text("x")  # the target's s04.ply is a folder
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        pairs = build_manifest(src, tgt, gt)
    assert [(p.pair_id, p.gt) for p in pairs] == [("s01", gt / "s01.txt"), ("s02", gt / "s02.txt"),
                                                  ("s03", gt / "s03.txt")]
    assert "have no ground truth" not in caplog.text
    assert (f"{tgt}: target folder has subfolders or other entries named like point cloud files, left out (not "
            "files): s04.ply") in caplog.text
    (gt / "s01.TXT").write_text("x")  # beside a folder s01.txt, a file s01.TXT is the ground truth
    (gt / "s01.txt").unlink()
    (gt / "s01.txt").mkdir()
    assert build_manifest(src, tgt, gt)[0].gt == gt / "s01.TXT"


def test_build_without_gt(folders):
    src, tgt, _ = folders
    pairs = build_manifest(str(src), str(tgt))
    assert len(pairs) == 3 and all(p.gt is None for p in pairs)


def test_build_then_write_then_read(folders, tmp_path):
    src, tgt, gt = folders
    pairs = build_manifest(src, tgt, gt)
    out = tmp_path / "pairs.csv"
    write_manifest(out, pairs)
    assert read_manifest(out) == pairs
    assert "src/s01.ply" in out.read_text()


def test_build_no_match(tmp_path):
    src, tgt = empty_folders(tmp_path)
    (src / "one.ply").write_text("x")
    (tgt / "two.ply").write_text("x")
    with pytest.raises(ManifestError) as ei:
        build_manifest(src, tgt)
    assert "no matching file stems" in str(ei.value) and "a (1 cloud)" in str(ei.value)


def test_subfolders_with_clouds_are_named_not_searched(tmp_path, caplog):
    """One folder per site: nested clouds are not paired, and a user got no hint why ('no matching file
    stems', or fewer pairs than expected)."""
    src, tgt = tmp_path / "a", tmp_path / "b"
    for d in (src / "site1", tgt / "site1", src / "empty"):
        d.mkdir(parents=True)
    for d in (src / "site1", tgt / "site1"):
        (d / "scan.ply").write_text("x")
    (src / "only.ply").write_text("x")
    with pytest.raises(ManifestError) as ei:
        build_manifest(src, tgt)
    assert str(ei.value).endswith(f"; subfolders are not searched: {src}: 1 subfolder(s) with point clouds "
                                  f"(site1/); {tgt}: 1 subfolder(s) with point clouds (site1/)")
    (tgt / "only.ply").write_text("x")
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        assert [p.pair_id for p in build_manifest(src, tgt)] == ["only"]
    assert "only the folders' own files pair; subfolders are not searched" in caplog.text


def test_csv_files_are_not_taken_for_clouds_by_folder_pairing(folders):
    """``.csv`` clouds are read when named, but a folder's CSV files (logs, a manifest, ``s01.csv`` beside
    ``s01.ply``) are tables far more often: they neither pair nor make a stem ambiguous."""
    src, tgt, gt = folders
    for name in ("s01.csv", "pairs.csv"):
        (src / name).write_text("x")
    (tgt / "pairs.csv").write_text("x")
    assert [p.pair_id for p in build_manifest(src, tgt, gt)] == ["s01", "s02", "s03"]


def test_left_out_csv_files_are_named_where_they_would_have_paired(tmp_path, caplog):
    src, tgt = empty_folders(tmp_path)
    for d in (src, tgt):
        (d / "r1.csv").write_text("x")
    with pytest.raises(ManifestError) as ei:
        build_manifest(src, tgt)
    assert str(ei.value) == (f"no matching file stems between {src} (0 clouds) and {tgt} (0 clouds); .csv files are "
                             "left out (in a folder of scans they are usually tables; name .csv clouds in a manifest): "
                             f"{src}: r1.csv; {tgt}: r1.csv")
    for d in (src, tgt):
        (d / "r2.ply").write_text("x")
    (src / "log.csv").write_text("x")  # pairs with nothing: not worth a warning
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        assert [p.pair_id for p in build_manifest(src, tgt)] == ["r2"]
    assert caplog.messages == ["1 stem(s) would pair with .csv files, which are left out (in a folder of scans they "
                               "are usually tables; name .csv clouds in a manifest): r1"]


def test_build_leaves_an_ambiguous_stem_out_and_pairs_the_rest(folders, caplog):
    """``a.ply`` beside ``a.laz`` (a scan just converted) stopped ``gctr manifest``, and with it the documented
    ``manifest && batch`` cron line: no pair was registered that night. The stem is left out with a warning
    naming its files; the other stems pair."""
    src, tgt, gt = folders
    (src / "s01.pcd").write_text("x")
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        assert [p.pair_id for p in build_manifest(src, tgt, gt)] == ["s02", "s03"]
    assert caplog.messages[0] == (f"{src}: source folder has several point cloud files with the same stem, left "
                                  "out (move or rename one): s01 (s01.pcd, s01.ply)")
    for stem in ("s02", "s03"):
        (tgt / f"{stem}.xyz").write_text("x")
    with pytest.raises(ManifestError) as ei:
        build_manifest(src, tgt)
    assert str(ei.value) == (f"no matching file stems between {src} (5 clouds) and {tgt} (6 clouds); left out as "
                             "ambiguous (several files with one stem): s01, s02, s03")


def test_build_skips_stems_that_begin_or_end_with_blank_space(folders, caplog):
    """A stem ``' s01'`` was written as the pair id ``' s01'``, which the manifest reader strips: it clashed
    with ``s01`` (``gctr batch`` refused the whole manifest) or was renamed silently."""
    src, tgt, gt = folders
    for d in (src, tgt):
        (d / " s01.ply").write_text("x")
        (d / "s04 .ply").write_text("x")
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        pairs = build_manifest(src, tgt, gt)
    assert [p.pair_id for p in pairs] == ["s01", "s02", "s03"]
    assert ("skipping 2 stem(s) unsafe as pair_id: ' s01' (begins or ends with blank space), 's04 ' (begins or "
            "ends with blank space)") in caplog.messages


def test_build_missing_folders_and_same_folder(folders, tmp_path):
    src, tgt, _ = folders
    with pytest.raises(ManifestError, match="target folder does not exist"):
        build_manifest(src, tmp_path / "nope")
    with pytest.raises(ManifestError, match="ground-truth folder does not exist"):
        build_manifest(src, tgt, tmp_path / "nogt")
    with pytest.raises(ManifestError, match="same"):
        build_manifest(src, src)


def test_build_skips_unsafe_stems(tmp_path, caplog):
    src, tgt = empty_folders(tmp_path)
    for d in (src, tgt):
        (d / "good.ply").write_text("x")
        (d / "bad\tname.ply").write_text("x")
    with caplog.at_level(logging.WARNING, logger="gctr_cli.manifest"):
        pairs = build_manifest(src, tgt)
    assert [p.pair_id for p in pairs] == ["good"]
    assert "bad\\tname" in caplog.text and "control character" in caplog.text


def test_a_record_spanning_lines_is_named_by_its_first_line(tmp_path):
    """A quoted cell may hold a line break: the problem is reported at the line where its record starts."""
    path = tmp_path / "pairs.csv"
    path.write_text('pair_id,source,target\na,x.ply,y.ply\n\n"c\nd",x.ply,y.ply\ne,x.ply\n', newline="")
    with pytest.raises(ManifestError) as ei:
        read_manifest(path)
    assert "line 4: pair_id 'c\\nd' contains a control character" in str(ei.value)
    assert "line 6: empty 'target' cell" in str(ei.value)


def test_names_that_are_not_utf8_are_left_out_or_refused_with_a_message(tmp_path, caplog):
    """A Latin-1 ``café.ply`` of an old share: ``gctr manifest`` ended in a traceback and wrote nothing (one
    file cost the night its other pairs); a manifest in a folder with such a name stopped ``gctr batch``
    with a traceback and exit 1. ``x..y`` is a plain name (only '.' and '..' are not)."""
    import os

    for side in ("s", "t"):
        (tmp_path / side).mkdir()
        for name in (b"caf\xe9.ply", b"ok.ply", b"x..y.ply"):
            with open(os.path.join(os.fsencode(tmp_path / side), name), "w") as fh:
                fh.write("0 0 0\n")
    with caplog.at_level(logging.WARNING, logger="gctr_cli"):
        pairs = build_manifest(tmp_path / "s", tmp_path / "t")
    assert [p.pair_id for p in pairs] == ["ok", "x..y"]
    assert "names are not valid UTF-8, left out (rename them" in caplog.text and "caf\\xe9.ply" in caplog.text
    write_manifest(tmp_path / "pairs.csv", pairs)

    odd = os.path.join(os.fsencode(tmp_path), b"dir\xe9")
    os.mkdir(odd)
    with open(os.path.join(odd, b"pairs.csv"), "w") as fh:
        fh.write("pair_id,source,target\nok,s/ok.ply,t/ok.ply\n")
    with pytest.raises(ManifestError, match=r"line 2: path not valid UTF-8 \(source .*dir\\xe9/s/ok.ply"):
        read_manifest(os.fsdecode(os.path.join(odd, b"pairs.csv")))
    os.mkdir(os.path.join(odd, b"s"))
    with pytest.raises(ManifestError, match=r"dir\\xe9/s: source folder's path is not valid UTF-8"):
        build_manifest(os.fsdecode(os.path.join(odd, b"s")), tmp_path / "t")
