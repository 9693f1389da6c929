"""Running one pair: load both clouds and the ground truth, register, measure the errors.

This is all ``gctr register`` loads (it imports nothing of the batch machinery), and what every
executor's worker runs per pair. It knows nothing about the algorithm: it calls a ``register(source,
target, section, seed=...)`` function (:mod:`gctr_cli.methods`, the GCTR engine by default) and turns
whatever happens into one :class:`~gctr_cli.outcome.PairOutcome`; it never raises for a problem of the
pair itself.

Also here, because every worker needs them before its first pair: the per-pair seed
(:func:`derive_seed`), resolving a register function by reference (:func:`resolve_register_fn`) and
capping Open3D to one thread (:func:`limit_native_threads`).
"""

from __future__ import annotations

import hashlib
import importlib
import logging
import math
import sys
import time
from typing import Any

import numpy as np

from gctr_cli.config import Config
from gctr_cli.methods import RegisterFn
from gctr_cli.outcome import SNAPSHOT_LOGGER, PairOutcome, exc_message, failed_outcome

logger = logging.getLogger(__name__)

__all__ = ["RegisterFn", "default_register", "derive_seed", "limit_native_threads", "resolve_ref",
           "resolve_register_fn", "run_pair"]

#: ``runtime_s`` of a pair whose engine never ran (an unreadable cloud or ground truth)
NOT_RUN = 0.0
#: the errors against ground truth leave out points farther than this many 90th-percentile distances
#: from the median (far stray points; wide enough to keep a LiDAR sweep's sparse far returns)
METRIC_SPREAD = 10.0


def derive_seed(base_seed: int, pair_id: str) -> int:
    """Seed of one pair: a stable hash (SHA-256) of the config seed and the pair id, in ``[0, 2**31)``.

    Independent of the process, the platform, ``PYTHONHASHSEED`` and the order in which pairs run.
    """
    digest = hashlib.sha256(f"{int(base_seed)}\x1f{pair_id}".encode()).digest()
    return int.from_bytes(digest[:8], "big") % (2**31)


def resolve_ref(ref: str) -> RegisterFn:
    """The object named by a ``module:qualname`` reference."""
    module, _, qualname = ref.partition(":")
    obj: Any = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def resolve_register_fn(register_ref: str | None, config: Config) -> RegisterFn:
    """``register_ref`` (``module:qualname``) or, when None, the register function of the config's method."""
    return resolve_ref(register_ref) if register_ref else default_register(config)


def limit_native_threads() -> None:
    """One thread for Open3D too (its RANSAC is not reproducible otherwise), if it is loaded."""
    o3d = sys.modules.get("open3d")
    if o3d is not None:
        try:
            o3d.utility.set_max_threads(1)
        except Exception:  # noqa: BLE001 - older Open3D without the call
            pass


def _confidence(result: Any) -> float:
    """The result's confidence, NaN when the method does not report one."""
    value = getattr(result, "confidence", None)
    try:
        return float("nan") if value is None else float(value)
    except (TypeError, ValueError):
        return float("nan")


def default_register(config: Config) -> RegisterFn:
    """The register function of ``config.method`` (the GCTR engine by default)."""
    from gctr_cli.methods import get_register_fn

    return get_register_fn(config.method)


def _name_files(message: str, spec: Any) -> str:
    """The engine names the clouds ``source``/``target`` (it sees arrays); a row names the files."""
    for role, path in (("source", spec.source), ("target", spec.target)):
        if message.startswith(f"{role}: "):
            return f"{role} {path}: {message[len(role) + 2:]}"
    return message


def run_pair(
    spec: Any,
    config: Config,
    register_fn: RegisterFn | None = None,
    *,
    seed: int | None = None,
    snapshot: bool = False,
) -> PairOutcome:
    """Register one pair and return its outcome; never raises for a problem of the pair itself.

    ``spec`` is a :class:`gctr_cli.manifest.PairSpec`. ``register_fn`` defaults to the GCTR engine's
    ``register``; ``seed`` defaults to :func:`derive_seed` of the config seed and the pair id.
    Loading errors give the loader's message (file and problem); ground-truth problems give
    ``ground truth <file>: <problem>``; any exception during registration gives ``Type: message``.
    The target diagonal for the relative translation error is the bounding-box diagonal of the loaded
    target cloud.

    ``snapshot=True`` also renders the pair's PNG snapshot (:mod:`gctr_cli.snapshots`; input only for
    a failed pair, nothing when neither cloud could be loaded) into ``outcome.snapshot_png``, after the
    clock of ``runtime_s`` stopped. A rendering problem is logged as a warning and never fails the pair.
    """
    clouds: dict[str, np.ndarray] = {}
    outcome = _run_pair(spec, config, register_fn, seed, clouds)
    if snapshot and outcome.failure == "input":
        _load_other_clouds(spec, clouds)
    if snapshot and clouds:
        try:
            from dataclasses import replace

            from gctr_cli.snapshots import snapshot_of_outcome

            png = snapshot_of_outcome(outcome, clouds.get("source"), clouds.get("target"))
            outcome = replace(outcome, snapshot_png=png)
        except Exception as exc:  # noqa: BLE001 - a snapshot must never fail the pair
            logging.getLogger(SNAPSHOT_LOGGER).warning("snapshot failed: %s", exc_message(exc))
    return outcome


def _load_other_clouds(spec: Any, clouds: dict[str, np.ndarray]) -> None:
    """For the snapshot of a pair whose loading failed: load the clouds that were not tried, silently
    (the pair's row already names its problem; no new warning must change its message)."""
    from gctr_cli.io import load_point_cloud

    io_logger = logging.getLogger("gctr_cli.io")
    level = io_logger.level
    io_logger.setLevel(logging.ERROR)
    try:
        for role, path in (("source", spec.source), ("target", spec.target)):
            if role not in clouds:
                try:
                    clouds[role] = load_point_cloud(path)
                except Exception:  # noqa: BLE001
                    pass
    finally:
        io_logger.setLevel(level)


def _run_pair(spec: Any, config: Config, register_fn: RegisterFn | None, seed: int | None,
              clouds: dict[str, np.ndarray]) -> PairOutcome:
    """:func:`run_pair` without the snapshot; the loaded clouds are left in ``clouds``."""
    from gctr_cli.geometry import extent, robust_core
    from gctr_cli.io import MatrixError, PointCloudError, load_point_cloud, read_matrix
    from gctr_cli.io.errors import clean
    from gctr_cli.metrics import (
        GT_ORTHOGONALITY_TOL,
        STRICT_ORTHOGONALITY_TOL,
        is_similarity,
        nearest_similarity,
        orthogonality_deviation,
        transform_errors,
    )

    if seed is None:
        seed = derive_seed(config.seed, spec.pair_id)

    # 1. point clouds
    for role, path in (("source", spec.source), ("target", spec.target)):
        t_read = time.perf_counter()
        try:
            clouds[role] = load_point_cloud(path)
            logger.info("pair %s: %s %s: %d points, read in %.2f s", spec.pair_id, role, clean(path),
                        len(clouds[role]), time.perf_counter() - t_read)
        except PointCloudError as exc:
            return failed_outcome(spec, seed, str(exc), "input", NOT_RUN)
        except Exception as exc:  # noqa: BLE001 - a loader bug must still name the file
            return failed_outcome(spec, seed, f"{path}: {exc_message(exc)}", "input", NOT_RUN)
    source, target = clouds["source"], clouds["target"]

    # 2. ground truth (checked before the expensive part)
    T_gt = None
    if spec.gt is not None:
        try:
            T_gt = read_matrix(spec.gt)
            ok, reason = is_similarity(T_gt, orthogonality_tol=GT_ORTHOGONALITY_TOL)
            if not ok:
                raise MatrixError(f"{spec.gt}: not a similarity transform: {reason}")
            deviation = orthogonality_deviation(T_gt)
            if deviation > STRICT_ORTHOGONALITY_TOL:  # rounded, or slightly stretched: measure against the nearest
                logger.warning("ground truth %s: not exactly a similarity (R·Rᵀ differs from the identity by up to "
                               "%.2g; rounded?): errors are measured against the nearest similarity", spec.gt,
                               deviation)
                T_gt = nearest_similarity(T_gt)
        except MatrixError as exc:
            return failed_outcome(spec, seed, f"ground truth {exc}", "ground_truth", NOT_RUN)
        except Exception as exc:  # noqa: BLE001
            return failed_outcome(spec, seed, f"ground truth {spec.gt}: {exc_message(exc)}", "ground_truth", NOT_RUN)

    # 3. registration
    from gctr_cli.methods import method_config

    fn = register_fn if register_fn is not None else default_register(config)
    t0 = time.perf_counter()

    def elapsed() -> float:
        """The engine's time so far (reading the files excluded), for methods that report none."""
        return time.perf_counter() - t0

    try:
        result = fn(source, target, method_config(config), seed=seed)
    except Exception as exc:  # every problem becomes a failed row
        logger.debug("pair %s: register raised", spec.pair_id, exc_info=True)
        return failed_outcome(spec, seed, exc_message(exc), "register", elapsed())

    try:
        runtime = float(getattr(result, "runtime_s", float("nan")))
        if not math.isfinite(runtime):
            runtime = elapsed()
        if logger.isEnabledFor(logging.INFO):  # -v
            stages = ", ".join(f"{k} {v:.2f} s" for k, v in (getattr(result, "timings", None) or {}).items())
            logger.info("pair %s: %s in %.2f s, confidence %.2f%s", spec.pair_id, result.status, runtime,
                        _confidence(result), f"; stages: {stages}" if stages else "")
        fitness = float(result.fitness)
        rmse = float(result.inlier_rmse)
        confidence = _confidence(result)
        if result.status != "ok":
            # the engine refused the input before any answer (planar, too few salient points): nothing measured
            measured = getattr(result, "refusal", "") != "invalid_input"
            return failed_outcome(
                spec, seed, _name_files(result.message or "registration failed", spec), "register", runtime,
                fitness=fitness if measured else None, inlier_rmse=rmse if measured else None,
                confidence=confidence if measured else None,
            )
        T = np.array(result.transform, dtype=np.float64)
        ok, reason = is_similarity(T)
        if not ok:
            return failed_outcome(
                spec, seed, f"engine returned an invalid transform: {reason}", "register", runtime,
                fitness=fitness, inlier_rmse=rmse, confidence=confidence,
            )
        errors = success = None
        if T_gt is not None:
            # without far stray points (a 0 0 0 beside UTM coordinates): one point must not make a
            # wrong matrix a success by inflating the diagonal, nor move where translation is measured
            core_t, core_s = robust_core(target, METRIC_SPREAD), robust_core(source, METRIC_SPREAD)
            diagonal = float(np.linalg.norm(extent(core_t)))
            errors = transform_errors(T, T_gt, diagonal, source_centre=core_s.mean(axis=0))
            s = config.success
            success = errors.success(s.rotation_deg, s.translation_rel, s.scale)
        return PairOutcome(
            pair_id=spec.pair_id,
            source=str(spec.source),
            target=str(spec.target),
            status="ok",
            message=str(result.message or ""),
            seed=seed,
            runtime_s=runtime,
            transform=T,
            scale=float(result.scale),
            fitness=fitness,
            inlier_rmse=rmse,
            confidence=confidence,
            errors=errors,
            success=success,
        )
    except Exception as exc:  # noqa: BLE001 - a malformed result object
        return failed_outcome(spec, seed, f"invalid registration result: {exc_message(exc)}", "register", elapsed())
