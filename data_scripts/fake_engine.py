"""Deterministic stand-ins for ``gctr_cli.engine.register``: the batch tests' engine and the batch-layer
benchmark's (``data_scripts/bench_batch.py``, :func:`busy_register`).

They are module-level functions so that spawned worker processes can import them by name.
The test clouds are written so that ``target[i] = T_gt @ source[i]``: Umeyama on index
correspondences recovers ``T_gt`` exactly, and a tiny seeded offset makes the result depend on the
seed (so identical outputs across worker counts prove the seeds are passed correctly).

Special behaviours are chosen by the number of source points (the engine only sees arrays); see
the ``*_N`` constants below.
"""

from __future__ import annotations

import os
import signal
import tempfile
import time
from dataclasses import replace

import numpy as np

from gctr_cli.engine.result import RegistrationResult

KILL_N = 61  #: the worker SIGKILLs itself (a native crash / OOM kill)
SLEEP_N = 67  #: sleeps far beyond any time limit
RAISE_N = 71  #: raises ValueError (what the engine does for degenerate input)
FAIL_N = 73  #: returns a 'failed' result
EXIT_N = 79  #: the worker calls os._exit(3)

SEED_OFFSET = 1e-7  #: relative size of the seeded translation offset


def fake_confidence(seed: int) -> float:
    """Deterministic confidence of an ok pair: in [0.5, 1), a function of its seed (so of the pair id)."""
    return 0.5 + 0.5 * (seed % 997) / 997


def umeyama(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991) as a 4x4 matrix."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var)
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = mu_d - s * R @ mu_s
    return T


def register(source, target, config=None, seed=0):
    t0 = time.perf_counter()
    n = len(source)
    if n == KILL_N:
        os.kill(os.getpid(), signal.SIGKILL)
    if n == SLEEP_N:  # as a LAZ read does, it leaves a temporary file that only its worker's end can remove
        tempfile.mkstemp(prefix="fake-engine-")
        time.sleep(120)
    if n == RAISE_N:
        raise ValueError("degenerate input: the source cloud is planar")
    if n == EXIT_N:
        os._exit(3)
    m = min(len(source), len(target))
    T = umeyama(np.asarray(source[:m]), np.asarray(target[:m]))
    diag = float(np.linalg.norm(target.max(0) - target.min(0)))
    rng = np.random.default_rng(seed)
    T[:3, 3] += rng.uniform(-1.0, 1.0, 3) * SEED_OFFSET * diag
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    status, message = ("failed", "too few inliers (3 < 6)") if n == FAIL_N else ("ok", "")
    return RegistrationResult(
        transform=T,
        scale=s,
        rotation=T[:3, :3] / s,
        translation=T[:3, 3].copy(),
        fitness=0.875 if status == "ok" else 0.01,
        confidence=fake_confidence(seed) if status == "ok" else 0.05,
        inlier_rmse=0.001 * diag,
        n_inliers=m,
        iterations=1,
        status=status,
        message=message,
        runtime_s=time.perf_counter() - t0,
        seed=seed,
        refusal="" if status == "ok" else "weak_evidence",
    )


def busy_register(source, target, config=None, seed=0):
    """Like :func:`register`, plus ``GCTR_BENCH_WORK_MS`` milliseconds of CPU (a busy loop): the scale
    benchmark's engine, whose cost is the batch layer's own plus a known amount of work."""
    t0 = time.perf_counter()
    end = t0 + float(os.environ.get("GCTR_BENCH_WORK_MS", "0")) / 1000.0
    x = 0
    while time.perf_counter() < end:
        x += 1
    return replace(register(source, target, config, seed), runtime_s=time.perf_counter() - t0)


def slow_register(source, target, config=None, seed=0):
    """Like :func:`register`, 0.4 s per pair (to kill a batch mid-run)."""
    time.sleep(0.4)
    return register(source, target, config, seed)


def register_without_confidence(source, target, config=None, seed=0):
    """Like :func:`register`, for a method that computes no confidence (NaN)."""
    return replace(register(source, target, config, seed), confidence=float("nan"))


def register_reporting_allocator(source, target, config=None, seed=0):
    """Like :func:`register`, with the message telling whether this process set up glibc's malloc
    (:func:`gctr_cli.allocator.keep_freed_memory`; the local pool's workers must) and the malloc
    variables it started with (gctr's own dask LocalCluster must pass gctr's)."""
    from gctr_cli.allocator import USER_SETTINGS, is_set_up

    started_with = " ".join(f"{name}={os.environ.get(name)}" for name in USER_SETTINGS)
    return replace(register(source, target, config, seed), message=f"allocator set up: {is_set_up()}; {started_with}")
