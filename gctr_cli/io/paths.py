"""What a path the user gave points to, judged by that name (links are followed, never reported
by their target's name, and a link's target may have any name: DVC's cache files have none)."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from gctr_cli.io.errors import clean

__all__ = ["input_file_problem", "check_input_file"]


def input_file_problem(path: str | os.PathLike) -> tuple[str | None, int]:
    """``(problem, size)``: why ``path`` cannot be read as a data file (None if it can) and its size.

    Distinguishes a missing file, a broken link, a link loop, a folder, a device (``/dev/zero``), a
    pipe or socket, an unreadable file and an empty file. Never raises.
    """
    p = os.fspath(path)
    try:
        lst = os.lstat(p)
    except FileNotFoundError:
        return "file does not exist", 0
    except NotADirectoryError:
        return "file does not exist (a parent in the path is not a folder)", 0
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "is part of a symbolic link loop (the link never reaches a file)", 0
        return f"cannot be accessed ({clean(exc.strerror or 'operating system error', 80)})", 0
    is_link = stat.S_ISLNK(lst.st_mode)
    try:
        st = os.stat(p)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "is a symbolic link loop (the link never reaches a file)", 0
        if exc.errno in (errno.ENOENT, errno.ENOTDIR) and is_link:
            try:
                target = os.readlink(p)
            except OSError:
                target = "?"
            return f"is a broken symbolic link (its target {clean(target, 200)} does not exist)", 0
        return f"cannot be accessed ({clean(exc.strerror or 'operating system error', 80)})", 0
    via = " (through a symbolic link)" if is_link else ""
    mode = st.st_mode
    if stat.S_ISDIR(mode):
        return f"is a folder, not a regular file{via}", 0
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return f"is a device, not a regular file{via}", 0
    if stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode):
        return f"is a pipe or socket, not a regular file{via}", 0
    if not stat.S_ISREG(mode):
        return f"is not a regular file{via}", 0
    if not os.access(p, os.R_OK):
        return "is not readable (permission denied)", 0
    if st.st_size == 0:
        return "file is empty (0 bytes)", 0
    return None, st.st_size


def check_input_file(path: Path, err: type[ValueError]) -> int:
    """Raise ``err("<path>: <problem>")`` if ``path`` cannot be read as a data file; return its size."""
    problem, size = input_file_problem(path)
    if problem:
        raise err(f"{path}: {problem}")
    return size
