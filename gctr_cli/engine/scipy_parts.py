"""The two scipy objects the engine uses, imported without the rest of their packages.

``from scipy.spatial import cKDTree`` runs ``scipy/spatial/__init__.py``, which also loads Qhull,
the distance functions (and with them ``scipy.special``) and ``scipy.spatial.transform`` (and
``scipy.linalg``); ``from scipy.sparse.csgraph import dijkstra`` loads the graph Laplacian and with
it ``scipy.sparse.linalg``. The engine needs none of them; on one core they cost ``gctr register``
about 0.14 s of import time (0.62 -> 0.48 s in bench/PROCESS.md), a seventh of the whole command.

:func:`_submodule` loads just the compiled submodule: while it imports, a bare stand-in for the
package (its directory, no ``__init__``) sits in ``sys.modules``; afterwards the stand-in is removed
and the submodule stays registered under its real name. A later ``import scipy.spatial`` anywhere in
the process runs the real ``__init__``, which picks up the already loaded submodule, so
``scipy.spatial.cKDTree is cKDTree`` holds (a test checks it). If the package is already imported,
or the shortcut fails for any reason (a scipy that moved these modules), the normal import is used.
"""

from __future__ import annotations

import importlib
import sys
import types
from pathlib import Path
from typing import TYPE_CHECKING, Any


def _submodule(package: str, name: str, attribute: str) -> Any:
    """``package.name.attribute``, importing ``package.name`` without running ``package``'s ``__init__``."""
    if package not in sys.modules:
        parent_name, _, leaf = package.rpartition(".")
        try:
            parent = importlib.import_module(parent_name)
            stand_in = types.ModuleType(package)
            stand_in.__path__ = [str(Path(parent.__file__ or "").parent / leaf)]
            sys.modules[package] = stand_in
            try:
                return getattr(importlib.import_module(f"{package}.{name}"), attribute)
            finally:
                if sys.modules.get(package) is stand_in:
                    del sys.modules[package]
        except (ImportError, AttributeError):
            pass
    return getattr(importlib.import_module(package), attribute)


if TYPE_CHECKING:
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree
else:
    cKDTree = _submodule("scipy.spatial", "_ckdtree", "cKDTree")
    dijkstra = _submodule("scipy.sparse.csgraph", "_shortest_path", "dijkstra")

__all__ = ["cKDTree", "dijkstra"]
