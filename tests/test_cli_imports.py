"""What the ``gctr register`` and ``gctr --help`` processes import (issue 10 item 3: process overhead).

Each check runs the real command in a fresh interpreter and lists ``sys.modules`` afterwards: ``gctr
register`` must not load the batch machinery, the report/plotting code, Open3D or the comparison
methods; ``gctr --help`` must not even load numpy or pydantic.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import REPO, write_cloud

#: never needed to register one pair with the GCTR engine (the default method)
NOT_FOR_REGISTER = ("open3d", "dask", "distributed", "matplotlib", "tqdm", "pandas", "yaml", "gctr_cli.batch",
                    "gctr_cli.report", "gctr_cli.summary", "gctr_cli.snapshots", "gctr_cli.pool",
                    "gctr_cli.dask_executor", "gctr_cli.baselines",
                    # scipy: only the k-d tree and Dijkstra, not the rest of their packages (scipy_parts)
                    "scipy.linalg", "scipy.special", "scipy.sparse.linalg", "scipy.spatial.transform",
                    "scipy.spatial._qhull", "scipy.spatial.distance",
                    # numpy: what scipy's `from numpy import *` would load and nothing uses (scipy_parts)
                    "numpy.f2py", "numpy.testing", "numpy.polynomial", "numpy.char",
                    "numpy.ctypeslib", "numpy.rec", "numpy.strings")
NOT_FOR_HELP = ("numpy", "scipy", "pydantic", "yaml", "gctr_cli.config", "gctr_cli.io", "gctr_cli.engine")


def _modules_after(argv: list[str], tmp_path) -> tuple[int, set[str]]:
    script = textwrap.dedent(f"""
        import json, sys
        from gctr_cli.cli import main
        sys.argv = ["gctr", *{argv!r}]
        try:
            main()
            code = 0
        except SystemExit as exc:
            code = exc.code or 0
        print("\\n@@" + json.dumps({{"code": code, "modules": sorted(sys.modules)}}))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300,
                         env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"})
    assert "@@" in out.stdout, out.stderr[-3000:]
    data = json.loads(out.stdout.rsplit("@@", 1)[1])
    return data["code"], set(data["modules"])


def _run_script(script: str) -> list[str]:
    """Run ``script`` in a fresh interpreter (the repository on the path, one BLAS thread); its
    output split into words. Fails the test if the script fails."""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                         env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout.split()


def _loaded(modules: set[str], names: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules if any(m == n or m.startswith(n + ".") for n in names))


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair")
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3000, 3)) * [1.0, 0.6, 0.3]
    write_cloud(folder / "a.ply", pts)
    write_cloud(folder / "b.ply", pts * 2.0 + [1.0, 0.0, 0.5])
    return folder


def test_register_imports_only_what_it_uses(pair, tmp_path):
    code, modules = _modules_after(
        ["register", str(pair / "a.ply"), str(pair / "b.ply"), "-o", str(tmp_path / "m.txt")], tmp_path)
    assert code in (0, 1)  # the registration's outcome does not matter here, the import set does
    assert "gctr_cli.engine" in modules and "gctr_cli.pair" in modules  # it did run the engine
    assert _loaded(modules, NOT_FOR_REGISTER) == []
    # the two packages' __init__ never ran; their compiled parts the engine uses did load
    assert {"scipy.spatial", "scipy.sparse.csgraph"} & modules == set()
    assert {"scipy.spatial._ckdtree", "scipy.sparse.csgraph._shortest_path"} <= modules


def test_scipy_parts_are_scipys_own_objects():
    """After the lean import, a full ``import scipy.spatial`` elsewhere in the process gets the same
    classes (no second copy of the extension), and they work."""
    script = textwrap.dedent("""
        from gctr_cli.engine.scipy_parts import cKDTree, dijkstra
        import numpy as np, scipy.spatial, scipy.sparse.csgraph
        assert scipy.spatial.cKDTree is cKDTree and scipy.sparse.csgraph.dijkstra is dijkstra
        assert scipy.spatial.ConvexHull is not None  # the real __init__ ran
        d, i = cKDTree(np.eye(3)).query([0.9, 0.1, 0.0])
        print(int(i), round(float(d), 6))
    """)
    assert _run_script(script) == ["0", "0.141421"]


def test_lean_scipy_sparse_leaves_numpy_whole():
    """The stand-ins for the unused numpy submodules during scipy.sparse's import leave no trace: each
    loads for real afterwards and works, scipy's compatibility namespace does not hold the stand-ins, and
    Dijkstra and coo_matrix work, also on a numpy.ma array."""
    script = textwrap.dedent("""
        import sys
        from gctr_cli.engine.scipy_parts import _UNUSED_NUMPY_SUBMODULES, coo_matrix, dijkstra
        assert set(_UNUSED_NUMPY_SUBMODULES) >= {"f2py", "testing", "polynomial", "char"}
        assert not [n for n in _UNUSED_NUMPY_SUBMODULES if "numpy." + n in sys.modules]
        import scipy._lib.array_api_compat.numpy as compat
        assert not [n for n in _UNUSED_NUMPY_SUBMODULES if hasattr(compat, n)]
        exec("from scipy._lib.array_api_compat.numpy import *", {})
        import numpy as np
        np.testing.assert_allclose([1.0], [1.0])
        import numpy.f2py
        assert callable(numpy.f2py.run_main) and "numpy.testing" in sys.modules
        assert np.polynomial.Polynomial([1.0, 2.0])(3.0) == 7.0
        assert np.char.upper("ab") == "AB" and np.strings.lower("AB") == "ab"
        assert np.rec.fromarrays([[1, 2]], names="a").a.tolist() == [1, 2]
        assert np.ctypeslib.as_array((np.ctypeslib.ctypes.c_double * 2)(1.0, 2.0)).tolist() == [1.0, 2.0]
        graph = coo_matrix(([1.0, 2.0], ([0, 1], [1, 2])), shape=(3, 3)).tocsr()
        print(dijkstra(graph, directed=False, indices=[0]).ravel().tolist())
        print(dijkstra(np.ma.masked_equal(graph.toarray(), 0.0), directed=False, indices=[0]).ravel().tolist())
    """)
    assert _run_script(script) == ["[0.0,", "1.0,", "3.0]"] * 2


def test_lean_scipy_sparse_after_numpy_testing():
    """With numpy.testing already loaded (a test runner, a notebook) the normal import runs and the
    objects are scipy's own."""
    script = textwrap.dedent("""
        import numpy.testing, scipy.sparse.csgraph
        from gctr_cli.engine.scipy_parts import coo_matrix, dijkstra
        import scipy.sparse
        assert coo_matrix is scipy.sparse.coo_matrix and dijkstra is scipy.sparse.csgraph.dijkstra
        print("ok")
    """)
    assert _run_script(script) == ["ok"]


def test_lean_scipy_sparse_not_with_other_threads():
    """With another thread running, the stand-ins are not used (that thread could pick one up): the
    normal import runs, numpy.testing loads with it and another thread's import sees the real one."""
    script = textwrap.dedent("""
        import sys, threading
        stop = threading.Event()
        worker = threading.Thread(target=stop.wait)
        worker.start()
        from gctr_cli.engine.scipy_parts import dijkstra
        stop.set(); worker.join()
        import scipy._lib.array_api_compat.numpy as compat
        from numpy.testing import assert_allclose
        print("numpy.testing" in sys.modules, compat.testing is sys.modules["numpy.testing"])
    """)
    assert _run_script(script) == ["True", "True"]


def test_help_is_light(tmp_path):
    code, modules = _modules_after(["--help"], tmp_path)
    assert code == 0
    assert _loaded(modules, NOT_FOR_HELP) == []
    code, modules = _modules_after(["register", "--help"], tmp_path)
    assert code == 0
    assert _loaded(modules, NOT_FOR_HELP) == []
