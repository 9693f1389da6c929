"""Registration methods selectable with the config key ``method``.

Every method is a function ``fn(source, target, section, seed=...) -> RegistrationResult`` where
``section`` is the part of the config the method reads (:func:`method_config`). The batch runner
only calls :func:`get_register_fn`; it knows nothing about the methods' internals.

- ``gctr`` — the GCTR engine (:func:`gctr_cli.engine.register`), section ``engine``;
- ``icp``, ``fpfh_ransac``, ``fgr``, ``cpd`` — comparison methods (:mod:`gctr_cli.baselines`), section
  ``baselines``.
"""

from __future__ import annotations

from typing import Any, Callable

from gctr_cli.config import Config

RegisterFn = Callable[..., Any]

#: method name -> (module, function); imported on first use (workers load only what they run)
_METHODS = {
    "gctr": ("gctr_cli.engine", "register"),
    "icp": ("gctr_cli.baselines.icp", "register_icp"),
    "fpfh_ransac": ("gctr_cli.baselines.features", "register_fpfh_ransac"),
    "fgr": ("gctr_cli.baselines.features", "register_fgr"),
    "cpd": ("gctr_cli.baselines.cpd", "register_cpd"),
}

METHODS = tuple(_METHODS)
BASELINES = tuple(m for m in METHODS if m != "gctr")


def get_register_fn(method: str) -> RegisterFn:
    """The register function of a method name (imports are deferred: workers load what they use)."""
    try:
        module, name = _METHODS[method]
    except KeyError:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}") from None
    import importlib

    return getattr(importlib.import_module(module), name)


def method_config(config: Config) -> Any:
    """The config section a method's register function receives."""
    if config.method == "gctr":
        return config.engine
    return config.baselines
