"""The scene's up direction from its floor: the normal of the largest near-horizontal plane (open3d RANSAC).

Copies of a repeated element that stand on one floor differ by a turn about the floor's normal. nerfstudio's
"up" orientation only makes +z the mean of the cameras' up vectors, which can be several degrees off the
floor normal (7.6° on the office preset); turns about that axis then carry a tilt.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np


@dataclass
class UpAxisEstimate:
    """Result of :func:`floor_up_axis`.

    Attributes:
        up: (3,) unit up direction (the prior when no floor was found).
        found: whether a floor plane was found.
        inliers: number of points on the chosen plane.
        tilt_deg: angle between ``up`` and the prior.
        message: what was found, for the log.
    """

    up: np.ndarray
    found: bool
    inliers: int
    tilt_deg: float
    message: str


# open3d's RANSAC is not bit-reproducible: the same points get the same answer within a process (bench rows
# registering one model twice must differ only in what they ablate)
_ESTIMATES: OrderedDict = OrderedDict()
_CACHE_SIZE = 8


def floor_up_axis(
    points: np.ndarray,
    prior=(0.0, 0.0, 1.0),
    max_tilt_deg: float = 20.0,
    distance_rel: float = 0.005,
    min_inlier_fraction: float = 0.05,
    max_planes: int = 6,
    seed: int = 0,
) -> UpAxisEstimate:
    """Normal of the plane with the most points among those within ``max_tilt_deg`` of ``prior``.

    Planes are peeled off one at a time with open3d's ``segment_plane`` (RANSAC), so walls (far from the
    prior) do not hide the floor; parallel horizontal planes (steps, a table top) agree with the floor anyway.
    The chosen plane's normal is then refitted by least squares to the points within ever tighter bands
    around it (on the office preset's whole background: 0.39° → 0.17° from the true floor normal).

    Args:
        points: (N, 3) background points (e.g. the centres of the Gaussians not in any instance).
        prior: (3,) the expected up direction (nerfstudio's +z).
        max_tilt_deg: planes whose normal is further than this from ``prior`` are not floors.
        distance_rel: RANSAC inlier distance as a fraction of the points' bounding-box diagonal.
        min_inlier_fraction: a plane with fewer than this fraction of the points is not a floor; nor is one
            holding less than twice the share that a slab of its thickness would cut from points spread
            evenly over their extent along its normal.
        max_planes: planes tried at most.
        seed: open3d's random seed.
    Returns:
        :class:`UpAxisEstimate`; ``up`` is oriented to the prior's side and is the prior itself when
        nothing qualifies (too few points, no near-horizontal plane).
    """
    prior = np.asarray(prior, dtype=np.float64)
    prior = prior / np.linalg.norm(prior)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    key = hashlib.sha1(pts.tobytes() + np.array([*prior, max_tilt_deg, distance_rel, min_inlier_fraction,
                                                  max_planes, seed]).tobytes()).digest()
    if key not in _ESTIMATES:
        _ESTIMATES[key] = _estimate(pts, prior, max_tilt_deg, distance_rel, min_inlier_fraction, max_planes, seed)
        while len(_ESTIMATES) > _CACHE_SIZE:
            _ESTIMATES.popitem(last=False)
    found = _ESTIMATES[key]
    return replace(found, up=found.up.copy())


def _estimate(pts, prior, max_tilt_deg, distance_rel, min_inlier_fraction, max_planes, seed) -> UpAxisEstimate:
    """:func:`floor_up_axis` on finite (N, 3) points and a unit prior."""
    import open3d as o3d

    fallback = UpAxisEstimate(prior, False, 0, 0.0, "")
    min_inliers = max(3, int(min_inlier_fraction * len(pts)))
    if len(pts) < min_inliers:
        fallback.message = f"up axis: {len(pts)} background points, too few for a floor; using {_fmt(prior)}"
        return fallback
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.utility.random.seed(int(seed))
    cos_max = np.cos(np.radians(max_tilt_deg))
    threshold = max(distance_rel * diag, 1e-9)
    best = None  # (inliers, normal, offset)
    for _ in range(max_planes):
        if len(cloud.points) < min_inliers:
            break
        plane, idx = cloud.segment_plane(distance_threshold=threshold, ransac_n=3,
                                         num_iterations=1000)
        if len(idx) < min_inliers:
            break
        coeffs = np.asarray(plane, dtype=np.float64) / np.linalg.norm(plane[:3])  # n·x + d = 0, |n| = 1
        normal, offset = (coeffs[:3], coeffs[3]) if coeffs[:3] @ prior >= 0 else (-coeffs[:3], -coeffs[3])
        # a floor is denser than a slab of its thickness through scattered points would be
        extent = max(float(np.ptp(pts @ normal)), 10.0 * threshold)  # (a lone plane: its own noise)
        dense = len(idx) >= 2.0 * (2.0 * threshold / extent) * len(pts)
        if dense and normal @ prior >= cos_max and (best is None or len(idx) > best[0]):
            best = (len(idx), normal, float(offset))
        cloud = cloud.select_by_index(idx, invert=True)
    if best is None:
        fallback.message = f"up axis: no dense plane within {max_tilt_deg:.0f}° of {_fmt(prior)} (≥ {min_inliers} points); using it"
        return fallback
    n_in, up, offset = best
    # least squares on ever tighter bands (a RANSAC normal rests on 3 points), the last band until its point
    # set stops changing: runs of open3d's RANSAC (not bit-reproducible) then end on the same plane
    selected = None
    for band in (1.0, 0.5) + (0.25,) * 20:
        inside = np.abs(pts @ up + offset) < band * threshold
        if inside.sum() < 3:
            break
        if band == 0.25 and selected is not None and np.array_equal(inside, selected):
            break
        selected = inside
        centre = pts[inside].mean(axis=0)
        up = np.linalg.svd(pts[inside] - centre, full_matrices=False)[2][-1]
        up = up if up @ prior >= 0 else -up
        offset = -float(up @ centre)
    tilt = float(np.degrees(np.arccos(np.clip(up @ prior, -1.0, 1.0))))
    return UpAxisEstimate(up, True, int(n_in), tilt,
                          f"up axis: floor normal {_fmt(up)} ({n_in} points), {tilt:.1f}° from {_fmt(prior)}")


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in v) + ")"
