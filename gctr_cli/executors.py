"""Choosing where the pairs of a batch run: the executors and what they share.

An executor is a generator function that takes the batch's ``(spec, seed)`` tasks and yields one
:class:`~gctr_cli.outcome.PairOutcome` per task, in completion order, turning any fault of its
workers into a failed outcome and cleaning up in ``finally``:

* ``"local"`` (default): the crash-proof process pool of :mod:`gctr_cli.pool`;
* ``"dask"``: a dask.distributed cluster (:mod:`gctr_cli.dask_executor`, optional extra).

:mod:`gctr_cli.batch` consumes either with the same code, so the output files, the commit order,
``--resume`` and the lock do not depend on the executor. The executor modules are imported only when
chosen (the dask one imports distributed, which takes a second).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

from gctr_cli.config import Config
from gctr_cli.errors import BatchError
from gctr_cli.outcome import PairOutcome
from gctr_cli.pair import RegisterFn, resolve_ref

__all__ = ["EXECUTORS", "check_executor", "check_scheduler_address", "outcomes", "register_ref"]

#: executors a batch can run its pairs on
EXECUTORS = ("local", "dask")


def check_executor(executor: str, scheduler: str | None) -> None:
    """Raise :class:`BatchError` for an unknown executor, a scheduler without dask, or dask missing."""
    if executor not in EXECUTORS:
        raise BatchError(f"unknown executor {executor!r} (choose one of: {', '.join(EXECUTORS)})")
    if scheduler is not None and executor != "dask":
        raise BatchError("a scheduler address needs the dask executor (--executor dask)")
    if executor == "dask":
        from gctr_cli.dask_executor import check_available

        check_available()
        if scheduler is not None:
            check_scheduler_address(scheduler)


def check_scheduler_address(scheduler: str) -> None:
    """Raise :class:`BatchError` for an address a client cannot even try (``tcp://HOST`` without its
    port): distributed would raise only after a client half-built, whose clean-up then hangs a minute."""
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(scheduler)
        if scheme in ("tcp", "tls", "ws", "wss"):
            parse_host_port(location)
    except ValueError as exc:
        raise BatchError(f"cannot connect to the dask scheduler at {scheduler}: {exc} "
                         "(expected tcp://HOST:PORT, e.g. tcp://node-a:8786)") from None


def register_ref(register_fn: RegisterFn | str | None) -> str | None:
    """A ``module:qualname`` reference to ``register_fn`` that a fresh worker process can import."""
    if register_fn is None or isinstance(register_fn, str):
        if isinstance(register_fn, str):
            resolve_ref(register_fn)  # fail early, in the parent
        return register_fn
    module = getattr(register_fn, "__module__", None)
    qualname = getattr(register_fn, "__qualname__", None)
    if not module or not qualname or "<" in qualname:
        raise BatchError(f"register_fn {register_fn!r} must be a module-level function (workers import it)")
    ref = f"{module}:{qualname}"
    try:
        resolved = resolve_ref(ref)
    except Exception as exc:  # noqa: BLE001
        raise BatchError(f"register_fn {ref} cannot be imported: {exc}") from None
    if resolved is not register_fn:
        raise BatchError(f"register_fn {ref} is not importable under that name")
    return ref


def outcomes(executor: str, tasks: Sequence[tuple[Any, int]], config: Config, n_workers: int,
             ref: str | None, *, scheduler: str | None, snapshots: bool) -> Iterator[PairOutcome]:
    """The outcomes of ``tasks`` from the chosen executor (see the module docstring)."""
    time_limit_s = config.batch.time_limit_s
    if executor == "dask":
        from gctr_cli.dask_executor import dask_outcomes

        return dask_outcomes(tasks, config, n_workers, ref, time_limit_s, scheduler=scheduler, snapshots=snapshots)
    from gctr_cli.pool import pool_outcomes

    return pool_outcomes(tasks, config, n_workers, ref, time_limit_s, snapshots=snapshots)
