"""Tests for gctr_cli.io: point cloud readers/writers, validation, matrix I/O."""

from __future__ import annotations

import gzip
import logging
import os
import struct
from pathlib import Path

import numpy as np
import pytest

from gctr_cli import fsutil
from gctr_cli.geometry import random_rotation, to_matrix
from gctr_cli.io import (
    SUPPORTED_EXTENSIONS,
    MatrixError,
    PointCloudError,
    format_matrix,
    load_point_cloud,
    read_matrix,
    read_point_cloud,
    save_point_cloud,
    write_matrix,
)
from gctr_cli.io.cloud import COARSE_STEP_MIN_POINTS, COARSE_STEP_SAMPLE, PointCloud, coarse_step_note

DATA = Path("/work/shared/data")
BUN000 = DATA / "stanford/bunny/scans/bun000.ply"
ZIPPER4 = DATA / "stanford/bunny/reconstruction/bun_zipper_res4.ply"
REDKITCHEN0 = DATA / "real/3dmatch_redkitchen/cloud_bin_0.ply"
PCD_DIR = DATA / "stanford/bunny/pcl_pcd"
GT_BUN4 = PCD_DIR / "gt_bun4_to_bun0.txt"

needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared real data not available")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def cloud(rng) -> np.ndarray:
    return rng.normal(size=(200, 3))


def o3d():
    return pytest.importorskip("open3d")


def o3d_cloud(points: np.ndarray):
    m = o3d()
    return m.geometry.PointCloud(m.utility.Vector3dVector(points))


def ply_header(fmt: str, elements: list[tuple[str, int, list[str]]]) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment test file"]
    for name, count, props in elements:
        lines.append(f"element {name} {count}")
        lines += [f"property {p}" for p in props]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def assert_error(exc_info, path: Path, *keywords: str) -> None:
    msg = str(exc_info.value)
    assert path.name in msg, msg
    for kw in keywords:
        assert kw in msg, f"{kw!r} not in {msg!r}"


# ----------------------------------------------------------------------------------------------------
# Real data files
# ----------------------------------------------------------------------------------------------------


@needs_data
def test_real_ascii_ply_with_range_grid():
    pts = load_point_cloud(BUN000)
    assert pts.shape == (40256, 3) and pts.dtype == np.float64
    # first vertex line of the file
    np.testing.assert_array_equal(pts[0], [-0.06325, 0.0359793, 0.0420873])
    ref = np.asarray(o3d().io.read_point_cloud(str(BUN000)).points)
    np.testing.assert_array_equal(pts, ref)


@needs_data
def test_real_ascii_ply_with_faces_and_extra_properties():
    pts = load_point_cloud(ZIPPER4)
    assert pts.shape == (453, 3)
    np.testing.assert_array_equal(pts[0], [-0.0312216, 0.126304, 0.00514924])
    np.testing.assert_array_equal(pts[1], [-0.0446774, 0.131204, 0.00570479])
    ref = np.asarray(o3d().io.read_point_cloud(str(ZIPPER4)).points)
    np.testing.assert_array_equal(pts, ref)


@needs_data
def test_real_binary_ply():
    pts = load_point_cloud(REDKITCHEN0)
    assert pts.shape == (258342, 3)
    raw = REDKITCHEN0.read_bytes()
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n") :]
    np.testing.assert_array_equal(pts, np.frombuffer(body, "<f4").reshape(-1, 3).astype(np.float64))
    ref = np.asarray(o3d().io.read_point_cloud(str(REDKITCHEN0)).points)
    np.testing.assert_array_equal(pts, ref)


@needs_data
@pytest.mark.parametrize(
    "name, n, first",
    [
        ("bun0.pcd", 397, [0.0054215998, 0.11349, 0.040748999]),  # has normals + curvature columns
        ("bun4.pcd", 361, [0.053026, 0.11349, 0.077131]),  # VERSION .5 header
        ("bunny.pcd", 397, [0.0054216, 0.11349, 0.040749]),
    ],
)
def test_real_ascii_pcd(name, n, first):
    path = PCD_DIR / name
    pts = load_point_cloud(path)
    assert pts.shape == (n, 3)
    np.testing.assert_array_equal(pts[0], first)
    np.testing.assert_array_equal(pts, np.asarray(o3d().io.read_point_cloud(str(path)).points))


@needs_data
def test_real_gt_matrix_with_comment_lines():
    T = read_matrix(GT_BUN4)
    assert T.shape == (4, 4)
    assert T[0, 0] == 0.826350588 and T[2, 3] == -0.0109223
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)


# ----------------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip_exact(tmp_path, cloud, binary):
    path = tmp_path / "c.ply"
    save_point_cloud(path, cloud, binary=binary)
    head = path.read_bytes()[:80]
    assert (b"binary_little_endian" in head) == binary
    np.testing.assert_array_equal(load_point_cloud(path), cloud)
    # and Open3D reads what we write
    np.testing.assert_array_equal(np.asarray(o3d().io.read_point_cloud(str(path)).points), cloud)


def test_ply_written_by_open3d(tmp_path, cloud):
    pc = o3d_cloud(cloud)
    pc.normals = o3d().utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (len(cloud), 1)))
    path = tmp_path / "o3d.ply"
    o3d().io.write_point_cloud(str(path), pc, write_ascii=False)
    np.testing.assert_array_equal(load_point_cloud(path), cloud)


def test_ply_big_endian_mixed_types_and_trailing_faces(tmp_path, rng):
    n = 50
    pts = rng.normal(size=(n, 3)).astype(">f4")
    dt = np.dtype([("red", "u1"), ("x", ">f4"), ("y", ">f4"), ("intensity", ">i2"), ("z", ">f4")])
    rec = np.zeros(n, dt)
    rec["red"], rec["x"], rec["y"], rec["z"] = 7, pts[:, 0], pts[:, 1], pts[:, 2]
    rec["intensity"] = -3
    faces = b"".join(struct.pack(">Biii", 3, i, i + 1, i + 2) for i in range(10))
    hdr = ply_header(
        "binary_big_endian",
        [
            ("vertex", n, ["uchar red", "float x", "float y", "short intensity", "float z"]),
            ("face", 10, ["list uchar int vertex_indices"]),
        ],
    )
    path = tmp_path / "be.ply"
    path.write_bytes(hdr + rec.tobytes() + faces)
    np.testing.assert_array_equal(load_point_cloud(path), pts.astype(np.float64))


def test_ply_integer_coordinates(tmp_path, rng):
    pts = rng.integers(-1000, 1000, size=(30, 3)).astype("<i4")
    path = tmp_path / "int.ply"
    path.write_bytes(ply_header("binary_little_endian", [("vertex", 30, ["int x", "int y", "int z"])]) + pts.tobytes())
    out = load_point_cloud(path)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, pts)


def test_ply_binary_element_with_lists_before_vertex(tmp_path, rng):
    pts = rng.normal(size=(20, 3))
    # element 'grid' with a list property comes *before* the vertices; the reader must walk it
    grid = struct.pack("<Bi", 1, 5) + struct.pack("<B", 0) + struct.pack("<Biii", 3, 1, 2, 3)
    hdr = ply_header(
        "binary_little_endian",
        [("grid", 3, ["list uchar int idx"]), ("vertex", 20, ["double x", "double y", "double z"])],
    )
    path = tmp_path / "pre.ply"
    path.write_bytes(hdr + grid + pts.astype("<f8").tobytes())
    np.testing.assert_array_equal(load_point_cloud(path), pts)


def test_ply_binary_vertex_with_list_property(tmp_path, rng):
    pts = rng.normal(size=(15, 3))
    body = b"".join(
        struct.pack("<d", p[0]) + struct.pack("<B", k) + struct.pack(f"<{k}h", *range(k))
        + struct.pack("<dd", p[1], p[2])
        for k, p in zip(range(15), pts)
    )
    hdr = ply_header(
        "binary_little_endian", [("vertex", 15, ["double x", "list uchar short tags", "double y", "double z"])]
    )
    path = tmp_path / "vl.ply"
    path.write_bytes(hdr + body)
    np.testing.assert_array_equal(load_point_cloud(path), pts)


def test_ply_vertex_list_properties_not_kept_are_named_once(tmp_path, rng, caplog):
    """Per-vertex lists (here a variable-length 'tags' and a fixed 'rgb_list') were dropped without a word."""
    pts = rng.normal(size=(12, 3))
    body = b"".join(struct.pack("<d", p[0]) + struct.pack("<B", k) + struct.pack(f"<{k}h", *range(k))
                    + struct.pack("<dd", p[1], p[2]) + struct.pack("<B3B", 3, 1, 2, 3) + struct.pack("<f", 0.5)
                    for k, p in zip(range(12), pts))
    hdr = ply_header("binary_little_endian", [("vertex", 12, ["double x", "list uchar short tags", "double y",
                                                             "double z", "list uchar uchar rgb_list", "float q"])])
    path = tmp_path / "vl.ply"
    path.write_bytes(hdr + body)
    caplog.set_level(logging.WARNING, logger="gctr_cli.io")
    cloud = read_point_cloud(path)
    np.testing.assert_array_equal(cloud.points, pts)
    np.testing.assert_array_equal(cloud.attributes["q"], np.full(12, 0.5, np.float32))
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: vertex list properties 'tags', 'rgb_list' not kept (gctr keeps one value per vertex and property)"]
    caplog.clear()
    load_point_cloud(path)  # coordinates only: nothing is dropped that was asked for
    assert not caplog.records


def test_ply_ascii_element_before_vertex_and_list_in_vertex(tmp_path, rng):
    pts = np.round(rng.normal(size=(12, 3)), 6)
    lines = ["2 7 8", "0", "1 9"]  # 'grid' element with a list
    for i, p in enumerate(pts.tolist()):
        k = i % 3
        lines.append(" ".join([repr(p[0]), str(k)] + ["4"] * k + [repr(p[1]), repr(p[2])]))
    hdr = ply_header(
        "ascii",
        [("grid", 3, ["list uchar int idx"]), ("vertex", 12, ["float x", "list uchar int tags", "float y", "float z"])],
    )
    path = tmp_path / "al.ply"
    path.write_bytes(hdr + ("\n".join(lines) + "\n").encode())
    np.testing.assert_array_equal(load_point_cloud(path), pts)


def test_ascii_ply_pcd_attribute_its_type_cannot_hold_is_kept_not_wrapped(tmp_path, rng, caplog):
    """`300` under `property uchar red` became 44 (numpy's cast wraps); `0.5` under `int` became 0."""
    pts = np.round(rng.normal(size=(12, 3)), 6)
    rows = [f"{x!r} {y!r} {z!r} {250 + i} {i / 2} {i}" for i, (x, y, z) in enumerate(pts.tolist())]
    path = tmp_path / "wide.ply"
    path.write_bytes(ply_header("ascii", [("vertex", 12, ["float x", "float y", "float z", "uchar red", "int q",
                                                          "ushort ok"])]) + ("\n".join(rows) + "\n").encode())
    caplog.set_level("WARNING", logger="gctr_cli.io")
    cloud = read_point_cloud(path)
    np.testing.assert_array_equal(cloud.attributes["red"], 250 + np.arange(12))
    np.testing.assert_array_equal(cloud.attributes["q"], np.arange(12) / 2)
    assert cloud.attributes["ok"].dtype == np.uint16  # a column that fits keeps its type
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: 'red' is declared uchar but holds values it cannot (e.g. 256; range 0..255, whole "
        "numbers); kept as float64",
        f"{path}: 'q' is declared int but holds values it cannot (e.g. 0.5; range -2147483648..2147483647, "
        "whole numbers); kept as float64"]
    caplog.clear()
    pcd = tmp_path / "wide.pcd"  # the same in an ASCII PCD
    pcd.write_text("VERSION .7\nFIELDS x y z red\nSIZE 4 4 4 1\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 12\nHEIGHT 1\n"
                   "POINTS 12\nDATA ascii\n" + "".join(f"{x} {y} {z} {250 + i}\n" for i, (x, y, z) in enumerate(pts)))
    np.testing.assert_array_equal(read_point_cloud(pcd).attributes["red"], 250 + np.arange(12))
    assert [r.getMessage() for r in caplog.records] == [
        f"{pcd}: 'red' is declared U 1 but holds values it cannot (e.g. 256; range 0..255, whole numbers); "
        "kept as float64"]
    # 64-bit fields: float64 rounds 2**64 - 1 up to 2**64, which is beyond, not at, the limit
    caplog.clear()
    pcd.write_text("VERSION .7\nFIELDS x y z t s\nSIZE 4 4 4 8 8\nTYPE F F F U I\nCOUNT 1 1 1 1 1\nWIDTH 12\nHEIGHT 1\n"
                   "POINTS 12\nDATA ascii\n" + "".join(f"{x} {y} {z} 18446744073709551615 9223372036854775807\n"
                                                      for x, y, z in pts))
    wide = read_point_cloud(pcd).attributes
    assert wide["t"].dtype == wide["s"].dtype == np.float64  # not wrapped to 0 and to -2**63
    assert [r.getMessage().split(" but ")[0] for r in caplog.records] == [f"{pcd}: 't' is declared U 8",
                                                                          f"{pcd}: 's' is declared I 8"]
    caplog.clear()  # below 2**63 the values fit, but text beyond 2**53 is rounded: said, not hidden
    pcd.write_text(pcd.read_text().replace("18446744073709551615 9223372036854775807", "1700000000123456789 7"))
    assert read_point_cloud(pcd).attributes["t"].dtype == np.uint64
    assert [r.getMessage() for r in caplog.records] == [
        f"{pcd}: 't' (U 8) holds whole numbers beyond 2**53, which text is read as float64 and rounds (e.g. "
        "1700000000123456768); its last digits may differ from the file"]


def test_ply_crlf_header(tmp_path, cloud):
    body = "\r\n".join(" ".join(repr(v) for v in p) for p in cloud.tolist())
    hdr = ("ply\r\nformat ascii 1.0\r\nelement vertex 200\r\n"
           "property double x\r\nproperty double y\r\nproperty double z\r\nend_header\r\n")
    path = tmp_path / "crlf.ply"
    path.write_bytes((hdr + body + "\r\n").encode())
    np.testing.assert_array_equal(load_point_cloud(path), cloud)


def test_ply_with_carriage_returns_only_says_so(tmp_path, cloud):
    """Classic Mac OS line ends: the message was "no 'end_header' in the first bytes", though the header
    has one."""
    body = "\r".join(" ".join(repr(v) for v in p) for p in cloud.tolist())
    hdr = ("ply\rformat ascii 1.0\relement vertex 200\r"
           "property double x\rproperty double y\rproperty double z\rend_header\r")
    path = tmp_path / "cr.ply"
    path.write_bytes((hdr + body + "\r").encode())
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "carriage return only")


def test_ply_truncated_binary(tmp_path, cloud):
    path = tmp_path / "trunc.ply"
    save_point_cloud(path, cloud)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "truncated", "header declares 200 vertices", f"only {200 * 24 - 100} bytes")


def test_ply_truncated_ascii(tmp_path, cloud):
    path = tmp_path / "trunc_ascii.ply"
    save_point_cloud(path, cloud, binary=False)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "truncated", "header declares 200 vertices")


def test_ply_random_bytes(tmp_path, rng):
    path = tmp_path / "noise.ply"
    path.write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "not a PLY file", "missing 'ply' magic")


@pytest.mark.parametrize("name, content, hint", [
    ("scan.ply", gzip.compress(b"ply\nformat ascii 1.0\n", mtime=0), "gzip-compressed: decompress it first"),
    ("scan.ply", b"0.1 0.2 0.3\n0.4 0.5 0.6\n", "text columns of numbers: name it .xyz"),
    ("scan.ply", b"LASF" + bytes(300), "content is LAS or LAZ: name it .las or .laz"),
    ("scan.pcd", b"ply\nformat ascii 1.0\nelement vertex 1\n", "content is PLY: name it .ply"),
    ("scan.pcd", b"1.5,2.5,3.5\n", "text columns of numbers"),
    ("scan.pcd", gzip.compress(b"VERSION 0.7\n", mtime=0), "gzip-compressed"),
    ("scan.ply", b"# .PCD v0.7\nVERSION 0.7\n", "content is PCD: name it .pcd"),
])
def test_a_file_of_another_kind_under_a_ply_or_pcd_name_is_named_for_what_it_is(tmp_path, name, content, hint):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, f"not a {name[-3:].upper()} file", hint)


@pytest.mark.parametrize(
    "header, keyword",
    [
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n", "end_header"),
        (b"ply\nelement vertex 3\nproperty float x\nend_header\n", "no 'format' line"),
        (b"ply\nformat ascii 1.0\nelement face 3\nproperty list uchar int v\nend_header\n", "no 'vertex' element"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nend_header\n", "no z field"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float128 x\nend_header\n", "unknown property type"),
        (b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", "bad element count"),
        (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unsupported format"),
        (b"ply\nformat ascii 1.0\nvertices 3\nend_header\n", "unrecognised keyword"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
         b"property float z\nend_header\n", "line 7: duplicate vertex property 'z'"),
    ],
)
def test_ply_broken_headers(tmp_path, header, keyword):
    path = tmp_path / "broken.ply"
    path.write_bytes(header + b"1 2 3\n4 5 6\n7 8 9\n")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, keyword)


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
@pytest.mark.parametrize("written_binary", [False, True])
def test_data_under_a_header_of_the_other_encoding_is_named(tmp_path, cloud, ext, written_binary):
    """An ASCII body under a header that says binary would be read as garbage numbers; a binary body under
    one that says ascii gave 'line 12: point has 23 values'."""
    written, path = tmp_path / f"w{ext}", tmp_path / f"mislabelled{ext}"
    save_point_cloud(written, cloud, binary=written_binary)
    swaps = [(b"format ascii", b"format binary_little_endian"), (b"DATA ascii", b"DATA binary")]
    data = written.read_bytes()
    for a, b in swaps:
        data = data.replace(*((b, a) if written_binary else (a, b)))
    path.write_bytes(data)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    if written_binary:
        assert_error(ei, path, "says", "ascii but the data is binary")
    else:
        assert_error(ei, path, "says", "binary", "numbers written as text")


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
def test_ascii_rows_beyond_the_declared_count_are_named(tmp_path, cloud, ext, caplog):
    """A header that declares fewer points than the data holds is read as declared, with a warning
    (it went unnoticed): the count may be the mistake, or the extra lines."""
    path = tmp_path / f"more{ext}"
    save_point_cloud(path, cloud, binary=False)
    path.write_bytes(path.read_bytes() + b"0.5 0.5 0.5\n\n1 2 3\n")
    with caplog.at_level(logging.WARNING, logger="gctr_cli.io"):
        np.testing.assert_array_equal(load_point_cloud(path), cloud)
    assert f"{path}: 2 more data lines after the {len(cloud)}" in caplog.text


def test_binary_ply_records_beyond_the_declared_count_are_named(tmp_path, cloud, caplog):
    """A binary PLY whose vertex count is below the records present was cut without a word, where ASCII
    PLY, binary PCD and LAS warn; a stray byte or two after the data (a trailing newline) is not a record."""
    path = tmp_path / "more.ply"
    save_point_cloud(path, cloud, binary=True)
    data = path.read_bytes()
    n = len(cloud)
    path.write_bytes(data.replace(f"element vertex {n}\n".encode(), f"element vertex {n - 3}\n".encode()))
    with caplog.at_level(logging.WARNING, logger="gctr_cli.io"):
        np.testing.assert_array_equal(load_point_cloud(path), cloud[: n - 3])
    assert f"{path}: 72 more bytes after the {n - 3} vertices the header declares (3 vertices' worth" in caplog.text
    caplog.clear()
    path.write_bytes(data + b"\n")
    with caplog.at_level(logging.WARNING, logger="gctr_cli.io"):
        np.testing.assert_array_equal(load_point_cloud(path), cloud)
    assert "more bytes" not in caplog.text


def test_binary_pcd_records_beyond_the_declared_count_are_named(tmp_path, cloud, caplog):
    """A binary PCD whose POINTS is below the records present was cut without a word, where the ASCII
    reader warned; POINTS 0 said 'contains no points'."""
    body = cloud.astype("<f4").tobytes()
    header = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {0}\nHEIGHT 1\nPOINTS {0}\n"
              "DATA binary\n")
    path = tmp_path / "low.pcd"
    path.write_bytes(header.format(150).encode() + body + b"\n")  # a stray newline is not a record
    with caplog.at_level(logging.WARNING, logger="gctr_cli.io"):
        np.testing.assert_array_equal(load_point_cloud(path), cloud[:150].astype(np.float32))
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: 50 more point records after the 150 points the header declares (ignored)"]
    path.write_bytes(header.format(0).encode() + body)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert str(ei.value) == (f"{path}: the header declares 0 points but 200 point records follow (a writer that "
                             "never filled in POINTS/WIDTH?)")


def test_ply_non_numeric_ascii_value(tmp_path):
    path = tmp_path / "word.ply"
    rows = "\n".join(f"{i} {i * i} {i % 3}" for i in range(20)).replace("9 81", "9 abc")
    path.write_bytes(ply_header("ascii", [("vertex", 20, ["float x", "float y", "float z"])]) + rows.encode())
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "non-numeric value 'abc'")


# ----------------------------------------------------------------------------------------------------
# PCD
# ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False])
def test_pcd_round_trip_exact(tmp_path, cloud, binary):
    path = tmp_path / "c.pcd"
    save_point_cloud(path, cloud, binary=binary)
    assert (b"DATA binary\n" in path.read_bytes()[:400]) == binary
    np.testing.assert_array_equal(load_point_cloud(path), cloud)


@pytest.mark.parametrize("compressed", [False, True])
def test_pcd_written_by_open3d_binary(tmp_path, rng, compressed):
    pts = rng.normal(size=(3000, 3))
    pc = o3d_cloud(pts)
    pc.estimate_normals()  # extra fields after x y z
    path = tmp_path / ("comp.pcd" if compressed else "bin.pcd")
    assert o3d().io.write_point_cloud(str(path), pc, write_ascii=False, compressed=compressed)
    data = path.read_bytes()
    assert (b"DATA binary_compressed" in data) == compressed
    out = load_point_cloud(path)
    assert out.shape == (3000, 3)
    # Open3D stores PCD coordinates as float32
    np.testing.assert_array_equal(out, pts.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(out, np.asarray(o3d().io.read_point_cloud(str(path)).points))


def sensor_pcd(path: Path, data: str, n: int = 60) -> dict[str, np.ndarray]:
    """A PCD file as a scanner driver writes it: a COUNT 3 field, a packed rgba with alpha, a sensor
    VIEWPOINT; returns the values written."""
    rng = np.random.default_rng(12)
    v = {"xyz": rng.normal(size=(n, 3)).astype(np.float32), "hist": rng.integers(0, 1000, (n, 3)).astype(np.uint16),
         "rgba": rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)}
    header = ("VERSION 0.7\nFIELDS x y z hist rgba\nSIZE 4 4 4 2 4\nTYPE F F F U U\nCOUNT 1 1 1 3 1\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 10 20 1.5 0.7071067811865476 0 0 0.7071067811865476\nPOINTS {n}\n"
              f"DATA {data}\n").encode()
    if data == "ascii":
        body = "".join(f"{x!r} {y!r} {z!r} {h[0]} {h[1]} {h[2]} {c}\n" for (x, y, z), h, c in
                       zip(v["xyz"].astype(float).tolist(), v["hist"], v["rgba"])).encode()
    else:
        rec = np.empty(n, [("xyz", "<f4", (3,)), ("hist", "<u2", (3,)), ("rgba", "<u4")])
        rec["xyz"], rec["hist"], rec["rgba"] = v["xyz"], v["hist"], v["rgba"]
        body = rec.tobytes()
        if data == "binary_compressed":  # one column after the other
            import lzf

            raw = b"".join(np.ascontiguousarray(v["xyz"][:, j]).tobytes() for j in range(3))
            raw += v["hist"].tobytes() + v["rgba"].tobytes()
            packed = lzf.compress(raw, 2 * len(raw) + 64)  # random values do not shrink
            body = struct.pack("<II", len(packed), len(raw)) + packed
    path.write_bytes(header + body)
    return v


def test_ascii_pcd_rgb_typed_float_but_written_as_its_uint32_bits_is_read_as_colours(tmp_path):
    """PCL's ASCII writer stores a float ``rgb`` as the integer of its bits (and older PCL, and writers
    copying it, kept ``TYPE F`` in the header): 4291322930 (0xFFC86432) was read as the float 4.29e9 and
    came out as red 127 green 200 blue 100 without a word."""
    header = ("VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 4\nHEIGHT 1\n"
              "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA ascii\n")
    rows = "0 0 0 4291322930\n1 0 0 4278190080\n0 1 0 16777215\n0 0 1 0\n"
    (tmp_path / "pcl.pcd").write_text(header + rows)
    a = read_point_cloud(tmp_path / "pcl.pcd", min_points=4).attributes
    assert a["red"].tolist() == [200, 0, 255, 0]
    assert a["green"].tolist() == [100, 0, 255, 0]
    assert a["blue"].tolist() == [50, 0, 255, 0]


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_pcd_count_3_fields_rgba_alpha_and_viewpoint_are_kept(tmp_path, data, caplog):
    """A field of COUNT 3 and rgba's alpha were dropped without a word; a non-identity VIEWPOINT was
    ignored on read and written back as the identity."""
    v = sensor_pcd(tmp_path / "scan.pcd", data)
    caplog.set_level(logging.WARNING, logger="gctr_cli.io")
    cloud = read_point_cloud(tmp_path / "scan.pcd")
    np.testing.assert_array_equal(cloud.points, v["xyz"])
    for j in range(3):
        np.testing.assert_array_equal(cloud.attributes[f"hist_{j}"], v["hist"][:, j])
    np.testing.assert_array_equal(cloud.attributes["alpha"], v["rgba"] >> 24)
    np.testing.assert_array_equal(cloud.attributes["red"], (v["rgba"] >> 16) & 0xFF)
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'scan.pcd'}: the PCD VIEWPOINT (the sensor's pose: translation 10 20 1.5, rotation "
        "quaternion w x y z 0.707107 0 0 0.707107) is not applied to the points, as in PCL; only a PCD output "
        "keeps it, moved with the points"]

    from gctr_cli.io import write_aligned

    write_aligned(tmp_path / "scan.pcd", np.eye(4), tmp_path / "same.pcd")
    text = (tmp_path / "same.pcd").read_bytes()
    assert b"\nVIEWPOINT 10 20 1.5 0.7071067811865476 0 0 0.7071067811865476\n" in text
    assert b"FIELDS x y z rgba hist_0 hist_1 hist_2\n" in text
    back = read_point_cloud(tmp_path / "same.pcd")
    for k in ("hist_0", "alpha", "red", "blue"):
        np.testing.assert_array_equal(back.attributes[k], cloud.attributes[k], err_msg=k)

    T = to_matrix(2.0, rotation_z(90), [1.0, -1.0, 0.0])
    write_aligned(tmp_path / "scan.pcd", T, tmp_path / "moved.pcd")
    line = next(x for x in (tmp_path / "moved.pcd").read_text("latin-1").splitlines() if x.startswith("VIEWPOINT"))
    vp = np.array(line.split()[1:], dtype=float)
    np.testing.assert_allclose(vp[:3], [-39.0, 19.0, 3.0], atol=1e-9)  # 2 * Rz(90) (10, 20, 1.5) + (1, -1, 0)
    np.testing.assert_allclose(np.abs(vp[3:]), [0, 0, 0, 1], atol=1e-9)  # turned 90° twice about z: 180°
    # a matrix with a flipped axis (apply accepts it, warning): the viewpoint's nearest proper rotation,
    # not a crash of the writer
    write_aligned(tmp_path / "scan.pcd", np.diag([-1.0, 1.0, 1.0, 1.0]), tmp_path / "flipped.pcd")
    line = next(x for x in (tmp_path / "flipped.pcd").read_text("latin-1").splitlines() if x.startswith("VIEWPOINT"))
    vp = np.array(line.split()[1:], dtype=float)
    np.testing.assert_allclose(vp[:3], [-10.0, 20.0, 1.5], atol=1e-9)
    assert np.linalg.norm(vp[3:]) == pytest.approx(1.0)

    write_aligned(tmp_path / "scan.pcd", np.eye(4), tmp_path / "out.ply")
    ply = read_point_cloud(tmp_path / "out.ply").attributes
    assert {"hist_0", "hist_1", "hist_2", "alpha", "red"} <= ply.keys()


def test_lzf_repeating_patterns(tmp_path):
    # Highly repetitive data exercises long and overlapping back references.
    n = 2000
    pts = np.zeros((n, 3), np.float32)
    pts[:, 0] = np.arange(n) % 4
    pts[:, 1] = 1.0
    pts[:, 2] = np.arange(n) // 500
    path = tmp_path / "rep.pcd"
    o3d().io.write_point_cloud(str(path), o3d_cloud(pts.astype(np.float64)), write_ascii=False, compressed=True)
    csize, usize = struct.unpack("<II", path.read_bytes().split(b"DATA binary_compressed\n", 1)[1][:8])
    assert csize < usize / 10  # really compressed
    np.testing.assert_array_equal(load_point_cloud(path), pts)


def rotation_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_pcd_binary_field_order_padding_and_counts(tmp_path, rng):
    n = 40
    pts = rng.normal(size=(n, 3))
    dt = np.dtype([("y", "<f8"), ("pad", "u1", (3,)), ("rgb", "<u4"), ("x", "<f8"), ("hist", "<f4", (4,)),
                   ("z", "<f8")])
    rec = np.zeros(n, dt)
    rec["x"], rec["y"], rec["z"] = pts.T
    hdr = (
        "VERSION 0.7\nFIELDS y _ rgb x hist z\nSIZE 8 1 4 8 4 8\nTYPE F U U F F F\nCOUNT 1 3 1 1 4 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    path = tmp_path / "fields.pcd"
    path.write_bytes(hdr.encode() + rec.tobytes())
    np.testing.assert_array_equal(load_point_cloud(path), pts)


def test_pcd_truncated_binary(tmp_path, cloud):
    path = tmp_path / "trunc.pcd"
    save_point_cloud(path, cloud)
    data = path.read_bytes()
    path.write_bytes(data[:-24])
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "truncated", "header declares 200 points")


def test_pcd_truncated_compressed(tmp_path, cloud):
    path = tmp_path / "trunc_c.pcd"
    o3d().io.write_point_cloud(str(path), o3d_cloud(cloud), write_ascii=False, compressed=True)
    data = path.read_bytes()
    path.write_bytes(data[:-50])
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "truncated", "compressed bytes")


def test_pcd_random_bytes(tmp_path, rng):
    path = tmp_path / "noise.pcd"
    path.write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "not a PCD file")


_GOOD_PCD = {
    "VERSION": "0.7",
    "FIELDS": "x y z",
    "SIZE": "4 4 4",
    "TYPE": "F F F",
    "COUNT": "1 1 1",
    "WIDTH": "3",
    "HEIGHT": "1",
    "POINTS": "3",
    "DATA": "ascii",
}


@pytest.mark.parametrize(
    "change, keyword",
    [
        ({"FIELDS": None}, "missing FIELDS"),
        ({"FIELDS": "x y w"}, "no z field"),
        ({"FIELDS": "a b c"}, "no x/y/z fields"),
        ({"POINTS": "many"}, "bad POINTS value"),
        ({"POINTS": "-5"}, "bad POINTS value"),
        ({"DATA": "zipped"}, "unknown DATA type 'zipped'"),
        ({"DATA": None}, "missing DATA"),
        ({"SIZE": "4 4"}, "SIZE has 2 entries but FIELDS has 3"),
        ({"TYPE": "F F Q"}, "unsupported TYPE/SIZE"),
        ({"SIZE": None}, "missing SIZE"),
    ],
)
def test_pcd_broken_header(tmp_path, change, keyword):
    fields = {**_GOOD_PCD, **change}
    hdr = "# .PCD v0.7\n" + "".join(f"{k} {v}\n" for k, v in fields.items() if v is not None)
    path = tmp_path / "broken.pcd"
    path.write_text(hdr + "0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path, min_points=3)
    assert_error(ei, path, keyword)


def test_pcd_header_without_points_uses_width_height(tmp_path):
    fields = {**_GOOD_PCD, "POINTS": None, "WIDTH": "2", "HEIGHT": "2"}
    hdr = "".join(f"{k} {v}\n" for k, v in fields.items() if v is not None)
    path = tmp_path / "wh.pcd"
    path.write_text(hdr + "0 0 0\n1 0 0\n0 1 0\n0 0 1\n")
    np.testing.assert_array_equal(load_point_cloud(path, min_points=4), [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def test_pcd_ascii_fewer_rows_than_declared(tmp_path):
    hdr = "".join(f"{k} {v}\n" for k, v in {**_GOOD_PCD, "POINTS": "5", "WIDTH": "5"}.items())
    path = tmp_path / "short.pcd"
    path.write_text(hdr + "0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path, min_points=3)
    assert_error(ei, path, "truncated", "header declares 5 points")


# ----------------------------------------------------------------------------------------------------
# Text formats
# ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".xyz", ".pts", ".txt"])
def test_text_round_trip_exact(tmp_path, cloud, ext):
    path = tmp_path / f"c{ext}"
    save_point_cloud(path, cloud)
    np.testing.assert_array_equal(load_point_cloud(path), cloud)


def test_pts_written_with_count_line_readable_by_open3d(tmp_path, cloud):
    path = tmp_path / "c.pts"
    save_point_cloud(path, cloud)
    assert path.read_text().splitlines()[0] == "200"
    np.testing.assert_array_equal(np.asarray(o3d().io.read_point_cloud(str(path)).points), cloud)


def test_text_variants(tmp_path, rng):
    pts = np.round(rng.normal(size=(25, 3)), 5)
    extra = rng.integers(0, 255, size=(25, 4))
    rows_ws = [f"{a!r}\t{b!r}  {c!r} {' '.join(map(str, e))}" for (a, b, c), e in zip(pts.tolist(), extra.tolist())]
    rows_csv = [f"{a!r}, {b!r},{c!r},{e[0]}" for (a, b, c), e in zip(pts.tolist(), extra.tolist())]

    cases = {
        "ws.xyz": "\n".join(rows_ws),
        "csv.txt": "X,Y,Z,intensity\n" + "\n".join(rows_csv),
        "count.pts": "25\n" + "\n".join(rows_ws),
        "comments.xyz": ("# exported\n//X Y Z\n\n" + "\n".join(rows_ws[:10]) + "\n# mid comment\n\n"
                         + "\n".join(rows_ws[10:])),
        "crlf.txt": "\r\n".join(rows_csv) + "\r\n",
    }
    for name, text in cases.items():
        path = tmp_path / name
        path.write_text(text, newline="")
        np.testing.assert_array_equal(load_point_cloud(path), pts, err_msg=name)


def test_text_bad_line_reports_line_number(tmp_path):
    path = tmp_path / "bad.xyz"
    lines = [f"{i} {i % 5} {i % 7}" for i in range(20)]
    lines[12] = "1 2 oops"
    path.write_text("\n".join(lines))
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "line 13", "non-numeric value 'oops'")

    lines[12] = "1 2"
    path.write_text("\n".join(lines))
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "line 13", "2 column(s)")


def test_text_dialect_holds_for_the_whole_file(tmp_path, rng):
    """The dialect is read off the first data line but must not misread later lines: whole numbers
    first and decimal commas later (semicolons) are still decimal commas; a blank-separated file's
    later decimal commas, an empty cell among x y z and a bad first data line are errors, never a
    silent shift of the columns."""
    pts = np.round(rng.normal(size=(30, 3)) * 100, 3)
    path = tmp_path / "dc.txt"
    rows = [";".join(f"{v:.3f}".replace(".", ",") for v in p) for p in pts]
    path.write_text("12;-80;41\n" + "\n".join(rows) + "\n")
    np.testing.assert_allclose(load_point_cloud(path), np.vstack([[12, -80, 41], pts]))
    sections = "".join(f"{len(part)}\n" + "".join(" ".join(f"{v:.3f}" for v in p) + " 17 200 30 40\n" for p in part)
                       for part in (pts[:12], pts[12:]))  # a two-scan Leica PTS: count line, x y z i r g b
    path = tmp_path / "two_scans.pts"
    path.write_text(sections)
    np.testing.assert_allclose(load_point_cloud(path), pts, atol=5e-4)
    readable = {  # runs of tabs align columns; headers may start with a number; an empty later column
        "tabs.txt": "\n".join("\t\t".join(f"{v:.3f}" for v in p) for p in pts),
        "header.xyz": "20 points\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts),
        "nan_header.xyz": "nan x y\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts),
        "later_empty.txt": "\n".join(",".join(f"{v:.3f}" for v in p) + ",,7" for p in pts),
    }
    for name, text in readable.items():
        path = tmp_path / name
        path.write_text(text + "\n")
        np.testing.assert_allclose(load_point_cloud(path), pts, atol=5e-4, err_msg=name)

    cases = {
        "blank.xyz": ("1 2 3\n4 5 6\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts)
                      + "\n1,5 2,5 3,5\n", ["line 33", "values look like decimal commas separated by blanks"]),
        "empty.csv.txt": ("\n".join(",".join(f"{v:.3f}" for v in p) + ",7" for p in pts[:10])
                          + "\n1.5,,2.5,7\n", ["line 11", "empty x, y or z value", "'1.5,,2.5,7'"]),
        "empty.dc.txt": ("\n".join(rows[:5]) + "\n1,5;;2,5\n", ["line 6", "empty x, y or z value"]),
        "bad_first.xyz": ("0.1 0.2 0.x3\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts),
                          ["line 1", "non-numeric value '0.x3'"]),
        "truncated.pts": (f"{len(pts) + 5}\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts),
                          ["line 1 declares 35 points but the file has 30", "truncated"]),
        "sections.pts": (f"{len(pts)}\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts)
                         + "\n12\n1 2 3\n", ["its 2 point-count lines declare 42 points but the file has 31"]),
    }
    big = np.round(rng.normal(size=(6000, 3)), 6)  # past the first 64 KiB block: numpy's fast path
    lines = [",".join(f"{v:.6f}" for v in p) + ",,7" for p in big]  # empty later columns are fine
    lines[5000] = lines[5000].replace(",", ",,", 1)
    cases["empty_late.txt"] = ("\n".join(lines) + "\n", ["line 5001", "empty x, y or z value"])
    for name, (text, keywords) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(PointCloudError) as ei:
            load_point_cloud(path)
        assert_error(ei, path, *keywords)


def test_a_ply_version_other_than_1_0_is_read_with_a_warning(tmp_path, rng, caplog):
    pts = np.round(rng.normal(size=(20, 3)), 3)
    path = tmp_path / "v2.ply"
    path.write_text("ply\nformat ascii 2.0\nelement vertex 20\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts) + "\n")
    caplog.set_level("WARNING", logger="gctr_cli.io")
    np.testing.assert_allclose(load_point_cloud(path), pts, atol=1e-6)
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: PLY header line 2: version '2.0' (only 1.0 is defined); read as 1.0"]


def test_pts_count_line_below_the_points_warns_and_reads_them_all(tmp_path, rng, caplog):
    """A count line lower than the points that follow (extra rows of a PLY or PCD are ignored with a warning):
    every point is read, and the mismatch is said, as for the other formats."""
    pts = np.round(rng.normal(size=(30, 3)), 3)
    path = tmp_path / "short_count.pts"
    path.write_text("20\n" + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts) + "\n")
    caplog.set_level("WARNING", logger="gctr_cli.io")
    np.testing.assert_allclose(load_point_cloud(path), pts)
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: line 1 declares 20 points but the file has 30 (all 30 read)"]


def test_text_without_numbers(tmp_path):
    path = tmp_path / "words.txt"
    path.write_text("hello world\nthis is not a cloud\n")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "contains no points")


def test_text_binary_garbage(tmp_path, rng):
    path = tmp_path / "garbage.xyz"
    path.write_bytes(rng.integers(0, 256, 2048, dtype=np.uint8).tobytes() + b"\x00")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert path.name in str(ei.value)


# ----------------------------------------------------------------------------------------------------
# Generic validation
# ----------------------------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    path = tmp_path / "nope.ply"
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "does not exist")


@pytest.mark.parametrize("ext", SUPPORTED_EXTENSIONS)
def test_empty_file(tmp_path, ext):
    path = tmp_path / f"empty{ext}"
    path.write_bytes(b"")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "is empty")


def test_unsupported_extension(tmp_path, cloud):
    path = tmp_path / "cloud.foo"
    path.write_text("1 2 3\n")
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "unsupported extension '.foo'", "supported: .ply, .pcd")
    with pytest.raises(PointCloudError) as ei:
        save_point_cloud(tmp_path / "out.e57", cloud)
    assert "unsupported extension '.e57' for writing" in str(ei.value)


def test_extension_case_insensitive(tmp_path, cloud):
    path = tmp_path / "UPPER.PLY"
    save_point_cloud(path, cloud)
    np.testing.assert_array_equal(load_point_cloud(path), cloud)


def test_directory_instead_of_file(tmp_path):
    d = tmp_path / "dir.ply"
    d.mkdir()
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(d)
    assert_error(ei, d, "not a regular file")


@pytest.mark.parametrize("n", [0, 1, 2])
@pytest.mark.parametrize("ext", [".ply", ".pcd", ".xyz"])
def test_too_few_points(tmp_path, n, ext):
    path = tmp_path / f"few{ext}"
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])[:n]
    if ext == ".xyz" and n == 0:
        path.write_text("# nothing here\n")
    else:
        save_point_cloud(path, pts)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    if n == 0:
        assert_error(ei, path, "no")
        assert "points" in str(ei.value)
    else:
        assert_error(ei, path, f"only {n} finite point{'' if n == 1 else 's'}", "at least 10")


def test_one_far_stray_point_does_not_make_a_cloud_degenerate(tmp_path, cloud):
    """A "no return" 0 0 0 beside UTM coordinates, or one corrupt value, must not make a good cloud look
    flat or collinear: the shape tests ignore far outliers. A line with a stray point is still a line."""
    utm = cloud + [500000.0, 4500000.0, 100.0]
    path = tmp_path / "stray.ply"
    save_point_cloud(path, np.vstack([utm, [0.0, 0.0, 0.0]]))
    assert len(load_point_cloud(path)) == len(utm) + 1
    line = np.outer(np.linspace(0.0, 1.0, 200), [1.0, 2.0, 3.0])
    save_point_cloud(path, np.vstack([line, [1e4, 0.0, 0.0]]))
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "collinear", "apart from 1 far outlier")


@pytest.mark.parametrize("factor, expected", [(1e200, "coordinates too large"), (1e-200, "cloud too small")])
def test_coordinates_float64_cannot_register_are_refused(tmp_path, cloud, factor, expected):
    path = tmp_path / "extreme.ply"
    save_point_cloud(path, cloud * factor)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, expected)


def test_min_points_parameter(tmp_path):
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    path = tmp_path / "tri.ply"
    save_point_cloud(path, pts)
    np.testing.assert_array_equal(load_point_cloud(path, min_points=3), pts)
    with pytest.raises(PointCloudError):
        load_point_cloud(path, min_points=4)


@pytest.mark.parametrize("ext", [".ply", ".pcd", ".xyz"])
def test_nan_rows_dropped_with_warning(tmp_path, cloud, caplog, ext):
    pts = cloud.copy()
    pts[[3, 50, 51], 1] = np.nan
    pts[100, 2] = np.inf
    pts[101, 0] = -np.inf
    path = tmp_path / f"nan{ext}"
    save_point_cloud(path, pts)
    with caplog.at_level(logging.WARNING, logger="gctr_cli.io"):
        out = load_point_cloud(path)
    keep = np.ones(len(pts), bool)
    keep[[3, 50, 51, 100, 101]] = False
    np.testing.assert_array_equal(out, cloud[keep])
    recs = [r for r in caplog.records if r.name == "gctr_cli.io" and r.levelno == logging.WARNING]
    assert len(recs) == 1
    assert path.name in recs[0].getMessage() and "dropped 5 of 200" in recs[0].getMessage()


def test_nan_rows_leave_too_few(tmp_path, cloud, caplog):
    pts = cloud[:12].copy()
    pts[:5, 0] = np.nan
    path = tmp_path / "mostly_nan.ply"
    save_point_cloud(path, pts)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "only 7 finite points", "after dropping 5 non-finite")


def test_all_nan(tmp_path):
    path = tmp_path / "all_nan.pcd"
    save_point_cloud(path, np.full((20, 3), np.nan))
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "no finite points", "all 20 points are non-finite")


def test_identical_points(tmp_path):
    path = tmp_path / "same.ply"
    save_point_cloud(path, np.tile([1.5, -2.0, 3.25], (30, 1)))
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "all 30 points are identical")


def test_collinear_points(tmp_path, rng):
    t = rng.uniform(-5, 5, size=(100, 1))
    pts = np.array([1e3, -2e3, 5e2]) + t * np.array([0.3, -0.5, 0.8])
    path = tmp_path / "line.xyz"
    save_point_cloud(path, pts)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "collinear")


def test_a_line_stored_as_float32_is_collinear_within_its_rounding(tmp_path, rng):
    """float32 rounding moves a stored line's points off it by about 1e-7 of the coordinates: still a line
    (it was found only as "planar" by the engine), while a float64 strip far from the origin is not."""
    t = rng.uniform(-0.1, 0.1, size=(2000, 1))
    line = (t * np.array([1.0, 2.0, 3.0])).astype(np.float32)
    path = tmp_path / "line32.ply"
    save_point_cloud(path, line)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    assert_error(ei, path, "collinear", "2000 points on one line, within the float32 rounding")
    # a float32 strip 5 m wide at UTM-size offsets (steps of 0.5 m) is wider than its rounding: kept
    strip = (np.c_[rng.uniform(0, 100, 500), rng.uniform(0, 5, 500), rng.uniform(0, 5, 500)]
             + [5e5, 5e6, 200.0]).astype(np.float32)
    assert len(load_point_cloud(_saved(tmp_path / "strip.ply", strip))) == 500


def test_a_large_cloud_is_checked_on_a_sample_and_a_problem_counted_on_every_point(tmp_path, rng, monkeypatch):
    """Above STATS_POINTS points the order statistics and shape tests run on an even sample (a 10-million-point
    PLY took 7.6 s to read, 6.2 of them in these checks; now 1.9 s); a degenerate cloud is still refused, its
    message counting every point, and a cloud that passes is read whole."""
    import gctr_cli.geometry

    monkeypatch.setattr(gctr_cli.geometry, "STATS_POINTS", 1000)
    n = 5000
    line = np.outer(np.linspace(0.0, 1.0, n), [1.0, 2.0, 3.0])
    for name, pts, expected in (
            ("same", np.tile([1.5, -2.0, 3.25], (n, 1)), f"all {n} points are identical"),
            ("same_far", np.vstack([np.ones((n, 3)), rng.normal(size=(4, 3)) * 1e6]),
             f"{n} of its {n + 4} points are identical; the other 4 lie far from them"),
            ("line_far", np.vstack([line, np.eye(3) * 1e5]),
             f"collinear ({n} points on one line, apart from 3 far outlier(s))")):
        path = _saved(tmp_path / f"{name}.ply", pts)
        with pytest.raises(PointCloudError) as ei:
            load_point_cloud(path)
        assert_error(ei, path, expected)
    # one point off the line among 5000 is missed by the sample but not by the whole cloud: accepted, whole
    off = np.vstack([line[:2500], [[0.5, 0.2, 0.1]], line[2500:]])
    np.testing.assert_array_equal(load_point_cloud(_saved(tmp_path / "off.ply", off)), off)
    # every 4th record a "no return" 0 0 0: a stride of 4 (the first form, every k-th point) sampled only
    # those and refused the cloud as identical points (found by a review); a seeded random sample does not
    scan = rng.normal(size=(4000, 3)) * [3.0, 2.0, 1.0]
    scan[::4] = 0.0
    np.testing.assert_array_equal(load_point_cloud(_saved(tmp_path / "returns.ply", scan)), scan)


def test_order_statistics_of_a_large_cloud_come_from_a_sample(rng, monkeypatch):
    """robust_core and the engine's normalisation: the whole cloud up to STATS_POINTS (the same numbers as
    before), a seeded sample above it (within a few percent of the whole cloud's), also for a cloud whose
    every 4th record is 0 0 0 (a stride of 4 made its size 0 and the normalised cloud inf)."""
    import gctr_cli.geometry
    from gctr_cli.engine.preprocess import robust_centre_and_size
    from gctr_cli.geometry import robust_core, row_norms

    pts = rng.normal(size=(20_000, 3)) * [3.0, 2.0, 1.0]
    d = row_norms(pts - np.median(pts, axis=0))
    np.testing.assert_array_equal(robust_core(pts), pts[d <= 3.0 * np.percentile(d, 90)])
    centre, size = robust_centre_and_size(pts)
    whole = len(robust_core(pts))
    monkeypatch.setattr(gctr_cli.geometry, "STATS_POINTS", 2000)
    core = robust_core(pts)  # the sample's median and percentile, applied to every point
    assert abs(len(core) / whole - 1) < 0.01 and set(map(tuple, core)) <= set(map(tuple, pts))
    sampled_centre, sampled_size = robust_centre_and_size(pts)
    assert np.linalg.norm(sampled_centre - centre) < 0.02 * size and abs(sampled_size / size - 1) < 0.02
    pts[::10] = 0.0  # every 10th record: a stride of 10 over 20,000 points for a 2,000-point sample
    monkeypatch.setattr(gctr_cli.geometry, "STATS_POINTS", 1_000_000)
    centre, size = robust_centre_and_size(pts)
    monkeypatch.setattr(gctr_cli.geometry, "STATS_POINTS", 2000)
    sampled_centre, sampled_size = robust_centre_and_size(pts)
    assert np.linalg.norm(sampled_centre - centre) < 0.03 * size and abs(sampled_size / size - 1) < 0.03


def _saved(path: Path, points: np.ndarray) -> Path:
    save_point_cloud(path, points)
    return path


def test_planar_points_accepted(tmp_path, rng):
    pts = np.c_[rng.normal(size=(100, 2)), np.zeros(100)]
    path = tmp_path / "plane.ply"
    save_point_cloud(path, pts)
    np.testing.assert_array_equal(load_point_cloud(path), pts)


@pytest.mark.parametrize("ext", [".ply", ".pcd", ".xyz", ".pts", ".txt"])
@pytest.mark.parametrize("binary", [True, False])
def test_utm_offset_round_trip_keeps_precision(tmp_path, rng, ext, binary):
    # UTM-like coordinates: millimetre detail on top of a 1e6 offset needs float64
    pts = rng.uniform(0, 50, size=(500, 3)) + np.array([4.5e5, 5.4e6, 1e6])
    path = tmp_path / f"utm{ext}"
    save_point_cloud(path, pts, binary=binary)
    out = load_point_cloud(path)
    np.testing.assert_array_equal(out, pts)
    assert not np.array_equal(out, pts.astype(np.float32).astype(np.float64))


def test_save_validates_shape(tmp_path):
    with pytest.raises(PointCloudError) as ei:
        save_point_cloud(tmp_path / "bad.ply", np.zeros((5, 2)))
    assert "bad.ply" in str(ei.value) and "shape (N, 3)" in str(ei.value)


def test_save_is_atomic(tmp_path, cloud, monkeypatch):
    path = tmp_path / "sub" / "atomic.ply"
    save_point_cloud(path, cloud)  # creates the parent folder
    before = path.read_bytes()

    def boom(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fsutil.os, "replace", boom)
    with pytest.raises(PointCloudError) as ei:
        save_point_cloud(path, cloud[:50])
    assert_error(ei, path, "cannot write", "No space left")
    assert path.read_bytes() == before  # old content intact
    assert sorted(p.name for p in path.parent.iterdir()) == ["atomic.ply"]  # temp file cleaned up


@pytest.mark.parametrize("ext", [".xyz", ".csv", ".pts", ".ply", ".pcd"])
def test_text_outputs_are_formatted_block_by_block_as_they_are_written(tmp_path, rng, monkeypatch, ext):
    """Text rows were built whole and copied before being written: 2 million points to .xyz peaked at
    390 MB, now 173 MB (the same bytes). The writer hands the file over in blocks, and a block that cannot be
    made leaves neither the file nor a temporary one."""
    import gctr_cli.io.ply as ply
    from gctr_cli.io.registry import format_of

    monkeypatch.setattr(ply, "TEXT_BLOCK_ROWS", 100)
    pts = rng.normal(size=(1050, 3))
    cloud = PointCloud(pts, {"intensity": rng.integers(0, 255, 1050).astype(np.uint16)}, "ply", {})
    path = tmp_path / f"out{ext}"
    pieces = format_of(path).write(cloud, False, path)
    assert not isinstance(pieces, bytes | list)  # lazy: nothing formatted yet
    pieces = list(pieces)
    assert len(pieces) == 1 + 11  # the header, then 11 blocks of at most 100 rows
    save_point_cloud(path, pts, binary=False)
    np.testing.assert_array_equal(load_point_cloud(path), pts)  # exact round trip

    def failing():
        yield b"x y z\n"
        raise OSError(5, "Input/output error")

    with pytest.raises(OSError):
        fsutil.atomic_write(tmp_path / "broken.xyz", failing())
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"out{ext}"]


def test_save_overwrites_and_leaves_no_temp(tmp_path, cloud):
    path = tmp_path / "over.pcd"
    save_point_cloud(path, cloud)
    save_point_cloud(path, cloud[:20])
    assert load_point_cloud(path).shape == (20, 3)
    assert [p.name for p in tmp_path.iterdir()] == ["over.pcd"]


def test_saved_file_permissions_follow_umask(tmp_path, cloud):
    old = os.umask(0o022)
    try:
        save_point_cloud(tmp_path / "perm.ply", cloud)
        write_matrix(tmp_path / "perm.txt", np.eye(4))
    finally:
        os.umask(old)
    assert (tmp_path / "perm.ply").stat().st_mode & 0o777 == 0o644  # not tempfile's 0600
    assert (tmp_path / "perm.txt").stat().st_mode & 0o777 == 0o644


# ----------------------------------------------------------------------------------------------------
# Matrices
# ----------------------------------------------------------------------------------------------------


def _random_similarity(rng) -> np.ndarray:
    """Scale 0.1-10 and translations of very different magnitudes (1e-7 to 1e6): hard to print exactly."""
    return to_matrix(rng.uniform(0.1, 10), random_rotation(rng), rng.normal(size=3) * np.array([1e-7, 1e3, 1e6]))


def test_matrix_round_trip_bit_exact(tmp_path, rng):
    for i in range(20):
        T = _random_similarity(rng)
        path = tmp_path / f"m{i}.txt"
        write_matrix(path, T)
        back = read_matrix(path)
        assert back.dtype == np.float64
        assert np.array_equal(back, T) and back.tobytes() == T.tobytes()
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".txt"] * 20


def test_format_matrix_layout(rng):
    T = _random_similarity(rng)
    text = format_matrix(T)
    lines = text.splitlines()
    assert text.endswith("\n") and len(lines) == 4
    assert all(len(line.split()) == 4 for line in lines)
    assert lines[3] == "0 0 0 1"
    assert float(lines[0].split()[0]) == T[0, 0]
    with pytest.raises(MatrixError):
        format_matrix(np.eye(3))


def test_read_matrix_lenient_layout(tmp_path):
    path = tmp_path / "loose.txt"
    path.write_text("# header comment\n\n1, 0, 0, 5   # trailing note\n  0\t1 0 -2\n\n0 0 1 3.5e-3\n0 0 0 1\n\n")
    T = read_matrix(path)
    expected = np.eye(4)
    expected[:3, 3] = [5, -2, 3.5e-3]
    np.testing.assert_array_equal(T, expected)


@pytest.mark.parametrize(
    "text, keywords",
    [
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", ["expected 4 rows", "found 3"]),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n0 0 0 1\n", ["more than 4 rows", "line 5"]),
        ("1 0 0 0 9\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", ["line 1", "5 values, expected 4 numbers", "four lines of four"]),
        ("1;0;0;0\n0;1;0;0\n0;0;1;0\n0;0;0;1\n", ["line 1", "';' does not separate numbers", "spaces or commas"]),
        ("[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n", ["16 values", "brackets are not read"]),
        ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n", ["16 values", "four lines of four numbers"]),
        ("[[1. 0. 0. 0.]\n [0. 1. 0. 0.]\n [0. 0. 1. 0.]\n [0. 0. 0. 1.]]\n", ["non-numeric", "brackets are not read"]),
        ("1; 0; 0; 0\n0; 1; 0; 0\n0; 0; 1; 0\n0; 0; 0; 1\n", ["non-numeric", "';' does not separate numbers"]),
        ("1 0 0 0\n0 one 0 0\n0 0 1 0\n0 0 0 1\n", ["line 2", "non-numeric"]),
        ("1_0 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", ["line 1", "non-numeric"]),
        ("1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", ["non-finite", "(0,3)"]),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", ["last row must be '0 0 0 1'"]),
        ("# only comments\n\n", ["expected 4 rows", "found 0"]),
    ],
)
def test_read_matrix_errors(tmp_path, text, keywords):
    path = tmp_path / "bad_matrix.txt"
    path.write_text(text)
    with pytest.raises(MatrixError) as ei:
        read_matrix(path)
    assert_error(ei, path, *keywords)


def test_read_matrix_missing_and_empty(tmp_path):
    missing = tmp_path / "missing.txt"
    with pytest.raises(MatrixError) as ei:
        read_matrix(missing)
    assert_error(ei, missing, "does not exist")
    empty = tmp_path / "empty.txt"
    empty.write_bytes(b"")
    with pytest.raises(MatrixError) as ei:
        read_matrix(empty)
    assert_error(ei, empty, "is empty")
    binary = tmp_path / "binary.txt"
    binary.write_bytes(b"\xff\xfe\x00\x01" * 10)
    with pytest.raises(MatrixError) as ei:
        read_matrix(binary)
    assert_error(ei, binary, "not a text file")


def test_write_matrix_validation(tmp_path):
    path = tmp_path / "w.txt"
    with pytest.raises(MatrixError) as ei:
        write_matrix(path, np.eye(3))
    assert_error(ei, path, "4x4", "(3, 3)")
    bad = np.eye(4)
    bad[1, 2] = np.inf
    with pytest.raises(MatrixError) as ei:
        write_matrix(path, bad)
    assert_error(ei, path, "non-finite")
    assert not path.exists()
    write_matrix(tmp_path / "nested" / "dir" / "m.txt", np.eye(4))
    assert (tmp_path / "nested" / "dir" / "m.txt").read_text() == "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"


# ----------------------------------------------------------------------------------------------------
# coordinates stored too coarsely for the cloud's size: a warning naming the file, the step and the cause
# ----------------------------------------------------------------------------------------------------


def _float32_ply(path: Path, points: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    path.write_bytes(header + points.astype("<f4").tobytes())


def test_a_float32_cloud_at_utm_coordinates_is_read_with_a_warning_naming_float32(tmp_path, caplog):
    """A 0.5 m object 4.7 million metres from the origin, exported as float32 (the commonest mistake with
    georeferenced data): y keeps 0.5 m steps. The cloud is read (it is a valid file), with a warning that
    names the step, its share of the cloud's size and the cause."""
    bunny = load_point_cloud(Path(__file__).parents[1] / "data" / "models" / "bunny.ply")
    path = tmp_path / "utm32.ply"
    _float32_ply(path, bunny * 3 + [512345.0, 4678901.0, 250.0])
    with caplog.at_level(logging.WARNING, logger="gctr_cli.io"):
        points = load_point_cloud(path)
    assert len(points) == len(bunny)
    [warning] = [r.getMessage() for r in caplog.records if "steps of" in r.getMessage()]
    assert warning.startswith(f"{path}: coordinates are stored in steps of 0.5 along y, ")
    assert "float32 values as far from the origin as 4.6789e+06 keep no finer steps" in warning


def test_a_coarse_las_like_quantum_is_told_and_fine_or_continuous_coordinates_are_not():
    """1 cm steps on a 15 cm object (a LAS scale of 0.01) are 4% of its size: told, with the file's digits as
    the cause. A 1 mm quantum on a 100 m scan or on the bunny, float64 coordinates and a few hundred random
    points (whose gaps are wide by chance) are not."""
    rng = np.random.default_rng(3)
    bunny = load_point_cloud(Path(__file__).parents[1] / "data" / "models" / "bunny.ply")
    note = coarse_step_note(np.round(bunny, 2))
    assert note is not None and note.startswith("coordinates are stored in steps of 0.01 along ")
    assert note.endswith("the file keeps no more digits (a LAS scale factor, a text export's decimals, "
                         "integer units?)")
    assert coarse_step_note(bunny) is None
    assert coarse_step_note(np.round(rng.uniform(0, 100, size=(50_000, 3)), 3)) is None
    assert coarse_step_note(rng.uniform(0, 1, size=(COARSE_STEP_MIN_POINTS, 3))) is None
    flat = np.c_[rng.uniform(0, 1, size=(1000, 2)), np.zeros(1000)]  # a flat axis has no step to see
    assert coarse_step_note(flat) is None
    assert coarse_step_note(np.round(bunny, 3)) is None  # 0.4% of its size: registers as well as float64


def test_a_coarse_step_is_a_lattice_of_the_core_and_not_a_few_levels_or_a_grid_sampled_unevenly():
    """Two exact levels (a floor and a table top) are no lattice; a row-major 1 m grid of 1000 x 1000 points
    (sampled beyond COARSE_STEP_SAMPLE) is fine at 0.07% of its size, whatever the sample; a stray 0 0 0
    does not hide 0.5 m float32 steps of a cloud 4.7 million metres from the origin."""
    rng = np.random.default_rng(5)
    floor = np.c_[rng.uniform(0, 5, size=(6000, 2)), np.repeat([0.0, 0.75], 3000)]
    assert coarse_step_note(floor) is None
    g = np.arange(1000.0)
    x, y = np.meshgrid(g, g)
    grid = np.c_[x.ravel(), y.ravel(), 5 * np.sin(x.ravel() / 30) + rng.normal(0, 0.1, x.size)]
    assert len(grid) > COARSE_STEP_SAMPLE and coarse_step_note(grid) is None
    bunny = load_point_cloud(Path(__file__).parents[1] / "data" / "models" / "bunny.ply")
    utm = (bunny * 3 + [512345.0, 4678901.0, 250.0]).astype(np.float32).astype(np.float64)
    note = coarse_step_note(np.vstack([utm, [0.0, 0.0, 0.0]]))
    assert note is not None and note.startswith("coordinates are stored in steps of 0.5 along y, ")


def test_float32_coordinates_written_as_text_get_the_float32_note(tmp_path):
    """float32 values far from the origin printed with 9 digits (``%.9g``) are off float32's lattice by a
    digit, enough to hide it from the lattice test: they are recognised as float32 values all the same."""
    bunny = np.asarray(load_point_cloud(Path(__file__).parents[1] / "data" / "models" / "bunny.ply"))
    far = (bunny + [3e5, 3e5, 200.0]).astype(np.float32)
    path = tmp_path / "far32.xyz"
    np.savetxt(path, far, fmt="%.9g")
    assert not np.all(np.loadtxt(path) == far.astype(np.float64))  # the text is not exactly the float32 values
    note = coarse_step_note(np.loadtxt(path))
    assert note is not None and "steps of 0.0312 along x and y" in note and "float32 values as far" in note
    assert coarse_step_note(bunny + [3e5, 3e5, 200.0]) is None  # the same offset in float64: no note
    # a float64 axis thinner than the snapping tolerance (1 cm at a UTM northing) falls on one float32 value:
    # no lattice, no note (it crashed the reader: an empty list of gaps)
    thin = np.random.default_rng(1).uniform(0, 0.03, (2000, 3)) + [5e5, 5e6, 100.0]
    assert coarse_step_note(thin) is None
    assert len(load_point_cloud(_saved(tmp_path / "thin.ply", thin))) == 2000


def test_a_float32_axis_collapsed_to_two_levels_is_the_one_named(tmp_path, caplog):
    """The bunny at full size 5.4 million metres from the origin in float32: y holds two values 0.5 apart,
    so the cloud's core is flat along y and the note named x's 0.03 steps instead of y's 0.5, the cause
    of the registration's refusal that follows (the points are planar)."""
    bunny = load_point_cloud(Path(__file__).parents[1] / "data" / "models" / "bunny.ply")
    path = tmp_path / "flat32.ply"
    _float32_ply(path, bunny + [512345.6, 5401234.6, 250.0])
    with caplog.at_level(logging.WARNING, logger="gctr_cli.io"):
        points = read_point_cloud(path).points
    assert len(np.unique(points[:, 1])) == 2
    [warning] = [r.getMessage() for r in caplog.records if "steps of" in r.getMessage()]
    assert warning.startswith(f"{path}: coordinates are stored in steps of 0.5 along y, ")
