"""World-frame shading of the template instances: one scene's light, seen through each copy's turn.

Copies of a template stand at different turns under one light. A face of the template that points toward
the light in one copy points away from it in another, so one shared colour cannot be right for both, and
the per-instance SH offsets only correct the faces each copy was seen on. Here every template Gaussian
carries an outward normal in template space; a copy's Gaussian is shaded by ``s = exp(W · n_world)``
with ``n_world`` that normal turned by the copy's pose and ``W`` [3, 3] (one row per colour channel)
learned for the whole scene. A face that a copy was never seen on then takes the brightness the scene's
light gives faces turned that way, learned from the copies whose faces were seen turned that way.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
"""Degree-0 SH basis constant: the rendered colour is ``SH_C0 · dc + (higher bands) + 0.5``."""


def shading_factors(normals_world: Tensor, weights: Tensor) -> Tensor:
    """Per-Gaussian RGB brightness factors ``exp(W · n)``.

    Args:
        normals_world: [M, 3] unit outward normals in the world (zero rows: no normal known).
        weights: [3, 3] one row per colour channel.
    Returns:
        [M, 3] factors > 0 (1 for zero normals).
    """
    return torch.exp(normals_world @ weights.T)


def shade_sh(sh: Tensor, factors: Tensor) -> Tensor:
    """SH coefficients whose rendered colour is ``factors`` times that of ``sh``.

    The renderer's colour is ``c = SH_C0 · dc + Σ_k Y_k c_k + 0.5``; scaling every coefficient by ``s`` and
    adding ``0.5 (s − 1) / SH_C0`` to the DC term gives ``s · c`` in every view direction.

    Args:
        sh: [M, K, 3]; factors: [M, 3].
    Returns:
        [M, K, 3].
    """
    scaled = sh * factors[:, None, :]
    dc = scaled[:, :1] + (0.5 / SH_C0) * (factors[:, None, :] - 1.0)
    return torch.cat((dc, scaled[:, 1:]), dim=1)


def camera_votes(
    means: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
    depths: Optional[Tensor] = None, depth_tolerance: float = 0.05, near: float = 0.01,
) -> Tensor:
    """Sum of the unit directions from each Gaussian to the cameras that see it.

    A view sees a centre in front of it (``z > near``), inside the image and, with ``depths``, not behind
    the rendered surface by more than ``depth_tolerance`` (relative).

    Args:
        means: [N, 3] world centres; viewmats: [V, 4, 4] world→camera (OpenCV); Ks: [V, 3, 3].
        depths: [V, H, W] rendered depth (0 = empty) or None.
    Returns:
        [N, 3] (zero rows: seen by no view).
    """
    points = means.detach().double()
    votes = torch.zeros_like(points)
    ones = torch.ones_like(points[:, :1])
    for v in range(viewmats.shape[0]):
        w2c = viewmats[v].double().to(points.device)
        cam = torch.cat((points, ones), dim=-1) @ w2c.T
        z = cam[:, 2]
        pix = cam[:, :3] @ Ks[v].double().to(points.device).T
        u, r = pix[:, 0] / z.clamp_min(near), pix[:, 1] / z.clamp_min(near)
        seen = (z > near) & (u >= 0) & (u < width) & (r >= 0) & (r < height)
        if depths is not None:
            surface = depths[v].double().to(points.device)[r.clamp(0, height - 1).long(), u.clamp(0, width - 1).long()]
            seen &= (surface <= 0) | (z <= surface * (1.0 + depth_tolerance))
        centre = -w2c[:3, :3].T @ w2c[:3, 3]
        to_camera = centre - points
        to_camera = to_camera / to_camera.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        votes += to_camera * seen[:, None]
    return votes.to(means.dtype)


def oriented_normals(means: Tensor, labels: Tensor, votes: Tensor, neighbours: int = 16) -> Tensor:
    """Outward unit normals of the labelled Gaussians, 0 elsewhere.

    Each instance's normals are the local PCA normals of its centres (open3d, ``neighbours`` nearest),
    turned toward the cameras that saw each Gaussian (``votes``). A Gaussian no camera saw (the far side of
    a copy) is turned away from its instance's centroid, which is right wherever the object is convex.

    Args:
        means: [N, 3]; labels: [N] long instance id (0 = background); votes: [N, 3] from :func:`camera_votes`.
    Returns:
        [N, 3] float, same dtype and device as ``means``.
    """
    import open3d as o3d

    out = np.zeros((len(means), 3))
    points_all = means.detach().cpu().double().numpy()
    votes_all = votes.detach().cpu().double().numpy()
    labels_np = labels.detach().cpu().numpy()
    for iid in np.unique(labels_np[labels_np > 0]):
        rows = np.flatnonzero(labels_np == iid)
        if len(rows) < 3:
            continue
        points = points_all[rows]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(min(neighbours, len(rows))))
        normals = np.asarray(cloud.normals).copy()
        side = np.einsum("ij,ij->i", normals, votes_all[rows])
        seen = np.abs(side) > 1e-9
        outward = np.einsum("ij,ij->i", normals, points - points.mean(axis=0))
        side = np.where(seen, side, outward)
        normals *= np.where(side < 0, -1.0, 1.0)[:, None]
        out[rows] = normals
    return torch.from_numpy(out).to(device=means.device, dtype=means.dtype)
