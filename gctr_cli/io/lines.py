"""Reading text data line by line with a bounded line length, in blocks for speed.

Shared by the ASCII PLY and ASCII PCD readers: every element instance is one line with a declared
number of values, so a short line is an error naming its line number instead of shifting every
later value by one.
"""

from __future__ import annotations

import io as _stdio
import logging
import warnings
from pathlib import Path

import numpy as np

from gctr_cli.io.cloud import ATTRIBUTE_NOTE, integer_misfit
from gctr_cli.io.errors import PointCloudError, clean, content_hint, quote

__all__ = ["MAX_LINE", "LineReader", "as_declared", "binary_data", "header_line", "numeric_text", "parse_float",
           "read_rows"]

logger = logging.getLogger("gctr_cli.io")

#: longest line accepted in a text body (bytes); a longer one means the file is not text we can read
MAX_LINE = 1 << 20
#: bytes read per block
BLOCK = 1 << 22


_NUMERIC_TEXT = frozenset(b"0123456789+-.eE \t\r\n")


def _peek(fh, n: int = 256) -> bytes:
    """The first ``n`` bytes from ``fh``'s position, which is left where it was."""
    start = fh.tell()
    data = fh.read(n)
    fh.seek(start)
    return data


def content_note(fh) -> str:
    """``; `` and what the first bytes of the open file ``fh`` show it to be (:func:`content_hint`), or "":
    the end of a reader's "not a PLY / PCD file" message."""
    fh.seek(0)
    hint = content_hint(fh.read(512))
    return f"; {hint}" if hint else ""


def header_line(raw: bytes) -> str:
    """A header line as text: UTF-8 when it is (a property named ``intensité`` by a current tool), else
    Latin-1, which decodes any byte."""
    try:
        return raw.decode("utf-8").strip()
    except UnicodeDecodeError:
        return raw.decode("latin-1").strip()


def numeric_text(fh) -> bool:
    """Whether the data section that starts at ``fh``'s position (left where it was) is numbers written
    as text: the bytes of binary numbers are almost never all digits, signs, points and blanks, so a
    header that says binary over such data was written for another format."""
    data = _peek(fh)
    return len(data) >= 16 and b"\n" in data and all(b in _NUMERIC_TEXT for b in data)


def binary_data(fh) -> bool:
    """Whether the data section that starts at ``fh``'s position (left where it was) is binary: a NUL byte,
    or more than a tenth of its first 256 bytes neither printable ASCII nor blanks (text numbers, even
    with a stray UTF-8 comment, stay well below), so a header that says ascii over it was written for
    another format."""
    data = _peek(fh)
    odd = sum(1 for b in data if not (32 <= b < 127 or b in b"\t\r\n"))
    return len(data) >= 16 and (b"\x00" in data or odd > len(data) // 10)


def parse_float(tok: bytes) -> float | None:
    """A decimal number token (``1``, ``-2.5e3``, ``nan``, ``inf``) as float, or None."""
    if b"_" in tok:  # Python accepts 1_000; no point cloud writer does
        return None
    try:
        return float(tok)
    except ValueError:
        return None


class LineReader:
    """Whole lines of a binary file object from its current position, counting line numbers."""

    def __init__(self, fh, path: Path, lines_before: int) -> None:
        self.fh, self.path = fh, path
        self.lineno = lines_before  # number of the last line handed out
        self._buf = b""
        self._pos = 0  # start of the unread part of _buf
        self._eof = False

    def _fill(self) -> bool:
        if self._eof:
            return False
        chunk = self.fh.read(BLOCK)
        if not chunk:
            self._eof = True
            return False
        self._buf = self._buf[self._pos :] + chunk
        self._pos = 0
        return True

    def _too_long(self) -> PointCloudError:
        return PointCloudError(
            f"{self.path}: line {self.lineno + 1} is longer than {MAX_LINE // 1024} KiB (the data is not text lines)"
        )

    def take(self, max_lines: int) -> tuple[bytes, int]:
        """Up to ``max_lines`` whole lines (each ending in ``\\n``, except maybe the file's last) and
        their number; ``(b"", 0)`` at the end of the file."""
        while True:
            nl = self._buf.find(b"\n", self._pos)
            if nl >= 0 or self._eof:
                break
            if len(self._buf) - self._pos > MAX_LINE:
                raise self._too_long()
            self._fill()
        start = self._pos
        if nl < 0:  # last line of the file, without a line end
            if len(self._buf) == start:
                return b"", 0
            if len(self._buf) - start > MAX_LINE:
                raise self._too_long()
            self._pos = len(self._buf)
            self.lineno += 1
            return self._buf[start:], 1
        if nl - start > MAX_LINE:
            raise self._too_long()
        if max_lines == 1:
            k, cut = 1, nl + 1
        else:
            ends = np.flatnonzero(np.frombuffer(self._buf, dtype=np.uint8, offset=start) == 10)
            k = min(max_lines, len(ends))
            cut = start + int(ends[k - 1]) + 1
        self._pos = cut
        self.lineno += k
        return self._buf[start:cut], k

    def line(self) -> bytes | None:
        """The next line without its line end, or None at the end of the file."""
        data, k = self.take(1)
        return data.rstrip(b"\r\n") if k else None

    def lines_left(self) -> int:
        """How many non-blank lines follow (read to the end): data a header did not declare."""
        n = 0
        while True:
            data, k = self.take(1 << 16)
            if not k:
                return n
            n += sum(1 for ln in data.splitlines() if ln.strip())


def _fast_block(block: bytes, n_values: int) -> np.ndarray | None:
    """The rows of a block of plain numeric lines via numpy's C parser, or None (slow path decides)."""
    if b"_" in block or b"\r" in block.replace(b"\r\n", b"\n") or b"\x00" in block:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            arr = np.loadtxt(_stdio.BytesIO(block), dtype=np.float64, comments=None, ndmin=2, encoding="latin-1")
        except ValueError:
            return None
    n_lines = block.count(b"\n") + (not block.endswith(b"\n"))
    if arr.shape != (n_lines, n_values):
        return None  # blank lines or a wrong number of values: the slow path says which
    return arr


def read_rows(reader: LineReader, n_rows: int, n_values: int, what: str, plural: str = "lines") -> np.ndarray:
    """``n_rows`` lines of exactly ``n_values`` numbers each, as an ``(n_rows, n_values)`` float64 array.

    Blank lines are skipped. The caller has checked that the file is large enough for the declared
    rows (at least two bytes per value), so the array is bounded by the file size. Errors name the
    line: a line with too few or too many values, a non-numeric value, or data that ends early.
    """
    out = np.empty((n_rows, n_values), dtype=np.float64)
    got = 0
    while got < n_rows:
        start_line = reader.lineno
        block, k = reader.take(min(n_rows - got, 1 << 16))
        if k == 0:
            raise PointCloudError(
                f"{reader.path}: truncated: the header declares {n_rows} {plural} but the data "
                f"ends after {got}"
            )
        arr = _fast_block(block, n_values)
        if arr is not None:
            out[got : got + len(arr)] = arr
            got += len(arr)
            continue
        for i, raw in enumerate(block.split(b"\n")[:k]):
            toks = raw.split()
            if not toks:
                continue
            lineno = start_line + i + 1
            if len(toks) != n_values:
                raise PointCloudError(
                    f"{reader.path}: line {lineno}: {what} has {len(toks)} values, the header declares {n_values}"
                )
            for j, t in enumerate(toks):
                v = parse_float(t)
                if v is None:
                    raise PointCloudError(f"{reader.path}: line {lineno}: non-numeric value {quote(t)} in {what}")
                out[got, j] = v
            got += 1  # never more than n_rows: the block holds at most n_rows - got lines
    return out


def as_declared(path: Path, name: str, declared: str, values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """An attribute read as float64 text in its declared type ``dtype`` (``declared`` names it as the
    header does). Text can hold what an integer type cannot (``300`` in a ``uchar``, ``0.5`` in an
    ``int``), which a cast would wrap or truncate without a word: such a column stays float64, with a
    warning."""
    if dtype.kind not in "iu":
        return values.astype(dtype)
    info = np.iinfo(dtype)
    misfit = integer_misfit(values, int(info.min), int(info.max))
    if misfit is None:
        if dtype.itemsize == 8 and len(values) and np.abs(values).max() > 2.0**53:
            logger.warning("%s: %r (%s) holds whole numbers beyond 2**53, which text is read as float64 and "
                           "rounds (e.g. %d); its last digits may differ from the file", clean(path), name, declared,
                           int(values[np.argmax(np.abs(values))]), extra=ATTRIBUTE_NOTE)
        return values.astype(dtype)
    logger.warning("%s: %r is declared %s but holds values it cannot (e.g. %s; range %d..%d, whole numbers); "
                   "kept as float64", clean(path), name, declared, misfit, info.min, info.max, extra=ATTRIBUTE_NOTE)
    return values.astype(np.float64)
