"""The errors of the I/O layer and the rules every message follows.

A message names the path the user wrote, says what is wrong in words (never a Python exception name
or text), contains no control characters (a header's NUL bytes or terminal escapes never reach a CSV
cell or the terminal) and is capped in length (a 60,000-character property name gives a short quote).
"""

from __future__ import annotations

import re

__all__ = ["MAX_MESSAGE", "MatrixError", "PointCloudError", "clean", "content_hint", "escaped", "quote"]

#: longest message an error carries (characters); the rest is replaced by "..."
MAX_MESSAGE = 600
#: longest quoted token (a property name, a bad value) inside a message
MAX_TOKEN = 40

# the lone surrogates that stand for undecodable bytes in a file name (os.fsdecode's surrogateescape)
_SURROGATE = re.compile("[\ud800-\udfff]")
# C0 and C1 control characters, DEL, and the Unicode line/paragraph separators and bidi controls
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def clean(text: object, limit: int = MAX_MESSAGE) -> str:
    """``text`` with every control character replaced by ``?``, every undecodable byte of a file name
    shown as ``\\xe9`` (as :func:`escaped` does), and cut to ``limit`` characters."""
    s = _CONTROL.sub("?", _SURROGATE.sub(_byte, str(text)))
    return s if len(s) <= limit else s[: max(limit - 3, 0)] + "..."


def escaped(text: object) -> str:
    """``text`` with every undecodable byte of a file name (a lone surrogate) as ``\\xe9``, the byte it
    stands for: the whole text stays writable as UTF-8 (a report, a summary under a strict locale)."""
    s = str(text)
    return _SURROGATE.sub(_byte, s) if _SURROGATE.search(s) else s


def _byte(match: re.Match[str]) -> str:
    """``\\xe9`` for the surrogate that stands for byte 0xE9 (surrogateescape); U+FFFD for any other."""
    code = ord(match.group()) - 0xDC00
    return f"\\x{code:02x}" if 0x80 <= code <= 0xFF else "\ufffd"


#: file signatures a point-cloud reader may meet under the wrong name: (leading bytes, what to tell the user)
_SIGNATURES = (
    (b"\x1f\x8b", "it is gzip-compressed: decompress it first, e.g. with gunzip"),
    (b"PK\x03\x04", "it is a zip archive: extract it first"),
    (b"BZh", "it is bzip2-compressed: decompress it first, e.g. with bunzip2"),
    (b"\xfd7zXZ\x00", "it is xz-compressed: decompress it first, e.g. with unxz"),
    (b"\x28\xb5\x2f\xfd", "it is zstd-compressed: decompress it first, e.g. with unzstd"),
    (b"ply\n", "its content is PLY: name it .ply"),
    (b"ply\r\n", "its content is PLY: name it .ply"),
    (b"LASF", "its content is LAS or LAZ: name it .las or .laz"),
    (b"ASTM-E57", "its content is E57: name it .e57"),
)
_PCD_START = re.compile(rb"^\s*(#\s*\.PCD|VERSION\s|FIELDS\s)", re.IGNORECASE)
_NUMBER = rb"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?"
_NUMBERS_LINE = re.compile(rb"^\s*" + _NUMBER + rb"([\s,;]+" + _NUMBER + rb"){2,}\s*$")  # three or more numbers


def content_hint(head: bytes) -> str:
    """What a file's first bytes (``head``, a few hundred) show it to be, for the message of a reader
    that did not find its own format there: compressed, another format, or text columns of numbers.
    Empty when they show nothing known."""
    for signature, hint in _SIGNATURES:
        if head.startswith(signature):
            return hint
    if _PCD_START.match(head):
        return "its content is PCD: name it .pcd"
    first = head.split(b"\n", 1)[0].rstrip(b"\r")
    if _NUMBERS_LINE.match(first):
        return "it holds text columns of numbers: name it .xyz, .txt or .csv"
    return ""


def quote(token: object, limit: int = MAX_TOKEN) -> str:
    """A token from a file (bytes or text), cleaned, capped and in single quotes, for a message."""
    if isinstance(token, (bytes, bytearray)):
        token = bytes(token[: limit * 4]).decode("latin-1")
    return "'" + clean(token, limit) + "'"


class _CleanError(ValueError):
    def __init__(self, message: object = "") -> None:
        super().__init__(clean(message))


class PointCloudError(_CleanError):
    """A point cloud file is missing, unreadable, malformed or degenerate (the message says which)."""


class MatrixError(_CleanError):
    """A matrix file is missing, malformed, or the matrix is not a valid 4x4 transform."""
