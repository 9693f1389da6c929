"""The three scipy objects the engine uses, imported without the rest of their packages.

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

:func:`_import_scipy_sparse` imports ``scipy.sparse`` (Dijkstra and the engine's ``coo_matrix`` need
it) without the numpy submodules nothing here uses (:data:`_UNUSED_NUMPY_SUBMODULES`). scipy.sparse
(scipy 1.17 here) pulls in its vendored ``array_api_compat.numpy``, which copies numpy's namespace with
``from numpy import *``; that loads every lazily imported numpy submodule: ``numpy.f2py`` (the Fortran
wrapper generator, with ``charset_normalizer``) and ``numpy.testing`` (with ``unittest``), 58 modules and
0.04-0.12 s of a 0.45-0.65 s import on one core of the Intel machine (median of 8 alternating runs about
0.08 s); and ``numpy.polynomial``, ``numpy.char``, ``numpy.ctypeslib``, ``numpy.rec`` and
``numpy.strings``, about 4.5 ms on one core of the AMD machine (``numpy.ma`` is not among them:
``np.unique`` and ``np.median`` load it on their first call anyway). While scipy.sparse imports, bare
stand-ins take their place; afterwards the stand-ins are removed from ``sys.modules``, from numpy's
namespace and from the compatibility module's (and its ``__all__``), so a later ``numpy.testing``,
``np.polynomial`` or ``import numpy.f2py`` anywhere in the process loads the real ones (a test checks
it). What remains different: scipy's private ``array_api_compat.numpy`` namespace lacks these
submodules (scipy 1.17 reads ``testing`` and ``f2py`` there only for CuPy and torch arrays, the others
nowhere). The shortcut is taken only in a process with a single thread (``gctr register``, the pool's
spawned workers): other threads would see the stand-ins while scipy.sparse imports.
"""

from __future__ import annotations

import importlib
import sys
import threading
import types
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

#: numpy submodules that ``from numpy import *`` loads and neither scipy.sparse nor the engine uses
_UNUSED_NUMPY_SUBMODULES = ("f2py", "testing", "polynomial", "char", "ctypeslib", "rec", "strings")


@contextmanager
def _standing_in(stand_ins: dict[str, types.ModuleType]) -> Iterator[None]:
    """Register ``stand_ins`` (module name -> bare module) in ``sys.modules`` for the ``with`` block;
    afterwards remove each one that is still there."""
    sys.modules.update(stand_ins)
    try:
        yield
    finally:
        for name, stand_in in stand_ins.items():
            if sys.modules.get(name) is stand_in:
                del sys.modules[name]


def _import_scipy_sparse() -> None:
    """Import ``scipy.sparse`` without loading :data:`_UNUSED_NUMPY_SUBMODULES` (see the module
    docstring); the normal import if scipy.sparse or one of them is already loaded, if another thread
    runs (it would see the stand-ins), or if anything goes wrong."""
    import numpy

    if ("scipy.sparse" in sys.modules or threading.active_count() > 1
            or any(f"numpy.{n}" in sys.modules for n in _UNUSED_NUMPY_SUBMODULES)):
        importlib.import_module("scipy.sparse")
        return
    stand_ins = {n: types.ModuleType(f"numpy.{n}") for n in _UNUSED_NUMPY_SUBMODULES}
    try:
        with _standing_in({f"numpy.{n}": m for n, m in stand_ins.items()}):
            for n, stand_in in stand_ins.items():
                setattr(numpy, n, stand_in)
            importlib.import_module("scipy.sparse")
    except Exception:  # noqa: BLE001 - a scipy that needs them at import: the normal import below
        pass
    finally:
        for n, stand_in in stand_ins.items():
            if numpy.__dict__.get(n) is stand_in:
                delattr(numpy, n)
        for name, module in list(sys.modules.items()):
            if not name.startswith("scipy."):  # by key: touching a lazily loaded module would load it
                continue
            namespace = vars(module) if hasattr(module, "__dict__") else {}
            for n, stand_in in stand_ins.items():
                if namespace.get(n) is stand_in:
                    del namespace[n]
                    exported = namespace.get("__all__")
                    if isinstance(exported, list) and n in exported:
                        exported.remove(n)
    importlib.import_module("scipy.sparse")  # a no-op when the import above succeeded


def _submodule(package: str, name: str, attribute: str) -> Any:
    """``package.name.attribute``, importing ``package.name`` without running ``package``'s ``__init__``."""
    if package not in sys.modules:
        parent_name, _, leaf = package.rpartition(".")
        try:
            parent = importlib.import_module(parent_name)
            stand_in = types.ModuleType(package)
            stand_in.__path__ = [str(Path(parent.__file__ or "").parent / leaf)]
            with _standing_in({package: stand_in}):
                return getattr(importlib.import_module(f"{package}.{name}"), attribute)
        except (ImportError, AttributeError):
            pass
    return getattr(importlib.import_module(package), attribute)


if TYPE_CHECKING:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree
else:
    _import_scipy_sparse()
    from scipy.sparse import coo_matrix

    cKDTree = _submodule("scipy.spatial", "_ckdtree", "cKDTree")
    dijkstra = _submodule("scipy.sparse.csgraph", "_shortest_path", "dijkstra")

__all__ = ["cKDTree", "coo_matrix", "dijkstra"]
