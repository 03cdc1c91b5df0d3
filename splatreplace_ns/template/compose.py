"""Shared-template math (paper §4.3): instance poses and composing instances into one scene (the SH rotation is
``render.transform``'s).

The scene after registration is stored as one set of Gaussians: background Gaussians (class 0) in
world coordinates and, per class ``c ≥ 1``, template Gaussians in *template space* (the world frame of
the class's template instance). Every instance ``i`` of class ``c`` is a reference to that template: a
pose ``P_i`` (template space → world) and per-Gaussian SH offsets in its slot ``s_i``. Its colour is
``c = λ c_shared + (1 − λ) c_offset`` (λ = 0.8), optionally times a learned gain per colour channel for the
whole copy (``model.copy_colour_gain``, not in the paper).

Quaternions are wxyz. Poses are ``q_i = exp(ω_i) ⊗ q0_i``, ``t_i = t0_i + δt_i`` with the learnable
``(ω_i, δt_i)`` starting at zero: a stable parametrisation (no normalisation drift, no gimbal lock,
identity at the registration result).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional

import torch
from torch import Tensor

from splatreplace_ns.render.projection import quat_to_rotmat
from splatreplace_ns.render.sh import SH_C0
from splatreplace_ns.render.transform import axis_angle_to_quat, quat_multiply, sh_rotation, zero_quats_to_identity


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


@dataclass
class ComposedScene:
    """Gaussians of the replaced scene in world coordinates (one rasterize call).

    Attributes:
        means [M, 3], quats [M, 4], log_scales [M, 3], logit_opacities [M, 1], sh [M, K, 3];
        param_index [M] long: the stored Gaussian each rendered one comes from (background first, then
        instance by instance); instance_id [M] long: 0 for background, else the instance's id;
        offsets [M_inst, K, 3]: the SH offsets in use (rows of the instances, in order), or None.
    """

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    logit_opacities: Tensor
    sh: Tensor
    param_index: Tensor
    instance_id: Tensor
    offsets: Optional[Tensor] = None


def mix_sh(shared: Tensor, offset: Tensor, lam: float) -> Tensor:
    """Per-instance SH: ``λ c_shared + (1 − λ) c_offset``. shared, offset: [..., K, 3] → [..., K, 3]."""
    return lam * shared + (1.0 - lam) * offset


def apply_colour_gain(coeffs: Tensor, log_gain: Tensor) -> Tensor:
    """SH coefficients whose colour is the input's times ``exp(log_gain)`` per channel.

    With the 3DGS convention ``rgb = SH(d) + 0.5`` (``render.sh``), scaling every coefficient by g and adding
    ``0.5 (g − 1) / C0`` to the DC term gives ``g · rgb`` in every direction (before the clamp at 0).

    Args:
        coeffs: [M, K, 3] SH coefficients; log_gain: [M, 3] or [3] natural log of the gain per channel.
    Returns:
        [M, K, 3].
    """
    gain = torch.exp(log_gain)
    dc_shift = torch.zeros_like(coeffs)
    dc_shift[:, 0, :] = (0.5 / SH_C0) * (gain - 1.0)
    return coeffs * gain.unsqueeze(-2) + dc_shift


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
    colour_gain: Optional[Tensor] = None,
) -> ComposedScene:
    """Places every instance's copy of its class template into the world.

    Args:
        means [N, 3], quats [N, 4] (wxyz, any norm; a zero one reads as the identity, as in the renderer),
            log_scales [N, 3], logit_opacities [N, 1] or [N]: stored Gaussians.
        sh: [N, K, 3] shared SH (background Gaussians: their own SH).
        sh_offsets: [N, S, K, 3] per-slot offsets (S = most instances of one class).
        gauss_class: [N] long, 0 = background, c ≥ 1 = template Gaussian of class c.
        instance_class [I], instance_slot [I], instance_ids [I]: long, per instance.
        pose_q [I, 4], pose_R [I, 3, 3], pose_t [I, 3]: template space → world (see :func:`instance_poses`).
        lam: mixing weight λ.
        sh_degree: degree used for the SH rotation (default: from K).
        colour_gain: [I, 3] natural log of each instance's colour gain per channel (:func:`apply_colour_gain`),
            or None (no gain).
    Returns:
        :class:`ComposedScene` with M = N_background + Σ_i N_{class(i)} Gaussians.
    """
    K = sh.shape[1]
    degree = int(round(math.sqrt(K))) - 1 if sh_degree is None else sh_degree
    device = means.device
    background = torch.nonzero(gauss_class == 0).squeeze(-1)
    # Row order: background, then instance by instance. Every per-row quantity is built with gathers,
    # per-row broadcasting and split/cat, never by slicing a big tensor per instance: the backward of a
    # slice writes a zero-filled buffer of the whole tensor, once per instance and step (that was most of
    # the fine-tuning step on CPU).
    rows, slots, counts, kept = [], [], [], []
    for i in range(len(instance_ids)):
        idx = torch.nonzero(gauss_class == instance_class[i]).squeeze(-1)
        if idx.numel():
            rows.append(idx)
            slots.append(torch.full_like(idx, int(instance_slot[i])))
            counts.append(idx.numel())
            kept.append(i)
    if not kept:
        return ComposedScene(means[background], quats[background], log_scales[background],
                             logit_opacities[background], sh[background], background, torch.zeros_like(background))
    inst_rows = torch.cat(rows)  # [M_inst]
    param_index = torch.cat((background, inst_rows))
    kept_t = torch.tensor(kept, dtype=torch.long, device=device)
    row_instance = torch.repeat_interleave(kept_t, torch.tensor(counts, device=device))  # [M_inst] index into I
    instance_id = torch.cat((torch.zeros_like(background), instance_ids.to(device)[row_instance]))

    R_rows, t_rows, q_rows = pose_R[row_instance], pose_t[row_instance], pose_q[row_instance]
    means_inst = torch.einsum("mij,mj->mi", R_rows, means[inst_rows]) + t_rows
    quats_inst = quat_multiply(q_rows, zero_quats_to_identity(quats[inst_rows]))
    offsets = sh_offsets[inst_rows, torch.cat(slots)]  # [M_inst, K, 3]
    coeffs = mix_sh(sh[inst_rows], offsets, lam)
    log_gain = None if colour_gain is None else colour_gain.to(coeffs)[row_instance]
    if log_gain is not None:  # a gain per channel commutes with the SH rotation below
        coeffs = apply_colour_gain(coeffs, log_gain)
    if K > 1:  # SH rotation: one [K, K] matrix per instance, applied to its block of rows
        rot = sh_rotation(pose_R[kept_t], degree)[..., :K, :K]  # [I', K, K]
        coeffs = torch.cat([torch.einsum("kl,nlc->nkc", rot[k], block) for k, block in enumerate(coeffs.split(counts))])
    return ComposedScene(
        torch.cat((means[background], means_inst)), torch.cat((quats[background], quats_inst)),
        log_scales[param_index], logit_opacities[param_index], torch.cat((sh[background], coeffs)),
        param_index, instance_id, offsets,
    )


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
