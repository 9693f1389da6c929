"""Connecting to a dask cluster, or starting gctr's own local one (``gctr batch --executor dask``), for
:mod:`gctr_cli.dask_executor`; and the preload of that local cluster's workers (:func:`dask_setup`).

A terminal's Ctrl-C reaches the whole process group; stopping the workers is the batch's business, so
each worker of the local cluster ignores SIGINT once its preload has run (a traceback per worker
otherwise; one still importing may print one). That is set in the worker, in its main thread, because
the batch cannot hand the workers an ignored SIGINT without ignoring a Ctrl-C itself while the cluster
starts; a stop signal meanwhile is deferred until the cluster is up (:func:`connect`).
"""

from __future__ import annotations

import logging
import signal
import threading
import warnings
from typing import Any

from gctr_cli.allocator import malloc_environment
from gctr_cli.errors import BatchError
from gctr_cli.fsutil import THREAD_ENV_VARS, start_resource_tracker, stop_signals_deferred
from gctr_cli.outcome import exc_message

__all__ = ["CONNECT_TIMEOUT_S", "connect", "dask_setup"]

logger = logging.getLogger("gctr_cli.dask_executor")

CONNECT_TIMEOUT_S = 30.0  #: seconds to wait for the scheduler when connecting
#: what dask's nanny sets ``MALLOC_TRIM_THRESHOLD_`` to unless its config says otherwise
DASK_DEFAULT_TRIM_THRESHOLD = 65536


def _pre_spawn_environment(configured: dict[str, Any]) -> dict[str, Any]:
    """The nanny's ``pre-spawn-environ`` for gctr's own LocalCluster: the configured one, with gctr's
    malloc settings (:mod:`gctr_cli.allocator`) for dask's default ``MALLOC_TRIM_THRESHOLD_`` (a pair
    takes 1.5x as long with it); other malloc settings are kept, and so is a variable already in the
    environment (the nanny's rule). Set before a worker process starts, the only time glibc reads them."""
    trim = configured.get("MALLOC_TRIM_THRESHOLD_")
    if "MALLOC_MMAP_THRESHOLD_" in configured or trim not in (None, DASK_DEFAULT_TRIM_THRESHOLD,
                                                              str(DASK_DEFAULT_TRIM_THRESHOLD)):
        return dict(configured)
    return {**configured, **malloc_environment()}


def _start_local_cluster(n_workers: int) -> Any:
    import dask
    from distributed import LocalCluster

    env = {var: "1" for var in THREAD_ENV_VARS}
    pre_spawn = _pre_spawn_environment(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    # allowed-failures 0: a pair that kills its worker fails at once (as with the local pool);
    # worker-saturation 1.0: a one-thread worker is sent one task at a time (a task starts when assigned)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                          "distributed.scheduler.worker-saturation": 1.0,
                          "distributed.nanny.pre-spawn-environ": pre_spawn}), warnings.catch_warnings():
        # the scheduler's HTTP routes move off a busy port 8787 with a UserWarning: not our concern
        warnings.filterwarnings("ignore", message=r"Port \d+ is already in use", category=UserWarning)
        return LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.CRITICAL,  # worker deaths are reported in the pairs' rows
            env=env,
            preload=[__name__],  # the workers ignore Ctrl-C: the batch stops them
        )



def connect(scheduler: str | None, n_workers: int) -> tuple[Any, Any]:
    """(client, cluster or None)."""
    from distributed import Client

    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except Exception as exc:  # noqa: BLE001 - OSError, TimeoutError, ValueError (bad address)
            raise BatchError(f"cannot connect to the dask scheduler at {scheduler}: {exc_message(exc)}") from None
        logger.info("connected to the dask scheduler at %s", scheduler)
        return client, None
    cluster: Any = None
    local_client: Any = None
    start_resource_tracker()
    try:
        # a Ctrl-C, SIGTERM or SIGHUP meanwhile is acted on when the cluster and its client are up, which
        # are closed then (stopped half-started, they printed tracebacks from their exit handlers)
        failure = None
        with stop_signals_deferred() as caught:
            try:
                cluster = _start_local_cluster(n_workers)
                if not caught:
                    local_client = Client(cluster, set_as_default=False)
            except Exception as exc:  # noqa: BLE001
                failure = exc
        if caught:  # first: the signal may be what failed the start (it reaches the workers too)
            signal.raise_signal(caught[0])  # the handler of before: KeyboardInterrupt, or gctr's for SIGTERM
        if failure is not None:
            raise BatchError(f"cannot start a dask LocalCluster: {exc_message(failure)}") from None
    except BaseException:
        if local_client is not None:
            local_client.close()
        if cluster is not None:
            cluster.close()
        raise
    logger.info("started a dask LocalCluster with %d worker processes at %s", n_workers, cluster.scheduler_address)
    return local_client, cluster


def dask_setup(worker: Any) -> None:  # noqa: ARG001 - the preload interface
    """Ignore SIGINT in this worker process (when called in its main thread, as the worker runs there)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
