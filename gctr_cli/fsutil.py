"""Small helpers shared by every writer and every worker (no numpy import here: the CLI uses them
before numpy may be loaded)."""

from __future__ import annotations

import os
import signal
import stat
import sys
import uuid
from collections.abc import Iterable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

#: environment variables that cap native thread pools; set to 1 in every worker before numpy loads
THREAD_ENV_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "BLIS_NUM_THREADS",
)


def output_problem(path: str | Path) -> str | None:
    """Why a file cannot be written at ``path`` (``None`` if it can, as far as can be told without
    writing it): a folder in its place, a file where a parent folder should be, or a parent folder in
    which no file can be created (tested by creating and removing a temporary file there; folders
    that do not exist yet are not created)."""
    try:
        return _output_problem(Path(path))
    except OSError as exc:  # a name too long, a folder that cannot be entered, ...
        return exc.strerror or str(exc)


def _is_special_file(path: Path) -> bool:
    """Whether ``path`` exists and is not a regular file or folder (a device such as /dev/null or
    /dev/stdout, a FIFO): replacing it atomically would replace the device itself."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def _output_problem(path: Path) -> str | None:
    if path.is_dir():
        return "it is a folder"
    if _is_special_file(path):
        return None if os.access(path, os.W_OK) else "it cannot be written"
    for parent in path.absolute().parents:
        if not parent.exists():
            continue
        if not parent.is_dir():
            return f"{parent} is a file, not a folder"
        probe = parent / f".gctr-probe-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        except OSError as exc:
            return f"cannot create files in {parent} ({exc.strerror or exc})"
        try:
            os.unlink(probe)
        except OSError:
            pass
        return None
    return None


def write_error(path: str | Path, exc: OSError) -> str:
    """The message of a failed write to ``path``: the problem :func:`output_problem` finds (clearer than
    the operating system's "File exists" for a parent that is a file), else the system's error."""
    return output_problem(path) or exc.strerror or "operating system error"


@contextmanager
def environment(values: dict[str, str]) -> Iterator[None]:
    """Set the environment variables ``values`` for the ``with`` block, then restore them: a process
    spawned inside sees them at exec."""
    saved = {var: os.environ.get(var) for var in values}
    try:
        os.environ.update(values)
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


def single_thread_env() -> AbstractContextManager[None]:
    """Every :data:`THREAD_ENV_VARS` set to 1 for the ``with`` block (:func:`environment`): a process
    spawned inside sees them at exec, before it imports numpy."""
    return environment({var: "1" for var in THREAD_ENV_VARS})


@contextmanager
def processes_ignore_ctrl_c() -> Iterator[None]:
    """Processes started within ignore SIGINT (an ignored signal stays ignored through exec, and Python
    then installs no KeyboardInterrupt handler): a Ctrl-C reaches the whole process group, and a worker
    still importing printed a traceback; stopping workers is the batch's business. Keep the block short
    (a process start): a Ctrl-C within it is lost for this process too."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


#: the signals that stop a batch (SIGHUP where the platform has it)
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


@contextmanager
def stop_signals_deferred() -> Iterator[list[int]]:
    """Within the block, SIGINT, SIGTERM and SIGHUP are only recorded (in the yielded list), not acted on:
    code that must not be cut in the middle (starting a dask cluster, which stopped half-started printed
    tracebacks from its exit handlers) runs to its end; the caller then cleans up and acts on them (e.g.
    with :func:`signal.raise_signal`, once the previous handlers are back). A signal ignored before (SIGHUP
    under ``nohup``) stays ignored."""
    import threading

    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return

    def record(signum, frame):  # noqa: ARG001
        caught.append(signum)

    previous = {}
    try:
        for sig in STOP_SIGNALS:  # within the try: one that arrives meanwhile finds every handler restored
            if signal.getsignal(sig) is not signal.SIG_IGN:
                previous[sig] = signal.getsignal(sig)
                signal.signal(sig, record)
        yield caught
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker now, with SIGHUP ignored: it ignores SIGINT and SIGTERM
    itself but not SIGHUP, so a closed terminal killed it and the batch's orderly stop (closing the dask
    cluster's semaphores) printed a dozen tracebacks. Started later by whatever needs it first, it also
    unblocks signals in that thread."""
    import threading
    from multiprocessing import resource_tracker

    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "SIGHUP"):
        return
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        resource_tracker.ensure_running()
    finally:
        signal.signal(signal.SIGHUP, previous)


def set_parent_death_signal() -> None:
    """Linux: this (child) process gets SIGKILL when its parent dies, so a killed batch or benchmark
    leaves no orphan computing. A no-op elsewhere or if ``prctl`` is unavailable."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except Exception:  # noqa: BLE001 - best effort
        pass


def atomic_write(path: str | Path, data: bytes | str | Iterable[bytes]) -> None:
    """Write ``data`` (bytes, text written as UTF-8 without newline translation, or pieces of bytes
    written one after another as they come: a large text file need not be built whole first) so that a
    reader or a kill never sees a half-written file: a temporary file next to ``path``, fsync,
    then ``os.replace``. Parent folders are created; the temporary file is removed on failure.
    Raises OSError (and whatever producing a piece raises).
    """
    path = Path(path)
    pieces: Iterable[bytes]
    if isinstance(data, str):
        pieces = [data.encode("utf-8")]
    elif isinstance(data, bytes | bytearray):
        pieces = [bytes(data)]  # (the same object for bytes: no copy)
    else:
        pieces = data
    if _is_special_file(path):  # /dev/null, /dev/stdout, a FIFO: write into it, never replace it
        with open(path, "wb") as fh:
            for piece in pieces:
                fh.write(piece)
        return
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # os.open with 0o666 honours the umask (tempfile would give 0600 files).
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
        with os.fdopen(fd, "wb") as fh:
            for piece in pieces:
                fh.write(piece)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            tmp.unlink()
        except OSError:
            pass
        if isinstance(exc, OSError) and exc.errno is not None and str(tmp) in (exc.filename, exc.filename2):
            # the temporary name is gone by the time a message shows it: name the file being written
            raise type(exc)(exc.errno, exc.strerror, str(path)) from exc
        raise
