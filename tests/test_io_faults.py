"""Each class of malformed input issue 11 names gives its own message, naming the path the user
wrote, in words, without control characters, within a bounded time and memory."""

from __future__ import annotations

import os
import re
import struct
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from conftest import read_csv, write_manifest_rows

from data_scripts import fake_engine
from gctr_cli.config import Config
from gctr_cli.io import PointCloudError, load_point_cloud, save_point_cloud
from gctr_cli.io.errors import MAX_MESSAGE, clean, escaped

RNG = np.random.default_rng(11)
PTS = RNG.normal(size=(50, 3))
PYTHON_WORDS = re.compile(r"Error\b|Exception|Traceback|errno|\bint\(\)|could not convert|invalid literal")


def load_error(path: Path, *keywords: str, shown: str | None = None) -> str:
    """The message of loading ``path``; checks it names ``shown`` (default: the path as given), has
    the keywords, no control characters, no Python exception text and a bounded length."""
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    msg = str(ei.value)
    assert msg.startswith(f"{shown or path}:"), msg
    for kw in keywords:
        assert kw in msg, f"{kw!r} not in {msg!r}"
    assert not re.search(r"[\x00-\x1f\x7f-\x9f]", msg), repr(msg)
    assert not PYTHON_WORDS.search(msg), msg
    assert len(msg) <= MAX_MESSAGE, len(msg)
    return msg


def ascii_ply_face_first(face_line: str) -> bytes:
    header = ("ply\nformat ascii 1.0\nelement face 2\nproperty list uchar int vertex_indices\n"
              f"element vertex {len(PTS)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    faces = f"{face_line}\n3 1 2 3\n"
    verts = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in PTS)
    return (header + faces + verts).encode()


# ----------------------------------------------------------------------------------------------------
# structure: element lines, list lengths, declared sizes
# ----------------------------------------------------------------------------------------------------


def test_face_before_vertex_with_a_short_list_line_is_an_error_not_shifted_vertices(tmp_path):
    good = tmp_path / "good.ply"
    good.write_bytes(ascii_ply_face_first("3 0 1 2"))
    np.testing.assert_allclose(load_point_cloud(good), PTS, atol=1e-6)
    short = tmp_path / "short.ply"
    short.write_bytes(ascii_ply_face_first("3 0 1"))  # used to shift every vertex value by one
    load_error(short, "line 10", "declares 3 items but the line has only 2")
    long = tmp_path / "long.ply"
    long.write_bytes(ascii_ply_face_first("3 0 1 2 7"))
    load_error(long, "line 10", "has 5 values")


def test_vertex_line_with_a_missing_value_names_its_line(tmp_path):
    text = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\n"
            "end_header\n1 2 3\n4 5\n7 8 9\n10 11 12\n")
    (tmp_path / "v.ply").write_text(text)
    load_error(tmp_path / "v.ply", "line 9", "vertex has 2 values, the header declares 3")


@pytest.mark.parametrize("fmt", ["ascii", "binary"])
def test_negative_list_length_is_refused_at_once(tmp_path, fmt):
    path = tmp_path / f"neg_{fmt}.ply"
    if fmt == "ascii":
        path.write_bytes(ascii_ply_face_first("-1 0 1 2"))
        keywords = ("line 10", "bad list length '-1'")
    else:
        header = ("ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list char int vertex_indices\n"
                  f"element vertex {len(PTS)}\nproperty double x\nproperty double y\nproperty double z\nend_header\n")
        body = struct.pack("<b3i", -1, 0, 1, 2) + PTS.astype("<f8").tobytes()
        path.write_bytes(header.encode() + body)
        keywords = ("negative list length -1",)
    t0 = time.perf_counter()
    load_error(path, *keywords)
    assert time.perf_counter() - t0 < 1.0


@pytest.mark.parametrize("count", ["1e20", "99999999999999999999", "-5", "0x10"])
def test_absurd_element_counts_are_refused_in_words(tmp_path, count):
    text = (f"ply\nformat binary_little_endian 1.0\nelement vertex {count}\nproperty double x\n"
            "property double y\nproperty double z\nend_header\n").encode() + PTS.astype("<f8").tobytes()
    (tmp_path / "c.ply").write_bytes(text)
    load_error(tmp_path / "c.ply", "vertices" if count.isdigit() else "bad element count")
    pcd = (f"VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 50\nHEIGHT 1\nPOINTS {count}\n"
           "DATA binary\n").encode() + PTS.astype("<f8").tobytes()
    (tmp_path / "c.pcd").write_bytes(pcd)
    load_error(tmp_path / "c.pcd", "truncated" if count.isdigit() else "bad POINTS value")


def test_declared_sizes_are_checked_against_the_file_before_allocating(tmp_path):
    header = ("ply\nformat binary_little_endian 1.0\nelement face 2000000000\nproperty list uchar int vertex_indices\n"
              "element vertex 50\nproperty double x\nproperty double y\nproperty double z\nend_header\n")
    (tmp_path / "faces.ply").write_bytes(header.encode() + PTS.astype("<f8").tobytes())
    tracemalloc.start()
    load_error(tmp_path / "faces.ply", "truncated or corrupt", "2000000000 'face' elements")
    ascii_header = header.replace("binary_little_endian", "ascii")
    (tmp_path / "faces_ascii.ply").write_bytes(ascii_header.encode() + b"3 0 1 2\n" * 10)
    load_error(tmp_path / "faces_ascii.ply", "at least 2 bytes per value")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 8 << 20, peak


def test_compressed_pcd_declaring_4_gb_is_refused_without_allocating(tmp_path):
    n = 1 << 28  # x y z float32: 3 GiB uncompressed, plus padding field -> 4 GiB
    header = (f"VERSION 0.7\nFIELDS x y z _\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
              f"POINTS {n}\nDATA binary_compressed\n").encode()
    body = struct.pack("<II", 120, (n * 16) & 0xFFFFFFFF) + bytes(120)
    (tmp_path / "bomb.pcd").write_bytes(header + body)
    tracemalloc.start()
    load_error(tmp_path / "bomb.pcd", "binary_compressed")
    n = 1 << 26  # 1 GiB declared, sizes consistent: refused by the LZF expansion bound
    header = header.replace(b"268435456", str(n).encode())
    (tmp_path / "bomb2.pcd").write_bytes(header + struct.pack("<II", 120, n * 16) + bytes(120))
    load_error(tmp_path / "bomb2.pcd", "LZF expands at most 88-fold")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 8 << 20, peak


def test_lzf_data_that_decompresses_to_the_wrong_size_is_refused(tmp_path):
    import lzf

    raw = PTS.astype("<f4").T.tobytes()
    comp = lzf.compress(raw, 2 * len(raw) + 16)  # random floats do not shrink: allow growth
    header = (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 50\nHEIGHT 1\nPOINTS 50\n"
              b"DATA binary_compressed\n")
    (tmp_path / "ok.pcd").write_bytes(header + struct.pack("<II", len(comp), len(raw)) + comp)
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "ok.pcd"), PTS.astype(np.float32))
    bad = bytearray(comp)
    bad[0] = 0xFF  # a back reference before the start of the output
    (tmp_path / "bad.pcd").write_bytes(header + struct.pack("<II", len(comp), len(raw)) + bytes(bad))
    load_error(tmp_path / "bad.pcd", "corrupt binary_compressed PCD data")


def test_text_without_line_ends_is_refused_with_bounded_memory(tmp_path):
    path = tmp_path / "oneline.xyz"
    path.write_bytes(b"1.0 2.0 3.0 " * 1_000_000)  # 12 MB, no newline
    tracemalloc.start()
    load_error(path, "line is longer than 1024 KiB")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 24 << 20, peak  # a few MiB of blocks, not the file many times over
    ply = tmp_path / "oneline.ply"
    ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                    b"property float z\nend_header\n" + b"1 2 3 " * 500_000)
    load_error(ply, "longer than 1024 KiB")


# ----------------------------------------------------------------------------------------------------
# messages
# ----------------------------------------------------------------------------------------------------


def test_control_characters_and_huge_names_never_reach_the_message(tmp_path):
    name = "x\x00\x1b[31mRED\x1b[0m\u202e" + "n" * 60_000
    header = (f"ply\nformat ascii 1.0\nelement vertex 1\nproperty float {name}\nproperty float y\n"
              "property float z\nend_header\n1 2 3\n").encode()
    (tmp_path / "esc.ply").write_bytes(header)
    msg = load_error(tmp_path / "esc.ply", "has no x field")
    assert "RED" in msg and "\x1b" not in msg and "..." in msg
    pcd = b"VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 5\nDATA \x1b]0;pwned\x07\n"
    (tmp_path / "esc.pcd").write_bytes(pcd)
    load_error(tmp_path / "esc.pcd", "unknown DATA type")
    (tmp_path / "esc.xyz").write_bytes(b"X Y Z\n" + b"1 2 3\n" * 20 + b"1 2 \x1b[2J\n")
    load_error(tmp_path / "esc.xyz", "line 22", "non-numeric value")


def test_a_file_name_with_control_characters_is_cleaned_too(tmp_path):
    path = tmp_path / "bad\nname\x1b.ply"
    path.write_bytes(b"not a ply")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert "bad?name?.ply: not a PLY file" in str(ei.value)


def test_a_file_name_that_is_not_utf8_is_shown_with_its_byte_escaped(tmp_path):
    path = Path(os.fsdecode(os.fsencode(tmp_path) + b"/bad\xffname.ply"))  # a lone surrogate in the str
    path.write_bytes(b"not a ply")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert "bad\\xffname.ply: not a PLY file" in str(ei.value)  # as the summary, report and manifest show it
    str(ei.value).encode("utf-8")  # printable and writable to a UTF-8 CSV cell


def test_messages_and_reports_show_an_undecodable_byte_alike():
    name = os.fsdecode(b"caf\xe9.ply")
    assert clean(name) == escaped(name) == "caf\\xe9.ply"
    assert escaped("a\ud800b") == "a\ufffdb"  # a lone surrogate that stands for no byte


# ----------------------------------------------------------------------------------------------------
# symbolic links: judged by the name the user gave
# ----------------------------------------------------------------------------------------------------


def test_dvc_style_link_to_an_extension_less_cache_file_is_read(tmp_path):
    cache = tmp_path / ".dvc" / "cache" / "ab" / "12cd34ef"
    cache.parent.mkdir(parents=True)
    save_point_cloud(tmp_path / "real.ply", PTS)
    os.replace(tmp_path / "real.ply", cache)
    (tmp_path / "scan.ply").symlink_to(cache)
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "scan.ply"), PTS)
    cache.write_bytes(b"garbage")
    load_error(tmp_path / "scan.ply", "not a PLY file")  # the link's name, not the cache file's


@pytest.mark.parametrize("kind, keywords", [
    ("dev_zero", ("is a device, not a regular file", "symbolic link")),
    ("folder", ("is a folder, not a regular file", "symbolic link")),
    ("loop", ("symbolic link loop",)),
    ("broken", ("broken symbolic link", "gone.ply")),
])
def test_links_to_unreadable_things_say_what_they_point_to(tmp_path, kind, keywords):
    link = tmp_path / "scan.ply"
    if kind == "dev_zero":
        link.symlink_to("/dev/zero")
    elif kind == "folder":
        (tmp_path / "dir").mkdir()
        link.symlink_to(tmp_path / "dir")
    elif kind == "loop":
        (tmp_path / "other.ply").symlink_to(link)
        link.symlink_to(tmp_path / "other.ply")
    else:
        link.symlink_to(tmp_path / "gone.ply")
    load_error(link, *keywords)


def test_a_folder_without_an_extension_is_named_a_folder(tmp_path):
    (tmp_path / "scans").mkdir()
    load_error(tmp_path / "scans", "is a folder, not a point cloud file")


def test_batch_with_a_symlink_loop_runs_every_pair_and_names_the_link(tmp_path):
    from gctr_cli.batch import run_batch
    from gctr_cli.manifest import read_manifest

    rng = np.random.default_rng(3)
    src = rng.normal(size=(200, 3))
    save_point_cloud(tmp_path / "s.ply", src)
    save_point_cloud(tmp_path / "t.ply", src * 2 + 1)
    (tmp_path / "a.ply").symlink_to(tmp_path / "b.ply")
    (tmp_path / "b.ply").symlink_to(tmp_path / "a.ply")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "link.ply").symlink_to(tmp_path / "s.ply")
    m = write_manifest_rows(tmp_path / "pairs.csv", [
        {"pair_id": "loop", "source": "a.ply", "target": "t.ply"},
        {"pair_id": "good", "source": "data/link.ply", "target": "t.ply"},
    ])
    pairs = read_manifest(m)
    assert pairs[0].source == tmp_path / "a.ply" and pairs[1].source == tmp_path / "data" / "link.ply"
    run_batch(pairs, Config(), tmp_path / "out", workers=1, register_fn=fake_engine.register)
    _, rows = read_csv(tmp_path / "out" / "transforms.csv")
    by_id = {r["pair_id"]: r for r in rows}
    assert by_id["good"]["status"] == "ok"
    assert by_id["loop"]["status"] == "failed"
    assert by_id["loop"]["message"].startswith(f"{tmp_path / 'a.ply'}: is a symbolic link loop")


# ----------------------------------------------------------------------------------------------------
# locale exports
# ----------------------------------------------------------------------------------------------------


def test_decimal_commas_with_tabs_or_semicolons_are_read_and_blank_separated_ones_explained(tmp_path):
    pts = np.round(RNG.normal(size=(30, 3)) * 100, 3)

    def rows(sep: str, dec: str) -> str:
        return "".join(sep.join(f"{v:.3f}".replace(".", dec) for v in p) + "\n" for p in pts)

    (tmp_path / "de_tab.txt").write_text("X\tY\tZ\n" + rows("\t", ","))
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "de_tab.txt"), pts)
    (tmp_path / "de_semi.xyz").write_text("X;Y;Z\n" + rows(";", ","))
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "de_semi.xyz"), pts)
    (tmp_path / "semi.xyz").write_text(rows(";", "."))
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "semi.xyz"), pts)
    (tmp_path / "tab.xyz").write_text(rows("\t", "."))
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "tab.xyz"), pts)
    (tmp_path / "de_blank.xyz").write_text(rows(" ", ","))
    load_error(tmp_path / "de_blank.xyz", "line 1", "decimal commas separated by blanks")


def test_writing_to_a_fifo_writes_into_it_instead_of_replacing_it(tmp_path):
    """/dev/null, /dev/stdout and FIFOs are written into: an atomic replace would swap the special file
    for a regular one (as root, /dev/null itself)."""
    import stat
    import threading

    from gctr_cli.io import write_matrix

    fifo = tmp_path / "pipe.txt"
    os.mkfifo(fifo)
    received = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()), daemon=True)
    reader.start()
    write_matrix(fifo, np.eye(4))
    reader.join(timeout=10)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still the FIFO
    assert received and received[0].decode().splitlines()[0].split() == ["1", "0", "0", "0"]
