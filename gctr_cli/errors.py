"""Exceptions of the batch layer that stop a whole batch (the CLI turns them into exit code 2).

Problems of one pair never raise: they become that pair's failed row (:mod:`gctr_cli.outcome`).
"""

from __future__ import annotations

__all__ = ["BatchError", "ExecutorLost", "LockError"]


class BatchError(Exception):
    """The batch cannot start or cannot go on (output folder in use or inconsistent, bad arguments,
    executor unavailable); the pairs finished so far are saved."""


class LockError(BatchError):
    """Another gctr batch holds the lock of the output folder."""


class ExecutorLost(BatchError):
    """The executor went away mid-batch (e.g. the dask scheduler died): finished pairs are saved,
    ``--resume`` continues."""
