"""glibc's malloc keeps freed blocks for reuse in the processes gctr sets up (gctr_cli.allocator)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO

from data_scripts import fake_engine
from gctr_cli.batch import run_batch

pytestmark = pytest.mark.skipif(sys.platform != "linux" or not os.confstr("CS_GNU_LIBC_VERSION"),
                                reason="glibc only")


def _heap_after_freeing_a_large_array(set_up: bool) -> tuple[int, int]:
    """In a fresh interpreter, with or without :func:`keep_freed_memory`: bytes glibc held in
    separate ``mmap`` blocks while a 16 MB array lived, and free bytes it kept in its heap after the
    array was freed (``mallinfo2``: hblkhd, fordblks)."""
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
        if {set_up!r}:
            assert keep_freed_memory() is True
        a = np.ones(2 << 20)  # float64: 16 MB
        mapped = mallinfo2().hblkhd
        del a
        print(mapped, mallinfo2().fordblks)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                         env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-2000:]
    mapped, kept = out.stdout.split()[-2:]
    return int(mapped), int(kept)


def test_a_freed_array_stays_in_the_heap_for_the_next_one():
    sixteen_mb = 16 << 20
    # default glibc: the array gets its own mmap, handed back to the kernel when freed, so the next
    # array of that size is faulted in again page by page
    mapped, kept = _heap_after_freeing_a_large_array(False)
    assert mapped >= sixteen_mb and kept < sixteen_mb
    # set up: the array lives in the heap, and its memory stays there when it is freed
    mapped, kept = _heap_after_freeing_a_large_array(True)
    assert mapped < sixteen_mb and kept >= sixteen_mb


def test_keep_freed_memory_is_idempotent():
    from gctr_cli.allocator import keep_freed_memory

    assert keep_freed_memory() is True
    assert keep_freed_memory() is True


def test_batch_workers_set_up_the_allocator(four_pairs, fast_config, tmp_path):
    run_batch(four_pairs.specs()[:2], fast_config, tmp_path / "out", workers=1,
              register_fn=fake_engine.register_reporting_allocator)
    rows = (tmp_path / "out" / "transforms.csv").read_text().splitlines()
    assert len(rows) == 3 and all("allocator set up: True" in row for row in rows[1:]), rows
