"""The registry of registration methods: the one place that lists them (config key ``method``).

Every method is a module-level function with the call signature of :class:`RegisterFn`::

    register(source: (N, 3) array, target: (M, 3) array, section, seed: int = 0) -> RegistrationResult

where ``section`` is the part of the config the method reads (:func:`method_config`): ``engine`` for
``gctr``, ``baselines`` for the comparison methods. The batch runner only calls
:func:`get_register_fn`; it knows nothing about the methods' internals.

Everything else derives from :data:`REGISTRY`: the accepted values of ``method`` in the config
(:data:`METHODS`), the comparison methods (:data:`BASELINES`), the methods ``make bench`` runs. The
functions are imported on first use, so a worker loads only the method it runs (and this module
imports nothing but the standard library: :mod:`gctr_cli.config` builds its ``method`` type from it).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # annotations only: importing the registry must stay cheap
    import numpy as np

__all__ = ["BASELINES", "METHODS", "REGISTRY", "Method", "RegisterFn", "get_register_fn", "is_available",
           "method_config"]


class RegisterFn(Protocol):
    """What every method's register function looks like (GCTR engine and comparison methods).

    ``source`` and ``target`` are ``(N, 3)`` / ``(M, 3)`` float arrays; ``section`` is the config
    section of :func:`method_config` (an ``EngineConfig`` or a ``BaselineConfig``; ``None`` = its
    defaults). Returns a :class:`gctr_cli.engine.RegistrationResult` whose ``transform`` maps the
    source onto the target in their original coordinates; a problem of the input gives
    ``status='failed'`` with a message, not an exception.
    """

    def __call__(self, source: np.ndarray, target: np.ndarray, section: Any = None, seed: int = 0) -> Any: ...


@dataclass(frozen=True)
class Method:
    """One registry entry: where its register function lives and which config section it reads."""

    module: str
    function: str
    section: str  # attribute of Config handed to the function: "engine" or "baselines"
    summary: str
    requires: str | None = None  # an optional package (import name) the method needs, not installed with gctr


#: method name -> entry; order = the order of ``gctr config show``, the benchmark tables and the plots
REGISTRY: dict[str, Method] = {
    "gctr": Method("gctr_cli.engine", "register", "engine", "the GCTR engine"),
    "icp": Method("gctr_cli.baselines.icp", "register_icp", "baselines",
                  "bounding-box normalisation + scaled point-to-point ICP (Open3D)"),
    "fpfh_ransac": Method("gctr_cli.baselines.features", "register_fpfh_ransac", "baselines",
                          "FPFH + RANSAC (Open3D) + scaled ICP"),
    "fgr": Method("gctr_cli.baselines.features", "register_fgr", "baselines",
                  "FPFH + Fast Global Registration (Open3D) + scaled ICP"),
    "cpd": Method("gctr_cli.baselines.cpd", "register_cpd", "baselines", "rigid Coherent Point Drift with scale"),
    "kiss_matcher": Method("gctr_cli.baselines.kiss", "register_kiss_matcher", "baselines",
                           "KISS-Matcher (Faster-PFH, ROBIN, GNC; optional package kiss-matcher) + scaled ICP",
                           requires="kiss_matcher"),
}

METHODS: tuple[str, ...] = tuple(REGISTRY)
BASELINES: tuple[str, ...] = tuple(m for m, entry in REGISTRY.items() if entry.section == "baselines")


def is_available(method: str) -> bool:
    """Whether the optional package a method needs (if any) can be imported, without importing it."""
    import importlib.util

    package = REGISTRY[method].requires
    return package is None or importlib.util.find_spec(package) is not None


def get_register_fn(method: str) -> RegisterFn:
    """The register function of a method name (imported now: workers load only what they use)."""
    try:
        entry = REGISTRY[method]
    except KeyError:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}") from None
    return getattr(importlib.import_module(entry.module), entry.function)


def method_config(config: Any) -> Any:
    """The config section a method's register function receives (``config`` is a :class:`~gctr_cli.config.Config`)."""
    return getattr(config, REGISTRY[config.method].section)
