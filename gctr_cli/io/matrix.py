"""4x4 transform matrices: four lines of four numbers (GUIDE §1), read strictly, written at
``%.17g`` (bit-exact round trip) and atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gctr_cli.fsutil import atomic_write, write_error
from gctr_cli.io.errors import MatrixError, quote
from gctr_cli.io.paths import check_input_file

__all__ = ["format_matrix", "read_matrix", "write_matrix"]

MAX_MATRIX_BYTES = 1 << 20


def read_matrix(path: str | Path) -> np.ndarray:
    """Read a 4x4 transform: four lines of four numbers (whitespace- or comma-separated).

    Blank lines, ``#`` comment lines and trailing ``# ...`` comments are ignored. The numbers must be
    finite and the last row must be ``0 0 0 1``. Raises :class:`MatrixError` naming the file and the
    problem (with the line number where relevant).
    """
    path = Path(path)
    size = check_input_file(path, MatrixError)
    if size > MAX_MATRIX_BYTES:
        raise MatrixError(f"{path}: is {size} bytes, too large for a matrix file (four lines of four numbers)")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise MatrixError(f"{path}: not a text file (invalid UTF-8 at byte {exc.start})") from None
    except OSError as exc:
        raise MatrixError(f"{path}: cannot read file ({exc.strerror or 'operating system error'})") from None

    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        tokens = line.split()
        if len(tokens) != 4:
            raise MatrixError(f"{path}: line {lineno} has {len(tokens)} values, expected 4 numbers: "
                              f"{quote(raw.strip(), 80)} ({_layout_hint(line) or FOUR_BY_FOUR})")
        if len(rows) == 4:
            raise MatrixError(f"{path}: more than 4 rows of numbers (extra row on line {lineno})")
        try:
            if any("_" in t for t in tokens):  # float() reads 1_0 as 10; no matrix writer does
                raise ValueError
            rows.append([float(t) for t in tokens])
        except ValueError:
            hint = _layout_hint(line)
            raise MatrixError(f"{path}: line {lineno} contains a non-numeric value: {quote(raw.strip(), 80)}"
                              + (f" ({hint})" if hint else "")) from None
    if len(rows) != 4:
        raise MatrixError(f"{path}: expected 4 rows of 4 numbers, found {len(rows)}")
    T = np.array(rows, dtype=np.float64)
    _check_matrix(T, str(path))
    return T


#: how a matrix file is laid out, for a line that is not
FOUR_BY_FOUR = "a matrix file is four lines of four numbers, separated by spaces or commas"


def _layout_hint(line: str) -> str:
    """What to change in a matrix line written in another layout (semicolons, brackets), or ""."""
    if ";" in line:
        return "';' does not separate numbers here: use spaces or commas, and '.' for decimals"
    if any(c in line for c in "[]()"):
        return "brackets are not read: write the numbers alone, four lines of four"
    return ""


def write_matrix(path: str | Path, T: np.ndarray) -> None:
    """Write a 4x4 matrix as four lines of four ``%.17g`` numbers (bit-exact round trip), atomically.

    Missing parent folders are created.
    """
    path = Path(path)
    try:
        M = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise MatrixError(f"{path}: matrix is not numeric") from None
    if M.shape != (4, 4):
        raise MatrixError(f"{path}: matrix must be 4x4, got shape {M.shape}")
    if not np.isfinite(M).all():
        raise MatrixError(f"{path}: matrix contains non-finite values")
    try:
        atomic_write(path, format_matrix(M).encode("ascii"))
    except OSError as exc:
        raise MatrixError(f"{path}: cannot write file ({write_error(path, exc)})") from None


def format_matrix(T: np.ndarray) -> str:
    """Return the text of a 4x4 matrix: four lines of four space-separated ``%.17g`` numbers."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise MatrixError(f"matrix must be 4x4, got shape {M.shape}")
    return "".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in M)


def _check_matrix(T: np.ndarray, where: str) -> None:
    if not np.isfinite(T).all():
        bad = [f"({i},{j})" for i, j in zip(*np.nonzero(~np.isfinite(T)))]
        raise MatrixError(f"{where}: matrix contains non-finite values at {', '.join(bad)}")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        raise MatrixError(
            f"{where}: last row must be '0 0 0 1' for a similarity transform, got {' '.join(f'{v:g}' for v in T[3])}"
        )
