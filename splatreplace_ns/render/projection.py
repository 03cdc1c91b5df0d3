"""EWA projection of 3D Gaussians into a pinhole (OpenCV) camera.

Follows the conventions of 3D Gaussian Splatting / gsplat ("classic" mode):

* covariance ``Sigma = R S S^T R^T`` from a (normalised) wxyz quaternion and
  linear scales;
* local affine approximation of the perspective projection, with the camera
  space x/y clamped to 1.3x the field of view before forming the Jacobian;
* a 0.3 px^2 low-pass added to the 2D covariance (no opacity compensation);
* radius ``ceil(3 * sqrt(lambda_max))`` used for culling, 0 = culled.

Everything is written with per-component tensor algebra (no batched 3x3
matmuls), which is both faster on CPU and numerically better behaved: the
determinant of the 2D covariance is computed with the Cauchy-Binet identity
so it can never go negative through cancellation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

__all__ = ["ProjectedGaussians", "project_gaussians", "quat_to_rotmat", "EPS2D"]

EPS2D = 0.3
# quaternions with a norm below this are treated as the identity rotation
QUAT_EPS = 1e-12


@dataclass
class ProjectedGaussians:
    """Per-Gaussian screen-space quantities (all of length N)."""

    means2d: Tensor  # [N, 2] pixel coordinates (0 where culled)
    depths: Tensor  # [N] camera-space z
    conics: Tensor  # [N, 3] inverse 2D covariance (xx, xy, yy), blur included
    cov2d: Tensor  # [N, 3] 2D covariance (xx, xy, yy), blur included
    radii: Tensor  # [N] int32, 0 = culled
    visible: Tensor  # [N] bool, radii > 0
    means_cam: Tensor  # [N, 3] camera-space means
    det2d: Tensor  # [N] determinant of cov2d (blur included), computed stably


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """wxyz quaternions (any norm) -> [N, 3, 3] rotation matrices.

    The quaternion is normalised with an epsilon; a zero quaternion therefore
    maps to the zero vector, for which the formula below yields the identity,
    and all gradients stay finite.
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_EPS)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        1.0 - 2.0 * (yy + zz),
        2.0 * (xy - wz),
        2.0 * (xz + wy),
        2.0 * (xy + wz),
        1.0 - 2.0 * (xx + zz),
        2.0 * (yz - wx),
        2.0 * (xz - wy),
        2.0 * (yz + wx),
        1.0 - 2.0 * (xx + yy),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
    cull: Optional[Tensor] = None,
) -> ProjectedGaussians:
    """Project N Gaussians (world space) into one camera.

    Args:
        means: [N, 3]; quats: [N, 4] wxyz (any norm); scales: [N, 3] linear.
        viewmat: [4, 4] world -> camera (OpenCV convention).
        K: [3, 3] intrinsics.
        cull: optional [N] bool, Gaussians culled wherever they project (radius 0).
    """
    dtype = means.dtype
    viewmat = viewmat.to(dtype)
    K = K.to(dtype)
    Rw = viewmat[:3, :3]
    tw = viewmat[:3, 3]

    means_c = means @ Rw.T + tw  # [N, 3]
    tx, ty, tz = means_c.unbind(-1)

    fx, fy = K[0, 0], K[1, 1]
    cx, cy = K[0, 2], K[1, 2]

    in_depth = (tz >= near) & (tz <= far) & (tz > 0)
    # safe depth for culled Gaussians so that nothing in the graph is inf/nan
    z = torch.where(in_depth, tz, torch.ones_like(tz))
    inv_z = 1.0 / z

    # Jacobian of the perspective projection, evaluated at the clamped point
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    u = torch.minimum(torch.maximum(tx * inv_z, -lim_x_neg), lim_x_pos)
    v = torch.minimum(torch.maximum(ty * inv_z, -lim_y_neg), lim_y_pos)
    # J = [[fx/z, 0, -fx*u/z], [0, fy/z, -fy*v/z]]
    j00 = fx * inv_z
    j02 = -fx * u * inv_z
    j11 = fy * inv_z
    j12 = -fy * v * inv_z

    # T = J @ W (2x3), A = T @ R S (2x3);  cov2d = A A^T
    R = quat_to_rotmat(quats)  # [N, 3, 3]
    M = R * scales.unsqueeze(-2)  # [N, 3, 3] = R diag(s)
    WM = torch.einsum("ij,njk->nik", Rw, M)  # [N, 3, 3] rotation into camera
    a0 = j00.unsqueeze(-1) * WM[:, 0, :] + j02.unsqueeze(-1) * WM[:, 2, :]  # [N, 3]
    a1 = j11.unsqueeze(-1) * WM[:, 1, :] + j12.unsqueeze(-1) * WM[:, 2, :]  # [N, 3]

    cxx = (a0 * a0).sum(-1)
    cxy = (a0 * a1).sum(-1)
    cyy = (a1 * a1).sum(-1)
    # det(A A^T) = sum of squared 2x2 minors of A (Cauchy-Binet): >= 0 always
    m01 = a0[:, 0] * a1[:, 1] - a0[:, 1] * a1[:, 0]
    m02 = a0[:, 0] * a1[:, 2] - a0[:, 2] * a1[:, 0]
    m12 = a0[:, 1] * a1[:, 2] - a0[:, 2] * a1[:, 1]
    det_raw = m01 * m01 + m02 * m02 + m12 * m12
    sxx = cxx + eps2d
    syy = cyy + eps2d
    det = (det_raw + eps2d * (cxx + cyy) + eps2d * eps2d).clamp_min(1e-30)
    inv_det = 1.0 / det
    conics = torch.stack([syy * inv_det, -cxy * inv_det, sxx * inv_det], dim=-1)
    cov2d = torch.stack([sxx, cxy, syy], dim=-1)

    means2d = torch.stack([fx * tx * inv_z + cx, fy * ty * inv_z + cy], dim=-1)

    with torch.no_grad():
        # lambda_max = b + sqrt(b^2 - det) with b^2 - det written stably
        half_diff = 0.5 * (sxx - syy)
        disc = (half_diff * half_diff + cxy * cxy).clamp_min(0.01)
        lam = 0.5 * (sxx + syy) + disc.sqrt()
        radius = torch.ceil(3.0 * lam.sqrt())
        mx, my = means2d[:, 0], means2d[:, 1]
        inside = (
            (mx + radius > 0)
            & (mx - radius < width)
            & (my + radius > 0)
            & (my - radius < height)
        )
        visible = in_depth & inside & torch.isfinite(radius) & torch.isfinite(det)
        if cull is not None:
            visible &= ~cull
        radius = radius.clamp_max(float(2**30))
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)

    vis_f = visible.unsqueeze(-1)
    means2d = torch.where(vis_f, means2d, torch.zeros_like(means2d))
    return ProjectedGaussians(
        means2d=means2d,
        depths=tz,
        conics=conics,
        cov2d=cov2d,
        radii=radii,
        visible=visible,
        means_cam=means_c,
        det2d=det,
    )
