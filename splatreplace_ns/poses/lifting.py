"""Lifting 2D matches to 3D with rendered depth (paper §4.2, Eq. 2): ``p = D · M_cam · K⁻¹ (u, v, 1)ᵀ``.

Pixel convention (the renderer's and COLMAP's): ``(u, v)`` are continuous image coordinates, pixel
``(col, row)`` covers ``[col, col+1) × [row, row+1)`` and its centre is ``(col + 0.5, row + 0.5)``. The
depth of a keypoint is read from the pixel that contains it (nearest, no interpolation across depth edges).
Depth is the z-depth in the camera frame (the renderer's "expected z"), not the distance along the ray.
"""

from __future__ import annotations

import numpy as np

from splatreplace_ns.poses.instance import float64_array


def project(points_world: np.ndarray, K: np.ndarray, viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection.

    Args:
        points_world: (M, 3); K: (3, 3); viewmat: (4, 4) world→camera (OpenCV).
    Returns:
        uv (M, 2) continuous pixel coordinates, z (M,) camera z-depth.
    """
    p = float64_array(points_world).reshape(-1, 3)
    vm = float64_array(viewmat)
    cam = p @ vm[:3, :3].T + vm[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = cam @ float64_array(K).T
        uv = uvw[:, :2] / uvw[:, 2:3]
    return uv, z


def backproject(
    uv: np.ndarray, depth: np.ndarray, K: np.ndarray, viewmat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project pixels to world points with a z-depth map.

    Args:
        uv: (M, 2) continuous pixel coordinates (u = column axis, v = row axis).
        depth: (H, W) or (H, W, 1) z-depth; values <= 0 or non-finite mean "no surface".
        K: (3, 3) intrinsics; viewmat: (4, 4) world→camera (OpenCV) of the view that produced ``depth``.
    Returns:
        points_world (M, 3) float64 (NaN where invalid), valid (M,) bool — False for non-positive /
        non-finite depth or ``uv`` outside the image.
    """
    uv = float64_array(uv).reshape(-1, 2)
    d = float64_array(depth)
    if d.ndim == 3:
        d = d[..., 0]
    h, w = d.shape
    col = np.floor(uv[:, 0])
    row = np.floor(uv[:, 1])
    inside = np.isfinite(uv).all(axis=1) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    z = np.zeros(len(uv))
    z[inside] = d[row[inside].astype(np.int64), col[inside].astype(np.int64)]
    valid = inside & np.isfinite(z) & (z > 0)
    rays = np.concatenate([uv, np.ones((len(uv), 1))], axis=1) @ np.linalg.inv(float64_array(K)).T  # z = 1
    cam = rays * np.where(valid, z, np.nan)[:, None]
    vm = float64_array(viewmat)
    rot, t = vm[:3, :3], vm[:3, 3]
    world = (cam - t) @ rot  # R^T (x - t)
    return world, valid
