"""Stages 1-2 for one cloud: the working cloud (voxel-downsampled, normals), its salient points
(supervoxel centroids) and what the later stages look up in it; and the cloud the verdict refines on.

Everything is in normalised coordinates (:func:`gctr_cli.engine.preprocess.normalise`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gctr_cli.config import EngineConfig
from gctr_cli.engine.preprocess import downsample_to, nearest_neighbours, normals_and_roughness
from gctr_cli.engine.ransac import OccupancyGrid
from gctr_cli.engine.scipy_parts import cKDTree
from gctr_cli.engine.supervoxel import supervoxels
from gctr_cli.engine.verdict import Surface


@dataclass
class StageTimer:
    """Seconds spent per pipeline stage (``RegistrationResult.timings``)."""

    timings: dict[str, float]

    def add(self, stage: str, start: float) -> float:
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + now - start
        return now


@dataclass(frozen=True)
class PreparedCloud:
    """One cloud after stages 1-2, in normalised coordinates."""

    points: np.ndarray  # downsampled working cloud
    normals: np.ndarray  # unit normals of ``points``
    tree: cKDTree  # over ``points``
    salient: np.ndarray  # supervoxel centroids
    salient_normals: np.ndarray
    salient_tree: cKDTree
    surface: Surface  # what the verdict moves and looks up
    roughness: float  # median distance of the points from their local PCA planes (preprocess.normals_and_roughness)
    grids: dict = field(default_factory=dict, compare=False)

    def reflected(self, mirror: np.ndarray, cfg: EngineConfig) -> PreparedCloud:
        """The same cloud reflected by the diagonal ``mirror`` (e.g. x -> -x): points, normals and salient
        points mirrored, the trees and the verdict's sample built again (the mirror check's search)."""
        points, normals = self.points * mirror, self.normals * mirror
        tree = cKDTree(points)
        salient = self.salient * mirror
        return PreparedCloud(points=points, normals=normals, tree=tree, salient=salient,
                             salient_normals=self.salient_normals * mirror, salient_tree=cKDTree(salient),
                             roughness=self.roughness,
                             surface=Surface.build(points, normals, tree, cfg.verdict.sample_points,
                                                   cfg.verdict.normal_balance))

    def grid(self, radius: float) -> OccupancyGrid:
        """Occupancy grid of the working cloud at ``radius`` (built once, then cached)."""
        if radius not in self.grids:
            self.grids[radius] = OccupancyGrid(self.points, radius)
        return self.grids[radius]


def prepare_cloud(points: np.ndarray, cfg: EngineConfig, rng: np.random.Generator, timer: StageTimer) -> PreparedCloud:
    """Working cloud, normals and salient points of one normalised cloud (stages 1-2)."""
    t = time.perf_counter()
    work = downsample_to(points, cfg.supervoxel.voxel_ratio, cfg.preprocess.max_points, rng)
    tree = cKDTree(work)  # one tree for the normals, the voxel graph and (if nothing is dropped) the later lookups
    neighbour_dist, neighbours = nearest_neighbours(work, cfg.preprocess.normal_neighbours, tree)
    normals, roughness = normals_and_roughness(work, neighbours)
    t = timer.add("preprocess", t)
    sv = supervoxels(work, normals, voxel=cfg.supervoxel.voxel_ratio, seed_spacing=cfg.supervoxel.seed_ratio,
                     spatial_weight=cfg.supervoxel.spatial_weight, normal_weight=cfg.supervoxel.normal_weight,
                     iterations=cfg.supervoxel.iterations, min_voxels=cfg.supervoxel.min_voxels,
                     neighbour_distances=neighbour_dist, tree=tree,
                     neighbour_indices=neighbours)
    # Voxels that no supervoxel reached are isolated — typically outliers. Dropping them from the
    # working cloud keeps outliers out of the refinement and the fitness (with 30% uniform
    # outliers they otherwise pull scaled ICP's scale inwards).
    surface = sv.labels >= 0
    if cfg.preprocess.drop_isolated and not surface.all() and surface.sum() >= max(50, len(work) // 4):
        work, normals = work[surface], normals[surface]
        tree = cKDTree(work)
    salient, salient_normals = sv.centroids, sv.normals
    if len(salient) > cfg.supervoxel.max_salient:
        keep = np.sort(np.argsort(-sv.sizes, kind="stable")[: cfg.supervoxel.max_salient])
        salient, salient_normals = salient[keep], salient_normals[keep]
    timer.add("supervoxels", t)
    return PreparedCloud(points=work, normals=normals, tree=tree, salient=salient, salient_normals=salient_normals,
                     salient_tree=cKDTree(salient), roughness=roughness,
                     surface=Surface.build(work, normals, tree, cfg.verdict.sample_points,
                                           cfg.verdict.normal_balance))


class MirroredTree:
    """The k-d tree of a cloud reflected by the diagonal ``mirror``, without building one: a query for ``x``
    is the original tree's query for ``x * mirror`` (a reflection keeps every distance, bit for bit: the same
    neighbours at the same distances, barring exact distance ties, which two trees may break differently).
    Only :meth:`query` is offered (all the verdict and the refinement ask of a tree). Building the reflected
    cloud's own tree cost every accepted pair's reflection check 1-3 ms."""

    def __init__(self, tree: cKDTree, mirror: np.ndarray) -> None:
        self.tree, self.mirror = tree, mirror

    def query(self, x: np.ndarray, *args: Any, **kwargs: Any) -> Any:
        """``cKDTree.query`` of the reflected cloud (indices into its points, which are the original's order)."""
        return self.tree.query(np.asarray(x) * self.mirror, *args, **kwargs)


@dataclass(frozen=True)
class RefinementCloud:
    """A finer working cloud for the refinement and the final verdict (precision needs more points
    than the search)."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree  # over ``points`` (a MirroredTree in a reflected cloud)
    surface: Surface
    roughness: float  # as PreparedCloud.roughness

    @classmethod
    def build(cls, points: np.ndarray, cfg: EngineConfig, rng: np.random.Generator) -> RefinementCloud:
        pts = downsample_to(points, cfg.refine.voxel_ratio, cfg.refine.max_points, rng)
        tree = cKDTree(pts)
        normals, roughness = normals_and_roughness(pts, nearest_neighbours(pts, cfg.preprocess.normal_neighbours,
                                                                           tree)[1])
        surface = Surface.build(pts, normals, tree, cfg.verdict.sample_points, cfg.verdict.normal_balance)
        return cls(pts, normals, tree, surface, roughness)

    def reflected(self, mirror: np.ndarray, cfg: EngineConfig) -> RefinementCloud:
        """The same cloud reflected by the diagonal ``mirror`` (e.g. x -> -x): points and normals mirrored,
        the verdict's sample built again, the tree this cloud's own seen through the mirror
        (:class:`MirroredTree`: no tree is built) (the reflection check,
        :func:`~gctr_cli.engine.decide.reflected_fit`)."""
        points, normals = self.points * mirror, self.normals * mirror
        tree = MirroredTree(self.tree, mirror)
        return RefinementCloud(points, normals, tree, Surface.build(points, normals, tree, cfg.verdict.sample_points,
                                                                    cfg.verdict.normal_balance), self.roughness)

    @classmethod
    def of(cls, prepared: PreparedCloud, points: np.ndarray, cfg: EngineConfig,
           rng: np.random.Generator) -> RefinementCloud:
        """The refinement cloud of one input: the search's working cloud itself when
        ``refine.voxel_ratio`` is 0, else a finer downsampling of ``points``."""
        if cfg.refine.voxel_ratio == 0:
            return cls(prepared.points, prepared.normals, prepared.tree, prepared.surface, prepared.roughness)
        return cls.build(points, cfg, rng)
