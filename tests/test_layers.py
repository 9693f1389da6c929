"""The batch layer's structure: import contracts (import-linter), module sizes, and what ``gctr register``
loads.

The contracts live in pyproject.toml (``[tool.importlinter]``): the layers cli -> batch -> report ->
summary -> executors/lock -> pool/dask_executor/outdir -> pair -> outcome/errors, the engine and readers
importing none of them, and no cycle between sibling modules. grimp, which import-linter builds on,
counts imports inside functions too, so a lazy import back up the layers breaks a contract.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from conftest import REPO

#: the modules of the batch layer (issue 12) and the report built on its summary
BATCH_MODULES = ("batch", "executors", "pool", "dask_executor", "dask_cluster", "pair", "outcome", "outdir", "lock",
                 "summary", "errors", "report")
MAX_LINES = 600


def test_import_contracts_are_kept():
    pytest.importorskip("importlinter")
    # in a subprocess: lint-imports configures logging (dictConfig), which would disable gctr's loggers here
    proc = subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
                           "sys.argv = ['lint-imports', '--no-cache']; lint_imports_command()"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "Contracts: 3 kept, 0 broken." in proc.stdout


def test_a_function_level_import_up_the_layers_breaks_the_contract(monkeypatch):
    """The check is not fooled by imports hidden inside functions (how the old cycle hid)."""
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("gctr_cli")
    # report.py imports summarize inside a function: grimp sees it
    assert "gctr_cli.summary" in graph.find_modules_directly_imported_by("gctr_cli.report")
    layers = ["gctr_cli.batch", "gctr_cli.report", "gctr_cli.summary"]
    assert not graph.find_illegal_dependencies_for_layers(layers=layers)
    graph.add_import(importer="gctr_cli.summary", imported="gctr_cli.batch", line_number=1, line_contents="")
    assert graph.find_illegal_dependencies_for_layers(layers=layers)


@pytest.mark.parametrize("name", BATCH_MODULES)
def test_no_batch_module_is_over_600_lines(name):
    n = len((REPO / "gctr_cli" / f"{name}.py").read_text().splitlines())
    assert n <= MAX_LINES, f"gctr_cli/{name}.py has {n} lines: split it by job"


DRIVER = """
import atexit, json, sys
from data_scripts import fake_engine
import gctr_cli.methods
gctr_cli.methods.get_register_fn = lambda method: fake_engine.register
atexit.register(lambda: print("MODULES " + json.dumps(
    sorted(m for m in sys.modules if m.startswith(("gctr_cli", "distributed", "dask"))))))
from gctr_cli import cli
sys.argv = ["gctr"] + sys.argv[1:]
cli.main()
"""


def test_gctr_register_loads_only_the_single_pair_path(four_pairs, subprocess_env):
    row = four_pairs.rows[0]
    src, tgt = four_pairs.root / row["source"], four_pairs.root / row["target"]
    proc = subprocess.run([sys.executable, "-c", DRIVER, "register", str(src), str(tgt), "--gt",
                           str(four_pairs.root / row["gt"])], env=subprocess_env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "status: ok" in proc.stdout and "success: true" in proc.stdout
    assert "confidence: 0." in proc.stdout  # the fake engine's confidence in [0.5, 1)
    line = next(x for x in proc.stdout.splitlines() if x.startswith("MODULES "))
    loaded = set(json.loads(line[len("MODULES "):]))
    assert {"gctr_cli.pair", "gctr_cli.outcome", "gctr_cli.io", "gctr_cli.cli"} <= loaded
    batch_machinery = {f"gctr_cli.{m}" for m in BATCH_MODULES if m not in ("pair", "outcome")}
    assert not loaded & batch_machinery, sorted(loaded & batch_machinery)
    assert not any(m.startswith(("distributed", "dask")) for m in loaded)
