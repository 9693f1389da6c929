"""gctr: cross-source point cloud registration (similarity transform) with GCTR."""

# The one place the version is written: pyproject.toml reads it (dynamic version), and
# ``gctr --version``, report.html and the installed package metadata all come from it.
__version__ = "0.1.0"
