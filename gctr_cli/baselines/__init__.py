"""Comparison methods for the benchmark and for users' own data (``method:`` in the config).

Each is a module-level function ``register_<name>(source, target, cfg: BaselineConfig, seed=0) ->
RegistrationResult`` with the same contract as :func:`gctr_cli.engine.register`: the similarity
mapping the source onto the target in the original coordinates, ``status='failed'`` with a message
(never an exception) for degenerate inputs. All of them start from the same normalisation
(centroids aligned, scale = ratio of bounding-box diagonals), see :mod:`gctr_cli.baselines.common`.

- ``icp``: scaled point-to-point ICP (Open3D) — :mod:`gctr_cli.baselines.icp`
- ``fpfh_ransac``: FPFH + Open3D RANSAC + scaled ICP — :mod:`gctr_cli.baselines.features`
- ``fgr``: FPFH + Open3D Fast Global Registration + scaled ICP — :mod:`gctr_cli.baselines.features`
- ``cpd``: rigid Coherent Point Drift with scale (numpy) — :mod:`gctr_cli.baselines.cpd`
"""

from gctr_cli.baselines.cpd import register_cpd
from gctr_cli.baselines.features import register_fgr, register_fpfh_ransac
from gctr_cli.baselines.icp import register_icp

REGISTER_FUNCTIONS = {
    "icp": register_icp,
    "fpfh_ransac": register_fpfh_ransac,
    "fgr": register_fgr,
    "cpd": register_cpd,
}

__all__ = ["REGISTER_FUNCTIONS", "register_cpd", "register_fgr", "register_fpfh_ransac", "register_icp"]
