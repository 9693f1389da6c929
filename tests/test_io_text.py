"""Text clouds (.xyz .txt .pts): the decimal mark read off x y z alone, the columns after x y z kept
as attributes, and .pts output that other tools read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gctr_cli.io import PointCloudError, load_point_cloud, read_point_cloud

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
