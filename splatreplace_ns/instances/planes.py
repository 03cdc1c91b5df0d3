"""Supporting planes among the Gaussian centres: found and removed (RANSAC, refined), told level (floors, boards)
from walls, the floor picked, and an instance cut off the floor it stands on."""

from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from splatreplace_ns.instances.geometric_config import ClusteringConfig
from splatreplace_ns.instances.point_cloud import (
    largest_component,
    local_normals,
    neighbourhood_spacing,
    o3d_cloud,
    robust_diagonal,
)


def two_sidedness(points: np.ndarray, plane: np.ndarray, threshold: float) -> float:
    """Fraction of the [P, 3] points between ``threshold`` and 10 × ``threshold`` from the [4] plane (unit
    normal) that lie on its less crowded side; 0 when there are none."""
    signed = points @ plane[:3] + plane[3]
    near = (np.abs(signed) > threshold) & (np.abs(signed) <= 10.0 * threshold)
    if not near.any():
        return 0.0
    above = float((signed[near] > 0).mean())
    return min(above, 1.0 - above)


def refine_plane(points: np.ndarray, plane: np.ndarray, threshold: float, max_rounds: int = 20) -> Tuple[np.ndarray, np.ndarray]:
    """Least-squares refit of a RANSAC plane on its inliers, repeated until the inliers stop changing.

    open3d's RANSAC runs its samples on several threads, so the plane it returns for one point set can
    differ from run to run by a sample; refitting to a fixed point removes that, so that the same model
    gives the same planes (and the same mask bytes).

    Args:
        points: [P, 3].
        plane: [4] (a, b, c, d), a x + b y + c z + d = 0.
        threshold: inlier distance.

    Returns:
        the refined [4] plane (unit normal, largest-magnitude normal component positive), inlier indices.
    """
    unit = plane[:3] / max(np.linalg.norm(plane[:3]), 1e-12)
    plane = np.append(unit, plane[3] / max(np.linalg.norm(plane[:3]), 1e-12))
    inliers = np.flatnonzero(np.abs(points @ plane[:3] + plane[3]) <= threshold)
    for _ in range(max_rounds):
        if len(inliers) < 3:
            break
        centre = points[inliers].mean(axis=0)
        normal = np.linalg.svd(points[inliers] - centre, full_matrices=False)[2][-1]
        normal = normal if normal[np.argmax(np.abs(normal))] > 0 else -normal
        plane = np.append(normal, -float(normal @ centre))
        refit = np.flatnonzero(np.abs(points @ plane[:3] + plane[3]) <= threshold)
        if np.array_equal(refit, inliers):
            break
        inliers = refit
    return plane, inliers


def remove_planes(points: np.ndarray, spacing: float, cfg: ClusteringConfig) -> Tuple[np.ndarray, List[np.ndarray]]:
    """Iteratively finds the largest planes (RANSAC) and marks their inliers.

    Only inliers whose local normal faces the plane's way count, and only their largest connected
    sheet is removed, and only when it spans a good part of the scene: nine chair seats at one height
    or a table top are not a floor. Rejected candidates are set aside so the search moves on.

    Args:
        points: [P, 3] solid Gaussian centres.
        spacing: the length unit.

    Returns:
        on_plane [P] bool, the removed planes ([4] each).
    """
    import open3d as o3d

    o3d.utility.random.seed(cfg.seed)
    normals = local_normals(points, spacing)
    scene_diagonal = robust_diagonal(points)
    on_plane = np.zeros(len(points), dtype=bool)
    set_aside = np.zeros(len(points), dtype=bool)
    planes: List[np.ndarray] = []
    threshold = cfg.plane_distance * spacing
    for _ in range(cfg.max_planes * 3):  # set-aside planes do not count toward max_planes
        if len(planes) >= cfg.max_planes:
            break
        remaining = np.flatnonzero(~on_plane & ~set_aside)
        if len(remaining) < max(3, cfg.min_plane_fraction * len(points)):
            break
        plane, _ = o3d_cloud(points[remaining]).segment_plane(threshold, 3, 1000)
        plane, inliers = refine_plane(points[remaining], np.asarray(plane, dtype=np.float64), threshold)
        inliers = remaining[inliers]
        unit = plane[:3] / max(np.linalg.norm(plane[:3]), 1e-12)
        facing = np.abs(normals[inliers] @ unit) >= cfg.plane_normal_agreement
        if int(facing.sum()) < cfg.min_plane_fraction * len(points):
            if len(inliers) < cfg.min_plane_fraction * len(points):
                break
            set_aside[inliers] = True  # not a supporting plane; look past these points
            continue
        inliers = inliers[facing]
        # a supporting plane is one connected sheet (the floor, a wall), not the seats of nine chairs; linked
        # at the sheet's own spacing, since a floor seen at a grazing angle holds sparser Gaussians than the objects
        own = neighbourhood_spacing(points[inliers], cfg.cluster_min_points)
        sheet = inliers[largest_component(points[inliers], cfg.cluster_eps * max(spacing, own))]
        if len(sheet) < cfg.min_plane_fraction * len(points):
            set_aside[inliers] = True
            continue
        wall = not is_level(unit)
        set_aside[inliers] = True  # what follows either removes the sheet or leaves it aside
        inliers = sheet
        if len(inliers) < cfg.min_plane_fraction * len(points):
            continue
        if robust_diagonal(points[inliers]) < cfg.min_plane_extent * scene_diagonal:
            continue
        if wall and two_sidedness(points, plane, threshold) > cfg.max_two_sidedness:
            continue
        set_aside[inliers] = False
        on_plane[inliers] = True
        planes.append(plane)
    return on_plane, planes


def floor_basis(up: np.ndarray) -> np.ndarray:
    """[3, 2] orthonormal basis of the plane perpendicular to the unit vector ``up`` [3] (coordinates across
    the floor)."""
    across = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    return np.stack([across, np.cross(up, across)], axis=1)


UP = (0.0, 0.0, 1.0)
"""nerfstudio's up in its normalised frame."""


LEVEL_TILT_DEG = 30.0
"""A plane whose normal lies within this many degrees of up is level (a floor, a board); others are walls."""


def is_level(normal: np.ndarray, prior: Sequence[float] = UP, max_tilt_deg: float = LEVEL_TILT_DEG) -> bool:
    """Whether a plane with the [3] ``normal`` (any length, either sign) is within ``max_tilt_deg`` of level."""
    prior = np.asarray(prior, dtype=np.float64)
    cos = abs(float(np.asarray(normal, dtype=np.float64) @ prior)) / max(np.linalg.norm(normal) * np.linalg.norm(prior), 1e-12)
    return cos >= np.cos(np.radians(max_tilt_deg))


def floor_plane(planes: Sequence[np.ndarray], prior: Sequence[float] = UP,
                max_tilt_deg: float = LEVEL_TILT_DEG, points: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
    """[4] the floor among the removed planes, as (n, d) with a unit normal n pointing along ``prior``
    (nerfstudio's up, +z), so that ``x · n + d`` is the height above it; None when no plane is within
    ``max_tilt_deg`` of ``prior`` (a capture whose only planes are walls).

    Without ``points`` the plane closest to ``prior`` is the floor; with them ([P, 3]), the level plane with the
    fewest points under it (a second level plane, such as the sheet a chessboard's pieces' tops make, lies above
    the floor)."""
    prior = np.asarray(prior, dtype=np.float64) / np.linalg.norm(prior)
    best, best_key = None, None
    for plane in planes:
        plane = np.asarray(plane, dtype=np.float64)
        norm = max(np.linalg.norm(plane[:3]), 1e-12)
        cos = float(plane[:3] @ prior) / norm
        if not is_level(plane[:3], prior, max_tilt_deg):
            continue
        plane = plane * np.sign(cos) / norm
        key = -abs(cos) if points is None else float(np.mean(points @ plane[:3] + plane[3] < 0))
        if best_key is None or key < best_key:
            best, best_key = plane, key
    return best


def cut_off_the_floor(
    ids: np.ndarray, means: np.ndarray, floor: np.ndarray, spacing: float, low: float, reach: float,
    ground: Optional[Dict[int, float]] = None, holds: Optional[np.ndarray] = None,
) -> np.ndarray:
    """Sends to the background an instance's low Gaussians that lie under nothing of it.

    Copies stand on the floor, so what lies low of an object lies under the object; faint Gaussians of the floor
    just above it, beside a foot or a leg, still join an instance through its cluster. An instance's Gaussians
    within ``low`` spacings above its ground go to the background when they lie farther across the floor than
    ``reach`` spacings from every one of its Gaussians higher than that.

    Args:
        ids: [N] instance id per Gaussian (0 = background); means: [N, 3].
        floor: [4] (unit normal pointing up, offset) of the floor plane (:func:`floor_plane`).
        spacing: the length unit; low, reach: in spacings.
        ground: {instance id: height in spacings} of the level an instance stands on when that is not the
            floor (a column on a step): its band is measured from there.
        holds: [N] bool, the Gaussians that can hold a foot up (opaque ones; None: all): faint fuzz reaching
            above the band must not hold up the fuzz under it.

    Returns:
        [N] ids.
    """
    from scipy.spatial import cKDTree

    up = floor[:3]
    height = (means @ up + floor[3]) / spacing
    out = ids.copy()
    basis = floor_basis(up)
    holds = np.ones(len(means), dtype=bool) if holds is None else holds
    for k in np.unique(out[out > 0]):
        members = np.flatnonzero(out == k)
        h = height[members] - (ground or {}).get(int(k), 0.0)
        raised = members[(h >= low) & holds[members]]
        lowest = members[h < low]
        if len(raised) == 0 or len(lowest) == 0:
            continue
        dist, _ = cKDTree(means[raised] @ basis).query(means[lowest] @ basis, k=1)
        out[lowest[dist > reach * spacing]] = 0
    return out
