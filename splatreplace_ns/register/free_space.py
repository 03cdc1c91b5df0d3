"""Free-space check of a registration: a copy of the template placed at an instance must not fill space that
the training cameras saw through.

A wrong pose of a partly seen copy can fit its few Gaussians well (a chair turned by 180° matches its seen
backrest to the template's) while the rest of the template then sticks out where the cameras saw the floor or
the wall behind. Parts of the template the cameras never saw lie *behind* the observed surfaces (hidden) and
cost nothing; parts in front of them are violations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F


@dataclass
class ObservedDepth:
    """What the training cameras saw: the scene's rendered depth per view (``inf`` where nothing is opaque)."""

    viewmats: np.ndarray
    """(V, 4, 4) world → camera (OpenCV: x right, y down, z forward)."""
    Ks: np.ndarray
    """(V, 3, 3) intrinsics of the stored depth maps (scaled with them)."""
    depths: Sequence[np.ndarray]
    """V depth maps (H_v, W_v) along the camera z axis (an array (V, H, W) when the views share one size)."""


def pooled_depth(depth: torch.Tensor, max_width: int) -> tuple[torch.Tensor, float]:
    """Depth map shrunk to at most ``max_width`` columns by min-pooling (the nearest surface of each block is
    kept, so a point is never judged in front of a surface that the block does not have).

    Args:
        depth: (H, W) depth (``inf`` where empty).
        max_width: largest width kept.
    Returns:
        (H', W') depth and the factor s (pixel coordinates scale as u' = u / s).
    """
    width = depth.shape[-1]
    factor = max(1, int(np.ceil(width / max(1, max_width))))
    if factor == 1:
        return depth, 1.0
    finite = torch.where(torch.isfinite(depth), depth, torch.full_like(depth, 1e30))
    pooled = -F.max_pool2d(-finite[None, None], kernel_size=factor, stride=factor, ceil_mode=True)[0, 0]
    return torch.where(pooled >= 1e29, torch.full_like(pooled, float("inf")), pooled), float(factor)


def scaled_intrinsics(K: np.ndarray, factor: float) -> np.ndarray:
    """(3, 3) intrinsics of an image shrunk by ``factor`` (pixel i covers [i, i + 1), as in gsplat: u' = u / s)."""
    out = np.asarray(K, dtype=np.float64).copy()
    out[:2, :] /= factor
    return out


def free_space_violation(points: np.ndarray, observed: ObservedDepth, margin: float) -> float:
    """How much of a placed shape lies where the cameras saw through.

    Args:
        points: (N, 3) world points (the posed template's solid centres).
        observed: the training views' depth.
        margin: a point counts as in front of a surface only when nearer than it by more than this (world units).
    Returns:
        mean over the points of the fraction of the views that see the point inside their image in which it
        lies in front of the observed surface (0: never in seen free space; 1: always); 0 for no points or
        no view that sees any.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        return 0.0
    front = np.zeros(len(pts))
    seen = np.zeros(len(pts))
    for viewmat, K, depth in zip(observed.viewmats, observed.Ks, observed.depths):
        height, width = depth.shape
        cam = pts @ np.asarray(viewmat[:3, :3], dtype=np.float64).T + np.asarray(viewmat[:3, 3], dtype=np.float64)
        z = cam[:, 2]
        ahead = z > 1e-6
        zs = np.where(ahead, z, 1.0)
        u = np.floor(K[0, 0] * cam[:, 0] / zs + K[0, 2]).astype(np.int64)  # pixel i covers [i, i + 1)
        v = np.floor(K[1, 1] * cam[:, 1] / zs + K[1, 2]).astype(np.int64)
        inside = ahead & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        surface = np.full(len(pts), np.inf)
        surface[inside] = depth[v[inside], u[inside]]
        seen += inside
        front += inside & (z < surface - margin)
    return float(np.mean(front / np.maximum(seen, 1.0)))


@torch.no_grad()
def observed_depth(render_depth, cameras, max_views: int = 64, max_width: int = 160) -> ObservedDepth:
    """The training views' depth, rendered by the model, evenly subsampled and min-pooled to keep it small.

    Args:
        render_depth: callable (one-camera Cameras) → (H, W) depth tensor with ``inf`` where nothing is opaque.
        cameras: nerfstudio Cameras of the training views.
        max_views: most views kept (evenly spaced).
        max_width: most depth-map columns kept.
    """
    from splatreplace_ns.render.cameras import world_to_camera

    n = len(cameras)
    if n == 0:
        return ObservedDepth(np.zeros((0, 4, 4)), np.zeros((0, 3, 3)), [])
    keep = np.unique(np.linspace(0, n - 1, num=min(n, max_views)).round().astype(int))
    viewmats = world_to_camera(cameras.camera_to_worlds[keep].float()).cpu().numpy()
    Ks_full = cameras.get_intrinsics_matrices()[keep].float().cpu().numpy()
    depths, Ks = [], []
    for k, idx in enumerate(keep):
        depth, factor = pooled_depth(render_depth(cameras[int(idx) : int(idx) + 1]).float().cpu(), max_width)
        depths.append(depth.numpy())
        Ks.append(scaled_intrinsics(Ks_full[k], factor))
    return ObservedDepth(viewmats, np.stack(Ks), depths)  # a list: the views of a capture may differ in size
