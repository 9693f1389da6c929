"""Text clouds (.xyz .txt .pts): the decimal mark read off x y z alone, the columns after x y z kept
as attributes, and .pts output that other tools read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gctr_cli import cli
from gctr_cli.io import (
    PointCloud,
    PointCloudError,
    load_point_cloud,
    read_point_cloud,
    write_aligned,
    write_matrix,
    write_point_cloud,
)

RNG = np.random.default_rng(2024)
#: past the first 64 KiB block, so numpy's fast path reads most of the lines
N_BIG = 6000


def _points(n: int) -> np.ndarray:
    return np.round(RNG.uniform(-500.0, 500.0, size=(n, 3)), 4)


def _decimal_comma(v: float) -> str:
    return f"{v:.4f}".replace(".", ",")


def _error(path: Path, *keywords: str) -> str:
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(path)
    msg = str(ei.value)
    assert str(path) in msg, msg
    for kw in keywords:
        assert kw in msg, f"{kw!r} not in {msg!r}"
    return msg


# ----------------------------------------------------------------------------------------------------
# the decimal mark is decided by the x y z cells alone
# ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("sep", [";", "\t"])
@pytest.mark.parametrize("later", ["timestamp", "label"])
def test_decimal_commas_are_read_whatever_a_later_column_holds(tmp_path, sep, later):
    """``4,3787;9,8742;0,7165;14.03.2024 10:15:00,000``: the comma of the timestamp (or of a label
    ``Punkt 1, Gruppe A``) made every comma a column separator, and x=4 y=3787 z=9 were read without a
    word. The x y z cells decide the decimal mark; later columns never change how x y z are read."""
    pts = _points(N_BIG)
    cells = {"timestamp": lambda i: f"14.03.2024 10:15:{i % 60:02d},{i % 1000:03d}",
             "label": lambda i: f"Punkt {i}, Gruppe A"}[later]
    rows = [sep.join([*map(_decimal_comma, p), cells(i)]) for i, p in enumerate(pts)]
    path = tmp_path / "export.txt"
    path.write_text(sep.join(["X", "Y", "Z", "Info"]) + "\n" + "\n".join(rows) + "\n")
    np.testing.assert_array_equal(load_point_cloud(path), pts)
    np.testing.assert_array_equal(read_point_cloud(path).points, pts)


def test_the_decimal_mark_of_x_y_z_holds_for_later_lines(tmp_path):
    """The dialect is still held to: a later line whose x y z cells do not fit it, or that has an empty
    x y z cell, is an error naming the line, never a silent shift of the columns."""
    pts = _points(20)
    rows = [";".join([*map(_decimal_comma, p), "Punkt 1, Gruppe A"]) for p in pts]
    path = tmp_path / "misfit.txt"
    path.write_text("\n".join(rows[:10] + ["1,5,2,5;3,5;Punkt 1, Gruppe A"] + rows[10:]) + "\n")
    _error(path, "line 11", "non-numeric value '1.5.2.5'")
    path.write_text("\n".join(rows[:10] + ["1,5;;3,5;Punkt 1, Gruppe A"] + rows[10:]) + "\n")
    _error(path, "line 11", "empty x, y or z value")


def test_commas_between_columns_and_between_blanks_are_still_told_apart(tmp_path):
    path = tmp_path / "comma.txt"
    path.write_text("".join(f"{x},{y},{z},a\n" for x, y, z in _points(20)))
    np.testing.assert_array_equal(load_point_cloud(path), np.loadtxt(path, delimiter=",", usecols=(0, 1, 2)))
    path = tmp_path / "semicolon_points.txt"  # decimal points, semicolons, a later comma: read as before
    pts = _points(20)
    path.write_text("".join(f"{x};{y};{z};Punkt 1, Gruppe A\n" for x, y, z in pts))
    np.testing.assert_array_equal(load_point_cloud(path), pts)
    path = tmp_path / "blanks.xyz"
    path.write_text("1,5 2,25 3,0\n" * 20)
    _error(path, "line 1", "decimal commas separated by blanks")


# ----------------------------------------------------------------------------------------------------
# the columns after x y z are kept as attributes (apply, --aligned), or dropped with one warning
# ----------------------------------------------------------------------------------------------------


def _rows(pts: np.ndarray, extra: np.ndarray, sep: str = " ") -> str:
    return "".join(sep.join([*(f"{v!r}" for v in p), *(f"{v:g}" for v in e)]) + "\n"
                   for p, e in zip(pts.tolist(), extra.tolist(), strict=True))


def _columns(n: int, k: int) -> np.ndarray:
    return RNG.integers(0, 256, size=(n, k)).astype(np.float64)


def test_gctr_text_output_round_trips_with_its_attribute_columns(tmp_path):
    """gctr writes ``# x y z name ...`` and one column per attribute; reading it dropped them all."""
    n = 300
    pts = _points(n)
    attrs = {"intensity": RNG.integers(0, 60000, n).astype(np.uint16), "red": RNG.integers(0, 256, n).astype(np.uint8),
             "green": RNG.integers(0, 256, n).astype(np.uint8), "blue": RNG.integers(0, 256, n).astype(np.uint8),
             "nx": RNG.normal(size=n).astype(np.float32), "scalar_field": RNG.normal(size=n)}
    for ext in (".xyz", ".txt"):
        write_point_cloud(tmp_path / f"out{ext}", PointCloud(pts, attrs))
        back = read_point_cloud(tmp_path / f"out{ext}")
        np.testing.assert_array_equal(back.points, pts)
        assert list(back.attributes) == list(attrs)
        for k, v in attrs.items():
            assert back.attributes[k].dtype == (np.uint8 if k in ("red", "green", "blue") else np.float64), k
            np.testing.assert_array_equal(back.attributes[k], v.astype(np.float64), err_msg=k)


@pytest.mark.parametrize("name, header, sep, expected", [
    ("upper.txt", "X Y Z R G B\n", " ", ["red", "green", "blue"]),
    ("intensity.txt", "//X,Y,Z,Intensity\n", ",", ["intensity"]),
    ("cloudcompare.txt", "//X,Y,Z,R,G,B,Scalar field\n", ",", ["red", "green", "blue", "scalar_field"]),
    ("tabs.txt", "X\tY\tZ\tI\tReturn Number\n", "\t", ["intensity", "return_number"]),
    ("count_below_names.xyz", "x y z a b\n20\n", " ", ["a", "b"]),
    ("no_names.xyz", "", " ", ["column_4", "column_5"]),
    ("other_count.xyz", "X Y Z R G B\n", " ", ["column_4", "column_5"]),  # 6 names, 5 columns
    ("unusable.txt", "X;Y;Z;Intensität;R;G;B\n", ";", ["column_4", "red", "green", "blue"]),
    ("coordinates.txt", "E N H X\n", " ", ["column_4"]),
    ("repeated.txt", "X Y Z Intensity I\n", " ", ["column_4", "column_5"]),
    ("b_alone.txt", "X Y Z A B\n", " ", ["a", "b"]),
    ("leica4.pts", "", " ", ["intensity"]),
    ("leica6.pts", "", " ", ["red", "green", "blue"]),
    ("leica7.pts", "", " ", ["intensity", "red", "green", "blue"]),
    ("leica5.pts", "", " ", ["column_4", "column_5"]),
    ("named.pts", "# x y z a b c d\n", " ", ["a", "b", "c", "d"]),
])
def test_attribute_names_come_from_the_header_or_the_pts_convention(tmp_path, name, header, sep, expected):
    n_cols = len(expected) + 3 if name != "other_count.xyz" else 5
    pts, extra = _points(N_BIG), _columns(N_BIG, n_cols - 3)
    path = tmp_path / name
    path.write_text(header + _rows(pts, extra, sep))
    back = read_point_cloud(path)
    np.testing.assert_array_equal(back.points, pts)
    assert list(back.attributes) == expected
    np.testing.assert_array_equal(np.stack([back.attributes[k] for k in expected], axis=1), extra)
    assert not read_point_cloud(path, attributes=False).attributes  # registration reads x y z only


def test_decimal_comma_attribute_columns_are_read(tmp_path):
    pts = _points(50)
    rows = [";".join([*map(_decimal_comma, p), _decimal_comma(i / 8), str(i % 256)]) for i, p in enumerate(pts)]
    path = tmp_path / "de.txt"
    path.write_text("Rechtswert;Hochwert;Höhe;Intensity;Klasse\n" + "\n".join(rows) + "\n")
    back = read_point_cloud(path)
    assert list(back.attributes) == ["intensity", "klasse"]
    np.testing.assert_array_equal(back.attributes["intensity"], np.arange(50) / 8)
    np.testing.assert_array_equal(back.attributes["klasse"], np.arange(50) % 256)


def _ragged(n: int, bad: int, bad_row: str) -> tuple[np.ndarray, str]:
    pts, extra = _points(n), _columns(n, 4)
    lines = _rows(pts, extra).splitlines(keepends=True)
    lines[bad] = bad_row
    return pts, "".join(lines)


@pytest.mark.parametrize("bad, bad_row, problem", [
    (9, "1 2 3 4 5\n", "line 10 has 5 columns, the first data line 7"),
    (N_BIG - 10, "1 2 3 4 5\n", f"line {N_BIG - 9} has 5 columns, the first data line 7"),  # numpy's fast path
    (N_BIG - 10, "1 2 3 4 5 6 7 8\n", f"line {N_BIG - 9} has 8 columns, the first data line 7"),
    (9, "1 2 3 4 5 six 7\n", "line 10 has a non-numeric value 'six' in column 6"),
    (N_BIG - 10, "1 2 3 4 5 nan 1_000\n", f"line {N_BIG - 9} has a non-numeric value '1_000' in column 7"),
])
def test_columns_that_do_not_fit_are_dropped_with_one_warning_naming_the_line(tmp_path, caplog, bad, bad_row,
                                                                              problem):
    """Lines with another number of columns or a non-numeric value after x y z: x y z are read (they are
    numbers), the other columns are dropped, and the user hears it once, never an error."""
    pts, text = _ragged(N_BIG, bad, bad_row)
    pts[bad] = [1, 2, 3]
    path = tmp_path / "ragged.xyz"
    path.write_text(text)
    caplog.set_level("WARNING", logger="gctr_cli.io")
    back = read_point_cloud(path)
    np.testing.assert_array_equal(back.points, pts)
    assert back.attributes == {}
    assert [r.getMessage() for r in caplog.records] == [f"{path}: columns after x y z are not kept: {problem}"]
    caplog.clear()
    np.testing.assert_array_equal(read_point_cloud(path, attributes=False).points, pts)
    assert not caplog.records  # a registration's read does not read them and says nothing


def test_the_first_line_that_does_not_fit_is_named(tmp_path, caplog):
    """A non-numeric value on line 5 and a short line on line 8 of the same block: line 5 is named."""
    _, text = _ragged(20, 7, "1 2 3 4 5\n")
    lines = text.splitlines(keepends=True)
    lines[4] = lines[4].rsplit(" ", 1)[0] + " n/a\n"
    (tmp_path / "two.xyz").write_text("".join(lines))
    caplog.set_level("WARNING", logger="gctr_cli.io")
    assert read_point_cloud(tmp_path / "two.xyz").attributes == {}
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'two.xyz'}: columns after x y z are not kept: line 5 has a non-numeric value 'n/a' in column 7"]


@pytest.mark.parametrize("text, problem", [
    ("".join(f"{i}.5 {i * i} 1\n" for i in range(12)) + "1 2 3 4 5\n", "line 13 has 5 columns, the first data line 3"),
    ("".join(f"{i}.5,{i * i},1,,7\n" for i in range(12)), "line 1 has an empty cell after x y z ('0.5,0,1,,7')"),
    ("".join(f"{i},5;{i * i};1;14.03.2024 10:15:00,000\n" for i in range(12)),
     "line 1 has a non-numeric value '14.03.2024' in column 4"),
])
def test_more_reasons_columns_are_dropped_are_said(tmp_path, caplog, text, problem):
    """Columns after a first line of only x y z; an empty cell, which would shift the later columns; a
    timestamp: each is said once."""
    path = tmp_path / "c.txt"
    path.write_text(text)
    caplog.set_level("WARNING", logger="gctr_cli.io")
    assert read_point_cloud(path).attributes == {}
    assert [r.getMessage() for r in caplog.records] == [f"{path}: columns after x y z are not kept: {problem}"]


def _apply_a_leica_pts(tmp_path: Path, out_name: str) -> tuple[np.ndarray, np.ndarray]:
    """``gctr apply`` (identity) of a 200-point ``x y z intensity red green blue`` PTS file to ``out_name``;
    the points and the four columns."""
    pts, extra = _points(200), np.hstack([_columns(200, 1), _columns(200, 3)])
    (tmp_path / "scan.pts").write_text("200\n" + _rows(pts, extra))
    write_matrix(tmp_path / "T.txt", np.eye(4))
    res = CliRunner().invoke(cli.main, ["apply", str(tmp_path / "T.txt"), str(tmp_path / "scan.pts"),
                                        "-o", str(tmp_path / out_name)])
    assert res.exit_code == 0, res.output
    return pts, extra


def test_apply_keeps_the_columns_of_a_text_cloud(tmp_path):
    """`gctr apply` to a PLY: the colours and intensity of a Leica PTS file arrive, and Open3D shows them."""
    import open3d as o3d

    pts, extra = _apply_a_leica_pts(tmp_path, "out.ply")
    back = read_point_cloud(tmp_path / "out.ply")
    np.testing.assert_allclose(back.points, pts, rtol=0, atol=1e-12)  # moved about their mean
    for j, k in enumerate(("intensity", "red", "green", "blue")):
        np.testing.assert_array_equal(back.attributes[k], extra[:, j], err_msg=k)
    np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(tmp_path / "out.ply")).colors),
                               extra[:, 1:] / 255.0, atol=1e-9)


def test_columns_read_over_many_blocks_are_joined_or_all_dropped(tmp_path, caplog, monkeypatch):
    """In blocks of 4 KiB (each a numpy read): the columns of every block are joined in order; one bad
    line in a late block drops those of the blocks before it too."""
    import gctr_cli.io.text as text

    monkeypatch.setattr(text, "_TEXT_BLOCK", 4096)
    pts, extra = _points(2000), _columns(2000, 2)
    (tmp_path / "good.xyz").write_text("X Y Z R Intensity\n" + _rows(pts, extra))
    back = read_point_cloud(tmp_path / "good.xyz")
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(np.stack([back.attributes["r"], back.attributes["intensity"]], axis=1), extra)
    lines = _rows(pts, extra).splitlines(keepends=True)
    lines[1900] = lines[1900].rstrip("\n") + " 7\n"
    (tmp_path / "late.xyz").write_text("".join(lines))
    caplog.set_level("WARNING", logger="gctr_cli.io")
    back = read_point_cloud(tmp_path / "late.xyz")
    np.testing.assert_array_equal(back.points, pts)
    assert back.attributes == {}
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'late.xyz'}: columns after x y z are not kept: line 1901 has 6 columns, the first data line 5"]


_CELLS = ["1", "-2.5", "3,25", "1e3", "nan", "abc", "", "14.03.2024 10:15:00,000", "Punkt 1, Gruppe A", "0,5",
          "1_0", "#", "12.5", "-0.125", "255"]


@pytest.mark.parametrize("name", ["c.xyz", "c.pts"])
def test_reading_the_columns_never_changes_the_points_or_the_error(tmp_path, name):
    """Text made of random cells, separators and headers (derandomised): with the columns after x y z
    read, x y z are the same as without (or the error is), and every attribute has one value per point."""
    hypothesis = pytest.importorskip("hypothesis")
    st = hypothesis.strategies

    lines = st.lists(st.lists(st.sampled_from(_CELLS), min_size=1, max_size=7), min_size=1, max_size=12)
    header = st.sampled_from(["", "X Y Z R G B\n", "//X,Y,Z,Intensity\n", "# x y z a b\n", "X;Y;Z;I\n", "12\n"])

    @hypothesis.settings(max_examples=150, deadline=None, derandomize=True, database=None,
                         suppress_health_check=[hypothesis.HealthCheck.function_scoped_fixture])
    @hypothesis.given(header=header, rows=lines, sep=st.sampled_from([" ", "\t", ",", ";", "; ", "\t\t"]))
    def check(header, rows, sep):
        path = tmp_path / name
        path.write_text(header + "".join(sep.join(r) + "\n" for r in rows))
        got = []
        for attributes in (False, True):
            try:
                cloud = read_point_cloud(path, attributes=attributes, min_points=1, degenerate_ok=True)
                got.append((cloud.points, cloud.attributes))
            except PointCloudError as exc:
                assert "malformed" not in str(exc)  # a reader bug, not a message about the file
                got.append((str(exc), {}))
        (before, _), (after, attrs) = got
        if isinstance(before, str):
            assert after == before
        else:
            np.testing.assert_array_equal(after, before)
            assert all(v.shape == (len(after),) and v.dtype == np.float64 for v in attrs.values())

    check()


def test_a_leading_line_of_only_separators_is_a_blank_line(tmp_path):
    """An empty spreadsheet row (``;;;``) before the header or the points was "malformed XYZ text file
    (its data does not match its header)" (a reader crash); further down it was always a blank line."""
    pts = _points(20)
    rows = "".join(";".join(map(_decimal_comma, p)) + ";7\n" for p in pts)
    path = tmp_path / "excel.txt"
    path.write_text(";;;\nX;Y;Z;I\n;;;\n" + rows + ";;;\n")
    back = read_point_cloud(path)
    np.testing.assert_array_equal(back.points, pts)
    assert list(back.attributes) == ["intensity"]
    path.write_text(",\n")
    _error(path, "contains no points")


# ----------------------------------------------------------------------------------------------------
# .pts output: the count line and rows x y z [intensity] [red green blue], which other tools read
# ----------------------------------------------------------------------------------------------------


def _pts_cloud(n: int, layout: str) -> tuple[PointCloud, list[str]]:
    """A cloud with the attributes of ``layout`` and the columns its .pts file should hold after x y z."""
    pts = np.round(RNG.normal(size=(n, 3)) * 10 + [500_000.0, 5_400_000.0, 300.0], 6)
    rgb = {k: RNG.integers(0, 256, n).astype(np.uint8) for k in ("red", "green", "blue")}
    intensity = {"intensity": RNG.integers(0, 4096, n).astype(np.uint16)}
    attrs = {"xyz": {}, "intensity": intensity, "rgb": rgb, "intensity_rgb": {**rgb, **intensity}}[layout]
    return PointCloud(pts, attrs), [k for k in ("intensity", "red", "green", "blue") if k in attrs]


@pytest.mark.parametrize("layout, n_columns", [("xyz", 3), ("intensity", 4), ("rgb", 6), ("intensity_rgb", 7)])
def test_pts_output_is_the_count_and_the_rows_open3d_reads(tmp_path, caplog, layout, n_columns):
    """gctr wrote a ``# x y z red green blue`` line after the count; PTS has no comments, and Open3D read
    every point as (0, 0, 0). Now: the count line, then x y z [intensity] [red green blue]."""
    import open3d as o3d

    cloud, columns = _pts_cloud(500, layout)
    path = tmp_path / "out.pts"
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_point_cloud(path, cloud)
    assert not caplog.records
    lines = path.read_text().splitlines()
    assert lines[0] == "500" and len(lines) == 501
    assert {len(line.split()) for line in lines[1:]} == {n_columns}
    o3d_cloud = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(o3d_cloud.points), cloud.points)
    if "red" in columns:
        rgb = np.stack([cloud.attributes[k] for k in ("red", "green", "blue")], axis=1)
        np.testing.assert_allclose(np.asarray(o3d_cloud.colors), rgb / 255.0, atol=1e-12)
    else:
        assert not o3d_cloud.has_colors()
    back = read_point_cloud(path)  # the Leica layout names the columns again
    np.testing.assert_array_equal(back.points, cloud.points)
    assert list(back.attributes) == columns
    for k in columns:
        np.testing.assert_array_equal(back.attributes[k], cloud.attributes[k], err_msg=k)


def test_pts_output_of_a_las_cloud_keeps_intensity_and_colours_and_names_the_rest(tmp_path, caplog):
    """A LAS cloud (16-bit colours, classification, GPS time, flags ...) moved to .pts: intensity and the
    colours as 8 bits are written, every other attribute is named in one warning that points to the
    formats that keep them."""
    import open3d as o3d

    n = 400
    pts = RNG.normal(size=(n, 3)) * 50 + [500_000.0, 5_400_000.0, 300.0]
    rgb8 = RNG.integers(0, 256, size=(n, 3))
    attrs = {"intensity": RNG.integers(0, 65536, n).astype(np.uint16),
             "classification": RNG.integers(0, 10, n).astype(np.uint8), "gps_time": RNG.uniform(0, 1e5, n),
             **{k: (rgb8[:, j] * 257).astype(np.uint16) for j, k in enumerate(("red", "green", "blue"))}}
    write_point_cloud(tmp_path / "scan.las", PointCloud(pts, attrs))
    las = read_point_cloud(tmp_path / "scan.las")
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_aligned(tmp_path / "scan.las", np.eye(4), tmp_path / "out.pts")
    others = [k for k in las.attributes if k not in ("intensity", "red", "green", "blue")]
    assert {"classification", "gps_time", "return_number"} <= set(others)
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'out.pts'}: attributes not written: {', '.join(others)} (a .pts file holds x y z, intensity "
        "and red green blue 0..255 only); write .ply, .pcd or .las to keep them"]
    lines = (tmp_path / "out.pts").read_text().splitlines()
    assert lines[0] == str(n) and {len(line.split()) for line in lines[1:]} == {7}
    o3d_cloud = o3d.io.read_point_cloud(str(tmp_path / "out.pts"))
    np.testing.assert_allclose(np.asarray(o3d_cloud.points), las.points, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(o3d_cloud.colors), rgb8 / 255.0, atol=1e-12)
    back = read_point_cloud(tmp_path / "out.pts").attributes
    np.testing.assert_array_equal(back["intensity"], las.attributes["intensity"])
    np.testing.assert_array_equal(np.stack([back[k] for k in ("red", "green", "blue")], axis=1), rgb8)


@pytest.mark.parametrize("colours, named", [
    ({"red": np.full(20, 0.5), "green": np.full(20, 0.25), "blue": np.ones(20)}, "red, green, blue"),  # 0..1
    ({"red": np.full(20, 300.0), "green": np.ones(20), "blue": np.ones(20)}, "red, green, blue"),  # (as text)
    ({"red": np.full(20, 7, np.uint8), "nx": np.ones(20)}, "red, nx"),  # one colour alone
])
def test_pts_colours_are_whole_numbers_0_to_255_or_not_written(tmp_path, caplog, colours, named):
    """Open3D reads PTS colours with ``%d``: ``0.5`` broke the line (the point read as garbage) and 300
    wrapped to 44. Colours that are not whole numbers 0..255 are named, not written (integer colours
    above 255 are 16-bit ones: their high byte is written, as in PLY and PCD)."""
    import open3d as o3d

    pts = RNG.normal(size=(20, 3))
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_point_cloud(tmp_path / "c.pts", PointCloud(pts, colours))
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'c.pts'}: attributes not written: {named} (a .pts file holds x y z, intensity and red "
        "green blue 0..255 only); write .ply, .pcd or .las to keep them"]
    assert {len(line.split()) for line in (tmp_path / "c.pts").read_text().splitlines()[1:]} == {3}
    np.testing.assert_array_equal(np.asarray(o3d.io.read_point_cloud(str(tmp_path / "c.pts")).points), pts)


def test_text_colours_reach_a_las_output_at_their_brightness(tmp_path):
    """Whole 0..255 colour columns are read as 8-bit colours, so LAS widens them to its 16 bits (as floats
    they were written as 121 of 65535: nearly black); colours that are not whole 0..255 stay floats."""
    import laspy

    pts, extra = _apply_a_leica_pts(tmp_path, "out.las")
    las = laspy.read(tmp_path / "out.las")
    np.testing.assert_array_equal(np.asarray(las.red), extra[:, 1].astype(np.uint16) * 257)
    np.testing.assert_array_equal(np.asarray(las.blue), extra[:, 3].astype(np.uint16) * 257)
    (tmp_path / "half.xyz").write_text("# x y z red green blue\n" + _rows(pts, np.full((200, 3), 0.5)))
    assert read_point_cloud(tmp_path / "half.xyz").attributes["red"].dtype == np.float64


# ----------------------------------------------------------------------------------------------------
# .csv files and quoted cells (spreadsheet and pandas exports)
# ----------------------------------------------------------------------------------------------------


def test_a_csv_file_round_trips_with_its_attributes(tmp_path):
    """``.csv`` is read and written as text: a header line ``x,y,z,intensity`` and comma-separated rows,
    read back exactly with the attribute named by the header."""
    pts = _points(N_BIG)
    intensity = RNG.uniform(0.0, 1.0, N_BIG)
    write_point_cloud(tmp_path / "out.csv", PointCloud(pts, {"intensity": intensity}))
    lines = (tmp_path / "out.csv").read_text().splitlines()
    assert lines[0] == "x,y,z,intensity"
    assert lines[1].count(",") == 3 and " " not in lines[1]
    back = read_point_cloud(tmp_path / "out.csv")
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(back.attributes["intensity"], intensity)


@pytest.mark.parametrize("style", ["all", "nonnumeric_text", "decimal_comma"])
def test_quoted_cells_are_read_as_their_values(tmp_path, style):
    """A spreadsheet or pandas export quotes its cells: ``"x","y","z"`` and ``"1.5","2.25","3"`` (every
    cell), a quoted label ``"Punkt 1, Gruppe A"`` after x y z (one cell, not three), or decimal commas
    quoted in a comma-separated file (``"1,5","2,25","3,0"`` is x=1.5 y=2.25 z=3, never six columns).
    They used to be refused as having no numeric x y z columns, or read as the wrong columns."""
    pts = _points(N_BIG)
    if style == "all":
        rows = ['"x","y","z","intensity"'] + [",".join(f'"{v}"' for v in (*p, i)) for i, p in enumerate(pts)]
    elif style == "nonnumeric_text":
        rows = ["x,y,z,label"] + [f'{p[0]},{p[1]},{p[2]},"Punkt {i}, Gruppe A"' for i, p in enumerate(pts)]
    else:
        rows = ['"x","y","z"'] + [",".join(f'"{_decimal_comma(v)}"' for v in p) for p in pts]
    path = tmp_path / "export.csv"
    path.write_text("\n".join(rows) + "\n")
    back = read_point_cloud(path)
    np.testing.assert_allclose(back.points, pts, rtol=0, atol=1e-9)
    if style == "all":
        np.testing.assert_array_equal(back.attributes["intensity"], np.arange(N_BIG))
    if style == "nonnumeric_text":
        assert back.attributes == {}  # a text column is not an attribute (a warning says so)


def test_a_stray_quote_is_an_error_naming_the_line(tmp_path):
    pts = _points(30)
    rows = [f"{p[0]},{p[1]},{p[2]}" for p in pts]
    rows[12] = f'"{pts[12][0]},{pts[12][1]},{pts[12][2]}'
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(rows) + "\n")
    _error(path, "line 13", "non-numeric value")


@pytest.mark.parametrize(("header", "order", "columns"), [
    (",x,y,z", "index", "2, 3 and 4"),
    ("id,x,y,z", "index", "2, 3 and 4"),
    ("Intensity X Y Z", "index", "2, 3 and 4"),
    ("z,y,x", "reversed", "3, 2 and 1"),
])
def test_a_header_that_puts_x_y_z_elsewhere_is_refused(tmp_path, header, order, columns):
    """x y z are read from the first three columns. A header naming them elsewhere — pandas' ``to_csv``
    with its index first, an ``id`` column, ``z,y,x`` — was read as the wrong cloud without a word (the
    index as x made a bunny planar; z,y,x a mirror image)."""
    pts = _points(40)
    sep = " " if " " in header else ","
    rows = [sep.join(map(str, [i, *p] if order == "index" else p[::-1])) for i, p in enumerate(pts)]
    path = tmp_path / "export.csv"
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    msg = _error(path, f"names x, y and z as columns {columns}, but x y z are read from the first three columns")
    assert msg.endswith("(pandas: to_csv(..., index=False))") == header.startswith(",")


def test_a_header_naming_x_y_z_first_or_naming_other_things_is_read(tmp_path):
    pts = _points(40)
    for header in ("x,y,z,id", "X,Y,Z", "easting,northing,height", "x,y,z scan of the hall"):
        path = tmp_path / "ok.csv"
        path.write_text(header + "\n" + "\n".join(",".join(map(str, [*p, i])) for i, p in enumerate(pts)) + "\n")
        np.testing.assert_array_equal(read_point_cloud(path).points, pts)
