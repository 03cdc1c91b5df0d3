"""Shared-template math (paper §4.3): poses, SH rotation and composing instances into one scene.

The scene after registration is stored as one set of Gaussians: background Gaussians (class 0) in
world coordinates and, per class ``c ≥ 1``, template Gaussians in *template space* (the world frame of
the class's template instance). Every instance ``i`` of class ``c`` is a reference to that template: a
pose ``P_i`` (template space → world) and per-Gaussian SH offsets in its slot ``s_i``. Its colour is
``c = λ c_shared + (1 − λ) c_offset`` (λ = 0.8).

Quaternions are wxyz. Poses are ``q_i = exp(ω_i) ⊗ q0_i``, ``t_i = t0_i + δt_i`` with the learnable
``(ω_i, δt_i)`` starting at zero: a stable parametrisation (no normalisation drift, no gimbal lock,
identity at the registration result).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Dict, Optional

import torch
from torch import Tensor

from splatreplace_ns.render.projection import quat_to_rotmat
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


def instance_poses(q0: Tensor, t0: Tensor, delta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Current instance poses from the registration result and the learned correction.

    Args:
        q0: [I, 4] initial rotations (wxyz, unit); t0: [I, 3] initial translations.
        delta: [I, 6] learned (ω, δt).
    Returns:
        q [I, 4] unit quaternions, R [I, 3, 3], t [I, 3] (template space → world).
    """
    q = quat_multiply(axis_angle_to_quat(delta[:, :3]), q0)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return q, quat_to_rotmat(q), t0 + delta[:, 3:]


@lru_cache(maxsize=8)
def _sample_directions(n: int) -> Tensor:
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
    dirs = _sample_directions(max(4 * K, 32)).to(device=R.device)
    pinv = torch.linalg.pinv(sh_basis(degree, dirs)).to(R.dtype)  # [K, n], float64 accuracy
    rotated = torch.einsum("...ji,nj->...ni", R, dirs.to(R.dtype))  # Rᵀ d: [..., n, 3]
    Y_rot = sh_basis(degree, rotated)  # [..., n, K]
    return torch.einsum("kn,...nl->...kl", pinv, Y_rot)


@dataclass
class ComposedScene:
    """Gaussians of the replaced scene in world coordinates (one rasterize call).

    Attributes:
        means [M, 3], quats [M, 4], log_scales [M, 3], logit_opacities [M, 1], sh [M, K, 3];
        param_index [M] long: the stored Gaussian each rendered one comes from (background first, then
        instance by instance); instance_id [M] long: 0 for background, else the instance's id.
    """

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    logit_opacities: Tensor
    sh: Tensor
    param_index: Tensor
    instance_id: Tensor


def mix_sh(shared: Tensor, offset: Tensor, lam: float) -> Tensor:
    """Per-instance SH: ``λ c_shared + (1 − λ) c_offset``. shared, offset: [..., K, 3] → [..., K, 3]."""
    return lam * shared + (1.0 - lam) * offset


def compose_scene(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    logit_opacities: Tensor,
    sh: Tensor,
    sh_offsets: Tensor,
    gauss_class: Tensor,
    instance_class: Tensor,
    instance_slot: Tensor,
    instance_ids: Tensor,
    pose_q: Tensor,
    pose_R: Tensor,
    pose_t: Tensor,
    lam: float = 0.8,
    sh_degree: Optional[int] = None,
) -> ComposedScene:
    """Places every instance's copy of its class template into the world.

    Args:
        means [N, 3], quats [N, 4], log_scales [N, 3], logit_opacities [N, 1] or [N]: stored Gaussians.
        sh: [N, K, 3] shared SH (background Gaussians: their own SH).
        sh_offsets: [N, S, K, 3] per-slot offsets (S = most instances of one class).
        gauss_class: [N] long, 0 = background, c ≥ 1 = template Gaussian of class c.
        instance_class [I], instance_slot [I], instance_ids [I]: long, per instance.
        pose_q [I, 4], pose_R [I, 3, 3], pose_t [I, 3]: template space → world (see :func:`instance_poses`).
        lam: mixing weight λ.
        sh_degree: degree used for the SH rotation (default: from K).
    Returns:
        :class:`ComposedScene` with M = N_background + Σ_i N_{class(i)} Gaussians.
    """
    K = sh.shape[1]
    degree = int(round(math.sqrt(K))) - 1 if sh_degree is None else sh_degree
    background = torch.nonzero(gauss_class == 0).squeeze(-1)
    # One gather per tensor for all copies (row order: background, then instance by instance): a gather's
    # backward writes a full-size gradient, so gathering per instance would cost one full [N, S, K, 3]
    # buffer per instance and step.
    rows, slots, counts, kept = [background], [], [], []
    for i in range(len(instance_ids)):
        idx = torch.nonzero(gauss_class == instance_class[i]).squeeze(-1)
        if idx.numel():
            rows.append(idx)
            slots.append(torch.full_like(idx, int(instance_slot[i])))
            counts.append(idx.numel())
            kept.append(i)
    param_index = torch.cat(rows)
    n_bg = background.numel()
    inst_rows = param_index[n_bg:]
    instance_id = torch.cat([torch.zeros_like(background)]
                            + [torch.full((n,), int(instance_ids[i]), dtype=torch.long, device=background.device)
                               for i, n in zip(kept, counts)])
    means_all, quats_all, sh_all = means[param_index], quats[param_index], sh[param_index]
    if not kept:
        return ComposedScene(means_all, quats_all, log_scales[param_index], logit_opacities[param_index], sh_all,
                             param_index, instance_id)
    offsets = sh_offsets[inst_rows, torch.cat(slots)]  # [M_inst, K, 3]
    rot = sh_rotation(pose_R[kept], degree)[..., :K, :K] if K > 1 else None  # [I', K, K]
    out_means, out_quats, out_sh = [means_all[:n_bg]], [quats_all[:n_bg]], [sh_all[:n_bg]]
    start = n_bg
    for k, (i, n) in enumerate(zip(kept, counts)):
        block = slice(start, start + n)
        out_means.append(means_all[block] @ pose_R[i].T + pose_t[i])
        out_quats.append(quat_multiply(pose_q[i].expand(n, 4), quats_all[block]))
        coeffs = mix_sh(sh_all[block], offsets[block.start - n_bg : block.stop - n_bg], lam)
        out_sh.append(torch.einsum("kl,nlc->nkc", rot[k], coeffs) if rot is not None else coeffs)
        start += n
    return ComposedScene(torch.cat(out_means), torch.cat(out_quats), log_scales[param_index],
                         logit_opacities[param_index], torch.cat(out_sh), param_index, instance_id)


def offsets_l1(sh_offsets: Tensor, gauss_class: Tensor, slots_per_class: Dict[int, int]) -> Tensor:
    """Mean absolute SH offset over the (Gaussian, slot) pairs that are in use.

    Args:
        sh_offsets: [N, S, K, 3]; gauss_class: [N] long; slots_per_class: {class: number of instances}.
    Returns:
        scalar tensor (0 when no offsets are in use).
    """
    total = sh_offsets.new_zeros(())
    count = 0
    for c, n_slots in slots_per_class.items():
        idx = gauss_class == c
        if n_slots and bool(idx.any()):
            used = sh_offsets[idx, :n_slots]
            total = total + used.abs().sum()
            count += used.numel()
    return total / max(count, 1)
