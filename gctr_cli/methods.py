"""Registration methods selectable with the config key ``method``.

Every method is a function ``fn(source, target, section, seed=...) -> RegistrationResult`` where
``section`` is the part of the config the method reads (:func:`method_config`). The batch runner
only calls :func:`get_register_fn`; it knows nothing about the methods' internals.
"""

from __future__ import annotations

from typing import Any, Callable

from gctr_cli.config import Config

RegisterFn = Callable[..., Any]


def get_register_fn(method: str) -> RegisterFn:
    """The register function of a method name (imports are deferred: workers load what they use)."""
    if method == "gctr":
        from gctr_cli.engine import register

        return register
    raise ValueError(f"unknown method {method!r}")


def method_config(config: Config) -> Any:
    """The config section a method's register function receives."""
    if config.method == "gctr":
        return config.engine
    return getattr(config, "baselines")
