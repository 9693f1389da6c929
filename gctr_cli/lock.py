"""The lock of an output folder: one gctr batch writes to a folder at a time.

``OUTDIR/.gctr.lock`` is created with ``O_CREAT | O_EXCL`` and holds ``pid start-time host``. A second
batch on the same folder is refused (:class:`~gctr_cli.errors.LockError`); a lock left by a process
that no longer runs (on this host; a reused pid is told apart by its start time) is stale and taken
over. A process on another host cannot be asked, so the holder touches its lock every
:data:`HEARTBEAT_S`; another host's lock untouched for :data:`STALE_AFTER_S` is stale (a Kubernetes
CronJob pod evicted mid-run: every later pod has another host name, and each night was refused).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

from gctr_cli.errors import LockError

logger = logging.getLogger(__name__)

__all__ = ["LOCK_NAME", "OutdirLock"]

LOCK_NAME = ".gctr.lock"
#: seconds between two touches of a held lock (its modification time says the holder is alive)
HEARTBEAT_S = 60.0
#: a lock of another host untouched this long is stale (generous: clocks of two hosts may differ)
STALE_AFTER_S = 900.0


def _proc_stat(pid: int) -> list[str] | None:
    """Fields of /proc/<pid>/stat from the state onwards (Linux), or None."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[-1].split()


def _process_start_time(pid: int) -> str:
    fields = _proc_stat(pid)
    return fields[19] if fields and len(fields) > 19 else "?"


def _pid_alive(pid: int, start_time: str = "?") -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    fields = _proc_stat(pid)
    if fields is not None:
        if fields[0] in ("Z", "X"):  # zombie: killed, not yet reaped
            return False
        if start_time != "?" and len(fields) > 19 and fields[19] != start_time:
            return False  # the pid was reused by another process
    return True


class OutdirLock:
    """``OUTDIR/.gctr.lock``: created with ``O_CREAT | O_EXCL``, holds ``pid start-time host``.

    A lock whose process no longer exists (on this host) is stale and taken over.
    """

    def __init__(self, outdir: Path) -> None:
        self.path = Path(outdir) / LOCK_NAME
        self.content = f"{os.getpid()} {_process_start_time(os.getpid())} {socket.gethostname()}\n"
        self.held = False
        self._beat = threading.Event()

    def _holder(self) -> tuple[str, bool]:
        """(description, alive) of the current lock holder."""
        try:
            text = self.path.read_text()
            age = time.time() - self.path.stat().st_mtime
        except FileNotFoundError:
            return "", False
        except OSError as exc:
            return f"unreadable lock ({exc})", True
        parts = text.split()
        if not parts:
            # a lock being created right now has no content for a moment
            return "a process that is starting", age < 10
        try:
            pid = int(parts[0])
        except ValueError:
            return f"unparseable lock {text[:40]!r}", age < 10
        start = parts[1] if len(parts) > 1 else "?"
        host = parts[2] if len(parts) > 2 else socket.gethostname()
        if host != socket.gethostname():
            if age >= STALE_AFTER_S:
                return f"pid {pid} on host {host}, untouched for {age / 60:.0f} min", False
            return f"pid {pid} on host {host}", True
        return f"pid {pid}", _pid_alive(pid, start)

    def acquire(self) -> None:
        for _ in range(5):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                who, alive = self._holder()
                if alive:
                    raise LockError(
                        f"another gctr batch ({who}) is writing to {self.path.parent}; wait for it to finish "
                        f"or choose another output folder (if no such batch is running, delete {self.path})"
                    ) from None
                self._break_stale(who)
                continue
            try:
                os.write(fd, self.content.encode())
                os.fsync(fd)
            except OSError:  # e.g. a full disk: leave no empty lock behind
                self.path.unlink(missing_ok=True)
                raise
            finally:
                os.close(fd)
            self.held = True
            self._beat = threading.Event()
            threading.Thread(target=self._heartbeat, args=(self._beat,), name="gctr-lock-heartbeat",
                             daemon=True).start()
            return
        raise LockError(f"could not acquire {self.path} (it keeps changing); is another batch starting?")

    def _break_stale(self, who: str) -> None:
        aside = self.path.with_name(f"{LOCK_NAME}.stale.{os.getpid()}")
        try:
            before = self.path.read_text()
            os.rename(self.path, aside)
        except FileNotFoundError:
            return
        try:
            if aside.read_text() != before:  # somebody replaced it meanwhile: put theirs back
                try:
                    os.link(aside, self.path)
                except FileExistsError:
                    pass
                return
            logger.warning("removed a stale lock %s left by %s (that batch is no longer running; its pid may "
                           "now be another process)" if " on host " not in who else
                           "removed a stale lock %s left by %s (a running batch touches its lock every minute)",
                           self.path, who)
        finally:
            try:
                aside.unlink()
            except FileNotFoundError:
                pass

    def _heartbeat(self, stop: threading.Event) -> None:
        """Touch the lock every :data:`HEARTBEAT_S` until ``stop`` is set (a batch on another host tells a
        running holder from one that died by the lock's age)."""
        while not stop.wait(HEARTBEAT_S):
            try:
                os.utime(self.path)
            except OSError:
                pass  # gone or unwritable: the batch itself reports its folder's problems

    def release(self) -> None:
        if not self.held:
            return
        self.held = False
        self._beat.set()
        try:
            if self.path.read_text() == self.content:
                self.path.unlink()
        except FileNotFoundError:
            pass

    def __enter__(self) -> OutdirLock:
        self.acquire()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()
