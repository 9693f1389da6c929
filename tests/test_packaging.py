"""Project hygiene: one version source, the licence and the typing marker as installed."""

from __future__ import annotations

import re
import subprocess
import sys
from importlib import metadata, resources
from pathlib import Path

from conftest import REPO

import gctr_cli

DIST = "gctr-cli"  # the distribution name (pyproject [project] name); the import package is gctr_cli


def test_gctr_version_is_the_package_metadata():
    exe = Path(sys.executable).with_name("gctr")  # the console script of this environment
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "gctr_cli"]
    out = subprocess.run([*cmd, "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"gctr, version {metadata.version(DIST)}"
    assert gctr_cli.__version__ == metadata.version(DIST)


def test_the_version_is_written_in_one_place():
    pyproject = (REPO / "pyproject.toml").read_text()
    project = pyproject.split("[project]", 1)[1].split("\n[", 1)[0]
    assert not re.search(r"^version\s*=", project, re.M), "the version belongs in gctr_cli/__init__.py only"
    assert re.search(r'^dynamic\s*=\s*\[[^]]*"version"', project, re.M)
    assert 'version = { attr = "gctr_cli.__version__" }' in pyproject


def test_licence_is_mit_in_the_metadata_and_the_file():
    assert metadata.metadata(DIST).get("License-Expression") == "MIT"
    text = (REPO / "LICENSE").read_text()
    assert text.startswith("MIT License") and "Copyright (c) 2026 the gctr authors" in text


def test_py_typed_ships_with_the_package():
    assert resources.files("gctr_cli").joinpath("py.typed").is_file()
