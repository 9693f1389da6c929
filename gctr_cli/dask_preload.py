"""Dask preload for the workers of gctr's own local cluster (``LocalCluster(preload=[__name__])``).

A terminal's Ctrl-C reaches the whole process group; stopping the workers is the batch's business, so
each worker ignores SIGINT from its start on (a traceback per worker otherwise). Set here, in the worker
process's main thread, because the parent cannot hand the workers an ignored SIGINT without ignoring a
Ctrl-C itself while the cluster starts.
"""

from __future__ import annotations

import signal
import threading
from typing import Any


def dask_setup(worker: Any) -> None:  # noqa: ARG001 - the preload interface
    """Ignore SIGINT in this worker process (when called in its main thread, as the worker runs there)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
