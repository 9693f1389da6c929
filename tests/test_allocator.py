"""glibc's malloc keeps freed blocks for reuse in the processes gctr sets up (gctr_cli.allocator)."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO

from data_scripts import fake_engine
from gctr_cli import allocator
from gctr_cli.batch import run_batch


def _glibc_with_mallinfo2() -> bool:
    """glibc 2.33 or later (``mallinfo2``), where the tests can read the allocator's state."""
    try:
        return bool(os.confstr("CS_GNU_LIBC_VERSION")) and hasattr(ctypes.CDLL(None), "mallinfo2")
    except (ValueError, OSError, AttributeError):
        return False


pytestmark = pytest.mark.skipif(sys.platform != "linux" or not _glibc_with_mallinfo2(), reason="glibc >= 2.33 only")


def _heap_after_freeing_a_large_array(set_up: bool, env: dict[str, str] | None = None) -> tuple[bool, int, int]:
    """In a fresh interpreter, with or without :func:`keep_freed_memory`: whether it set the
    thresholds, bytes glibc held in separate ``mmap`` blocks while a 16 MB array lived, and free bytes
    it kept in its heap after the array was freed (``mallinfo2``: hblkhd, fordblks)."""
    script = textwrap.dedent(f"""
        import ctypes
        import numpy as np
        from gctr_cli.allocator import keep_freed_memory

        class MallInfo2(ctypes.Structure):
            _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                                             "usmblks", "fsmblks", "uordblks", "fordblks",
                                                             "keepcost")]

        mallinfo2 = ctypes.CDLL(None).mallinfo2
        mallinfo2.restype = MallInfo2
        applied = keep_freed_memory() if {set_up!r} else False
        a = np.ones(2 << 20)  # float64: 16 MB
        mapped = mallinfo2().hblkhd
        del a
        print(applied, mapped, mallinfo2().fordblks)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                         env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1",
                              **(env or {})})
    assert out.returncode == 0, out.stderr[-2000:]
    applied, mapped, kept = out.stdout.split()[-3:]
    return applied == "True", int(mapped), int(kept)


SIXTEEN_MB = 16 << 20


def test_a_freed_array_stays_in_the_heap_for_the_next_one():
    # default glibc: the array gets its own mmap, handed back to the kernel when freed, so the next
    # array of that size is faulted in again page by page
    applied, mapped, kept = _heap_after_freeing_a_large_array(False)
    assert not applied and mapped >= SIXTEEN_MB and kept < SIXTEEN_MB
    # set up: the array lives in the heap, and its memory stays there when it is freed
    applied, mapped, kept = _heap_after_freeing_a_large_array(True)
    assert applied and mapped < SIXTEEN_MB and kept >= SIXTEEN_MB


def test_the_users_own_malloc_settings_win():
    # a trim threshold the user set is left alone, and so is everything else (the array is mapped)
    applied, mapped, _ = _heap_after_freeing_a_large_array(True, {"MALLOC_TRIM_THRESHOLD_": "65536"})
    assert not applied and mapped >= SIXTEEN_MB


def test_the_thresholds_are_set_once_per_process(monkeypatch):
    calls = []
    monkeypatch.setattr(allocator, "_applied", None)
    monkeypatch.setattr(allocator, "_set_thresholds", lambda: calls.append(1) or True)
    assert allocator.keep_freed_memory() is True and allocator.keep_freed_memory() is True
    assert calls == [1] and allocator.is_set_up()


def test_batch_workers_set_up_the_allocator(four_pairs, fast_config, tmp_path, monkeypatch):
    for name in allocator.USER_SETTINGS:  # a dask nanny started by an earlier test may have set them here
        monkeypatch.delenv(name, raising=False)
    run_batch(four_pairs.specs()[:2], fast_config, tmp_path / "out", workers=1,
              register_fn=fake_engine.register_reporting_allocator)
    rows = (tmp_path / "out" / "transforms.csv").read_text().splitlines()
    assert len(rows) == 3 and all("allocator set up: True" in row for row in rows[1:]), rows
