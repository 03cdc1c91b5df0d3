"""Point-cloud measures the geometric instances are built on: neighbour distances and the scene's spacing, normals,
robust sizes, DBSCAN and connected components (open3d), and points near others."""

from __future__ import annotations

from typing import Optional

import numpy as np


def kth_neighbour_distances(points: np.ndarray, k: int) -> np.ndarray:
    """[P] distance from each of [P, 3] points to its k-th nearest neighbour (empty when P <= k)."""
    from scipy.spatial import cKDTree

    if len(points) <= k:
        return np.zeros(0)
    dist, _ = cKDTree(points).query(points, k=k + 1)
    return dist[:, k]


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The smallest of [P] ``values`` at which the cumulative [P] non-negative ``weights`` (in the values'
    order) reach half their total; the plain median when every weight is 0."""
    if len(values) == 0:
        return float("nan")
    if not (weights > 0).any():
        return float(np.median(values))
    return float(np.quantile(values, 0.5, weights=weights.astype(np.float64), method="inverted_cdf"))


def neighbourhood_spacing(points: np.ndarray, k: int, weights: Optional[np.ndarray] = None) -> float:
    """Median distance from each of [P, 3] points to its k-th nearest neighbour, each point counted ``weights``
    [P] times when given."""
    kth = kth_neighbour_distances(points, k)
    if len(kth) == 0:
        return 1.0
    middle = np.median(kth) if weights is None else weighted_median(kth, weights)
    return float(max(middle, 1e-9))


def o3d_cloud(points: np.ndarray):
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return cloud


def local_normals(points: np.ndarray, spacing: float, neighbours: int = 16) -> np.ndarray:
    """[P, 3] unit normals from the covariance of each point's neighbourhood (open3d)."""
    import open3d as o3d

    cloud = o3d_cloud(points)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * spacing, max_nn=neighbours))
    return np.asarray(cloud.normals)


def robust_diagonal(points: np.ndarray) -> float:
    """Diagonal of the 2nd–98th percentile bounding box of [P, 3] points."""
    if len(points) == 0:
        return 0.0
    lo, hi = np.percentile(points, [2.0, 98.0], axis=0)
    return float(np.linalg.norm(hi - lo))


def dbscan_labels(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """[P] open3d DBSCAN label of each of [P, 3] points (-1: noise; ``min_points`` 1: single linkage)."""
    return np.asarray(o3d_cloud(points).cluster_dbscan(eps, min_points, print_progress=False), dtype=np.int64)


def largest_component(points: np.ndarray, eps: float) -> np.ndarray:
    """Indices of the largest DBSCAN component of [P, 3] points (linked within ``eps``)."""
    labels = dbscan_labels(points, eps, 3)
    if not (labels >= 0).any():
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(labels == np.bincount(labels[labels >= 0]).argmax())


def nearby_points(candidates: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the [C, 3] ``candidates`` within ``radius`` of any of the [P, 3] ``points`` (none when radius <= 0)."""
    from scipy.spatial import cKDTree

    if radius <= 0 or len(candidates) == 0 or len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    dist, _ = cKDTree(points).query(candidates, k=1, distance_upper_bound=radius)
    return np.flatnonzero(np.isfinite(dist))
