"""gctr: cross-source point cloud registration (similarity transform) with GCTR."""

__version__ = "0.1.0"
