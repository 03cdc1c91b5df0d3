"""Rigid transforms of Gaussians: quaternion algebra (wxyz), rotation matrices to quaternions, the rotation of
real SH coefficients with their object, and all three applied to a set of Gaussians."""

from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor

from splatreplace_ns.render.projection import QUAT_EPS
from splatreplace_ns.render.sh import num_sh_bases, sh_basis


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a ⊗ b``. a, b: [..., 4] wxyz (broadcast) → [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def zero_quats_to_identity(quats: Tensor) -> Tensor:
    """Quaternions with the zero ones (norm at most ``QUAT_EPS``) replaced by the identity. [..., 4] wxyz → [..., 4].

    The renderer reads a zero quaternion as the identity rotation (``projection.quat_to_rotmat``); composing a
    rotation with it then gives that rotation, where the raw product would stay zero and read as the identity.
    Other quaternions (also non-finite ones, which the renderer culls) come back as they are.
    """
    with torch.no_grad():
        zero = quats.norm(dim=-1, keepdim=True) <= QUAT_EPS
    if not bool(zero.any()):
        return quats
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    return torch.where(zero, identity, quats)


def axis_angle_to_quat(omega: Tensor) -> Tensor:
    """Rotation vector → unit quaternion. omega: [..., 3] (radians) → [..., 4] wxyz.

    Uses the Taylor series of sin(θ/2)/θ near 0, so values and gradients stay finite at ω = 0.
    """
    theta2 = (omega * omega).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2.clamp_min(1e-12))
    small = theta2 < 1e-8
    half_sinc = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(theta / 2) / theta)
    w = torch.where(small, 1.0 - theta2 / 8.0, torch.cos(theta / 2))
    return torch.cat((w, omega * half_sinc), dim=-1)


def rotmat_to_quat(R: Tensor) -> Tensor:
    """Rotation matrices → unit quaternions (w ≥ 0). R: [..., 3, 3] → [..., 4] wxyz. Not differentiated."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    flat = R.detach().cpu().double().reshape(-1, 3, 3).numpy()
    xyzw = Rotation.from_matrix(flat).as_quat() if len(flat) else np.zeros((0, 4))
    q = torch.as_tensor(xyzw[:, [3, 0, 1, 2]], dtype=R.dtype, device=R.device)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(*R.shape[:-2], 4)


@lru_cache(maxsize=8)
def sample_directions(n: int) -> Tensor:
    """[n, 3] float64 unit vectors spread over the sphere (Fibonacci lattice)."""
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / n
    r = torch.sqrt(1.0 - z * z)
    phi = math.pi * (1.0 + math.sqrt(5.0)) * k
    return torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), dim=-1)


def sh_rotation(R: Tensor, degree: int) -> Tensor:
    """Matrix that rotates SH coefficients with the object: coeffs_world = M @ coeffs_local.

    A function f_local(d) = Σ_k c_k Y_k(d) seen through the rotation R is f_world(d) = f_local(Rᵀ d).
    Each SH band is closed under rotation, so solving Y(d) M' = Y(Rᵀ d) in the least-squares sense on
    enough directions gives the exact rotation (block-diagonal per band): M = M'ᵀ.

    Args:
        R: [..., 3, 3] rotations. degree: SH degree (0..4).
    Returns:
        [..., K, K] with K = (degree + 1)², differentiable in R.
    """
    K = num_sh_bases(degree)
    dirs = sample_directions(max(4 * K, 32)).to(device=R.device)
    pinv = torch.linalg.pinv(sh_basis(degree, dirs)).to(R.dtype)  # [K, n], float64 accuracy
    rotated = torch.einsum("...ji,nj->...ni", R, dirs.to(R.dtype))  # Rᵀ d: [..., n, 3]
    Y_rot = sh_basis(degree, rotated)  # [..., n, K]
    return torch.einsum("kn,...nl->...kl", pinv, Y_rot)


def transform_gaussians(
    T: Tensor, means: Tensor, quats: Tensor, sh: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Applies a rigid transform to Gaussians.

    Args:
        T: [4, 4] rigid; means [n, 3]; quats [n, 4] wxyz (a zero one reads as the identity); sh [n, K, 3].
    Returns:
        means [n, 3], quats [n, 4], sh [n, K, 3] (SH rotated with the object).
    """
    R, t = T[:3, :3], T[:3, 3]
    q = rotmat_to_quat(R)
    K = sh.shape[1]
    degree = int(round(K**0.5)) - 1
    sh_out = torch.einsum("kl,nlc->nkc", sh_rotation(R, degree), sh) if K > 1 else sh
    return means @ R.T + t, quat_multiply(q.expand(len(quats), 4), zero_quats_to_identity(quats)), sh_out
