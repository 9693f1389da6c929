"""The documentation stays navigable: README short, every relative link in README.md and docs/ resolves."""

from __future__ import annotations

import re

import pytest
from conftest import REPO

DOCS = [REPO / "README.md", REPO / "CHANGELOG.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def test_readme_is_at_most_300_lines():
    assert len((REPO / "README.md").read_text(encoding="utf-8").splitlines()) <= 300


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(REPO).as_posix())
def test_relative_links_resolve(doc):
    text = doc.read_text(encoding="utf-8")
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # external links and anchors in the same page
        path = target.split("#", 1)[0]
        if not (doc.parent / path).exists():
            broken.append(target)
    assert not broken, f"{doc.name}: broken links {broken}"


def test_readme_python_example_prints_what_the_readme_shows():
    """The README's Python API example, run as shown, prints the output the README shows (but the
    run time): the numbers a reader compares against must be the engine's."""
    import subprocess
    import sys

    text = (REPO / "README.md").read_text(encoding="utf-8")
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    shown = re.search(r"Output \(run from the repository root\):\n\n```text\n(.*?)```", text, re.S).group(1)
    run = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120,
                         check=True)

    def without_runtime(out: str) -> list[str]:
        return [re.sub(r"runtime_s=[0-9.]+", "runtime_s=…", line) for line in out.strip().splitlines()]

    assert without_runtime(run.stdout) == without_runtime(shown)
