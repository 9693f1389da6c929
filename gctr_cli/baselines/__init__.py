"""Comparison methods for the benchmark and for users' own data (``method:`` in the config).

Each is a module-level function ``register_<name>(source, target, cfg: BaselineConfig, seed=0) ->
RegistrationResult`` with the signature of :class:`gctr_cli.methods.RegisterFn` and the same contract
as :func:`gctr_cli.engine.register`: the similarity mapping the source onto the target in the original
coordinates, ``status='failed'`` with a message (never an exception) for degenerate inputs. All of them
start from the same normalisation (centroids aligned, scale = ratio of bounding-box diagonals), see
:mod:`gctr_cli.baselines.common`.

- ``icp``: scaled point-to-point ICP (Open3D) — :mod:`gctr_cli.baselines.icp`
- ``fpfh_ransac``: FPFH + Open3D RANSAC + scaled ICP — :mod:`gctr_cli.baselines.features`
- ``fgr``: FPFH + Open3D Fast Global Registration + scaled ICP — :mod:`gctr_cli.baselines.features`
- ``cpd``: rigid Coherent Point Drift with scale (numpy) — :mod:`gctr_cli.baselines.cpd`
- ``kiss_matcher``: KISS-Matcher (optional package) + scaled ICP — :mod:`gctr_cli.baselines.kiss`

The list lives in :data:`gctr_cli.methods.REGISTRY`; the names below are resolved from it on first
access, so importing one method's module does not import the others.
"""

from __future__ import annotations

from typing import Any

from gctr_cli.methods import BASELINES, REGISTRY, get_register_fn

_FUNCTIONS = {REGISTRY[m].function: m for m in BASELINES}

__all__ = ["REGISTER_FUNCTIONS", *sorted(_FUNCTIONS)]


def __getattr__(name: str) -> Any:
    """``REGISTER_FUNCTIONS`` (method name -> function) and ``register_<name>``, imported when asked for."""
    if name == "REGISTER_FUNCTIONS":
        return {m: get_register_fn(m) for m in BASELINES}
    if name in _FUNCTIONS:
        return get_register_fn(_FUNCTIONS[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
