"""Geometric registration of point sets with open3d: ICP refinement (paper §4.2) and the FPFH + RANSAC
global-registration baseline (paper Fig. "ablation_register_3d").

All transforms are 4×4 rigid matrices ``T`` with target ≈ T · source.
"""

from __future__ import annotations

import numpy as np


def _cloud(points: np.ndarray):
    import open3d as o3d

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))


def refine_icp(
    source_points: np.ndarray,
    target_points: np.ndarray,
    init: np.ndarray | None = None,
    max_distance: float = 0.05,
    point_to_plane: bool = True,
    max_iterations: int = 100,
    normal_neighbours: int = 30,
) -> tuple[np.ndarray, float, float]:
    """Rigid ICP (open3d), point-to-plane by default (target normals estimated from ``normal_neighbours``
    nearest neighbours).

    Args:
        source_points: (N, 3); target_points: (M, 3).
        init: (4, 4) initial transform (identity if None).
        max_distance: correspondence distance cut-off (world units).
        point_to_plane: point-to-plane (True) or point-to-point error.
        max_iterations: ICP iteration cap.
        normal_neighbours: k for normal estimation.
    Returns:
        T (4, 4) with target ≈ T · source; fitness (fraction of source points with a correspondence within
        ``max_distance``); inlier rmse.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, tgt = _cloud(source_points), _cloud(target_points)
    init = np.eye(4) if init is None else np.asarray(init, dtype=np.float64)
    if len(src.points) < 3 or len(tgt.points) < 3:
        return init.copy(), 0.0, float("inf")
    if point_to_plane:
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=normal_neighbours))
        estimation = reg.TransformationEstimationPointToPlane()
    else:
        estimation = reg.TransformationEstimationPointToPoint(False)
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=1e-9, relative_rmse=1e-9, max_iteration=int(max_iterations)
    )
    out = reg.registration_icp(src, tgt, float(max_distance), init, estimation, criteria)
    return np.asarray(out.transformation).copy(), float(out.fitness), float(out.inlier_rmse)


def fpfh_ransac(
    source_points: np.ndarray,
    target_points: np.ndarray,
    voxel: float,
    seed: int = 0,
    max_iterations: int = 100000,
    confidence: float = 0.999,
    restarts: int = 1,
) -> tuple[np.ndarray, float]:
    """Global registration baseline: voxel down-sampling, FPFH features, feature-matching RANSAC (open3d).

    Normals use radius ``2·voxel``, FPFH radius ``5·voxel``; RANSAC inlier distance ``1.5·voxel`` with
    edge-length (0.9) and distance checkers, mutual feature filter. ``seed`` seeds open3d's generator.
    open3d's RANSAC stops early once its inlier ratio looks good, which can lock onto a near-symmetric
    wrong pose; ``restarts`` > 1 reruns it with seeds ``seed, seed+1, …`` and keeps the highest fitness.

    Args:
        source_points: (N, 3); target_points: (M, 3).
        voxel: down-sampling voxel size (world units).
    Returns:
        T (4, 4) with target ≈ T · source; fitness (inlier fraction of the down-sampled source).
    """
    import open3d as o3d

    reg = o3d.pipelines.registration

    def prep(points):
        pc = _cloud(points).voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel, max_nn=30))
        feat = reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100))
        return pc, feat

    src, src_f = prep(source_points)
    tgt, tgt_f = prep(target_points)
    if len(src.points) < 3 or len(tgt.points) < 3:
        return np.eye(4), 0.0
    dist = 1.5 * voxel
    best_T, best_fitness = np.eye(4), -1.0
    for k in range(max(1, int(restarts))):
        o3d.utility.random.seed(int(seed) + k)
        out = reg.registration_ransac_based_on_feature_matching(
            src,
            tgt,
            src_f,
            tgt_f,
            True,
            dist,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(int(max_iterations), float(confidence)),
        )
        if out.fitness > best_fitness:
            best_T, best_fitness = np.asarray(out.transformation).copy(), float(out.fitness)
    return best_T, max(best_fitness, 0.0)
