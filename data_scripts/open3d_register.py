"""What a user writes with Open3D for `gctr register SOURCE TARGET -o MATRIX` (the reference of bench_process.py).

    python data_scripts/open3d_register.py SOURCE TARGET MATRIX

Open3D's global-registration tutorial recipe, with scale: both clouds normalised (centroid, bounding-box
diagonal 1), voxel 0.02, FPFH (radii 2 / 5 voxels), RANSAC on feature matches with similarity hypotheses,
scaled point-to-point ICP, the similarity composed back and written as 4 lines of 4 numbers (%.17g).
Open3D's RANSAC is seeded (0), so two runs on the same pair write the same matrix.
"""
import sys

import numpy as np
import open3d as o3d

reg, search = o3d.pipelines.registration, o3d.geometry.KDTreeSearchParamHybrid
VOXEL = 0.02
o3d.utility.random.seed(0)


def load(path):  # -> normalised cloud, its centre and its diagonal
    p = np.asarray(o3d.io.read_point_cloud(path).points)
    centre, size = p.mean(axis=0), np.linalg.norm(p.max(axis=0) - p.min(axis=0))
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector((p - centre) / size)), centre, size


def features(pcd):
    down = pcd.voxel_down_sample(VOXEL)
    down.estimate_normals(search(radius=2 * VOXEL, max_nn=30))
    # open3d's stubs omit the default of `indices` (empty = every point), which the binding has
    return down, reg.compute_fpfh_feature(down, search(radius=5 * VOXEL, max_nn=100))  # type: ignore[call-arg]


(src, cs, ss), (tgt, ct, st) = load(sys.argv[1]), load(sys.argv[2])
(src_d, src_f), (tgt_d, tgt_f) = features(src), features(tgt)
ransac = reg.registration_ransac_based_on_feature_matching(
    src_d, tgt_d, src_f, tgt_f, False, 1.5 * VOXEL, reg.TransformationEstimationPointToPoint(True), 3,
    [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * VOXEL)],
    reg.RANSACConvergenceCriteria(100000, 0.999))
icp = reg.registration_icp(src.voxel_down_sample(VOXEL / 2), tgt.voxel_down_sample(VOXEL / 2), VOXEL,
                           ransac.transformation, reg.TransformationEstimationPointToPoint(True))


def frame(centre, size):  # normalised -> original coordinates
    F = np.eye(4)
    F[:3, :3], F[:3, 3] = size * np.eye(3), centre
    return F


np.savetxt(sys.argv[3], frame(ct, st) @ icp.transformation @ np.linalg.inv(frame(cs, ss)), fmt="%.17g")
