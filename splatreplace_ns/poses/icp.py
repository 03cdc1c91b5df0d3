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


def turn_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` (radians) about ``axis`` (3,)."""
    from scipy.spatial.transform import Rotation

    u = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(angle * u / np.linalg.norm(u)).as_matrix()


def nearest_upright(T: np.ndarray, source_points: np.ndarray, up) -> np.ndarray:
    """The turn about ``up`` nearest to T's rotation (T's heading of a horizontal direction), with the
    translation that keeps where T puts the source centroid.

    Args:
        T: (4, 4) rigid transform; source_points: (N, 3); up: (3,) axis.
    Returns:
        (4, 4) transform whose rotation is a pure turn about ``up``.
    """
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    e = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e /= np.linalg.norm(e)
    f = np.cross(u, e)
    heading = np.asarray(T, dtype=np.float64)[:3, :3] @ e
    R = turn_about(u, float(np.arctan2(heading @ f, heading @ e)))
    c = np.asarray(source_points, dtype=np.float64).reshape(-1, 3).mean(axis=0)
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = T[:3, :3] @ c + T[:3, 3] - R @ c
    return out


def refine_icp_upright(
    source_points: np.ndarray,
    target_points: np.ndarray,
    init: np.ndarray,
    up,
    max_distance: float = 0.05,
    max_iterations: int = 60,
    normal_neighbours: int = 30,
) -> tuple[np.ndarray, float]:
    """Point-to-plane ICP restricted to a turn about ``up`` and a translation (4 degrees of freedom).

    For copies that stand on one floor: their relative pose has no tilt, and leaving the tilt free lets ICP
    trade a small tilt for a better fit of a partly reconstructed copy. open3d's ICP has no constrained
    estimator, so each step solves the 4-parameter linearised point-to-plane problem here (target normals
    from open3d, nearest neighbours from scipy). ``init``'s rotation is first replaced by its nearest upright one
    (:func:`nearest_upright`).

    Args:
        source_points: (N, 3); target_points: (M, 3); init: (4, 4); up: (3,) axis.
        max_distance: correspondence distance cut-off.
        max_iterations: iteration cap (stops earlier once a step turns less than 1e-6 rad and moves less
            than 1e-6 of ``max_distance``).
        normal_neighbours: k for the target normals (open3d).
    Returns:
        T (4, 4) with target ≈ T · source and a pure turn about ``up`` as rotation; fitness (fraction of
        source points with a correspondence within ``max_distance``).
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    src = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    src = src[np.isfinite(src).all(axis=1)]
    tgt_cloud = _cloud(target_points)
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    T = nearest_upright(np.asarray(init, dtype=np.float64), src, u) if len(src) else np.asarray(init, float).copy()
    if len(src) < 4 or len(tgt_cloud.points) < 3:
        return T, 0.0
    tgt_cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=normal_neighbours))
    tgt, normals = np.asarray(tgt_cloud.points), np.asarray(tgt_cloud.normals)
    tree = cKDTree(tgt)
    fitness = 0.0
    for _ in range(int(max_iterations)):
        moved = src @ T[:3, :3].T + T[:3, 3]
        dist, idx = tree.query(moved, k=1, distance_upper_bound=max_distance)
        hit = np.isfinite(dist)
        fitness = float(hit.mean())
        if hit.sum() < 4:
            break
        p, q, n = moved[hit], tgt[idx[hit]], normals[idx[hit]]
        c = p.mean(axis=0)  # turn about the matched centroid: keeps turn and translation decoupled
        residual = np.einsum("ni,ni->n", n, p - q)
        # linearised p' = c + R(δ)(p − c) + t: d/dδ = n · (u × (p − c)), d/dt = n
        J = np.concatenate([np.einsum("ni,ni->n", n, np.cross(u, p - c))[:, None], n], axis=1)
        step = np.linalg.lstsq(J, -residual, rcond=None)[0]
        R = turn_about(u, float(step[0]))
        dT = np.eye(4)
        dT[:3, :3] = R
        dT[:3, 3] = c - R @ c + step[1:]
        T = dT @ T
        if abs(step[0]) < 1e-6 and np.linalg.norm(step[1:]) < 1e-6 * max_distance:
            break
    return T, fitness
