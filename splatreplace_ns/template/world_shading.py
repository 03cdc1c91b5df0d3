"""Light that stays with the world while a copy turns (``model.world_shading``, not in the paper).

A template's colour carries the light that fell on the copies it was fitted to. Turning it with a copy's pose turns
that light too: a face lit by the sun on one copy stays lit on a copy where it faces away. Per class, a low-order
shading term in *world* coordinates, shared by the copies, multiplies each Gaussian's colour by
``exp(s_c · [1, n_w])`` per channel, where ``n_w`` is the Gaussian's normal turned into the world by the copy's pose.
What turns with the copy (the template's colour) and what stays with the scene (the shading) are then learnt
apart, from every copy's views at once. The term starts at 0 (gain 1).
"""

from __future__ import annotations

import torch
from torch import Tensor

from splatreplace_ns.render.projection import quat_to_rotmat
from splatreplace_ns.render.transform import zero_quats_to_identity

SHADING_TERMS = 4
"""Terms of the shading function of a normal: a constant and the three components (SH degree 0 and 1)."""


def template_normals(means: Tensor, quats: Tensor, log_scales: Tensor, centre: Tensor) -> Tensor:
    """Unit normals of template Gaussians: the axis of their smallest scale, turned to point away from ``centre``
    (a Gaussian's axis has no sign; outwards is the side a surface of a compact object faces).

    Args:
        means [M, 3], quats [M, 4] (wxyz, any norm; zero reads as identity), log_scales [M, 3]; centre [M, 3] or
        [3]: the centre of each Gaussian's template.
    Returns:
        [M, 3] unit normals, template space (no gradient: the shading does not move the Gaussians).
    """
    with torch.no_grad():
        R = quat_to_rotmat(zero_quats_to_identity(quats))  # [M, 3, 3], columns = the Gaussian's axes
        axis = torch.argmin(log_scales, dim=-1)  # [M]
        normal = torch.gather(R, 2, axis[:, None, None].expand(-1, 3, 1))[..., 0]  # [M, 3]
        outwards = ((means - centre) * normal).sum(-1, keepdim=True)
        normal = torch.where(outwards < 0, -normal, normal)
        return normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def shading_log_gain(world_normals: Tensor, coefficients: Tensor) -> Tensor:
    """Natural log of the colour gain per channel of Gaussians with the given world normals.

    Args:
        world_normals: [M, 3] unit normals in the world; coefficients: [M, 4, 3] the shading of each Gaussian's
            class (constant, x, y, z terms per channel).
    Returns:
        [M, 3].
    """
    basis = torch.cat((torch.ones_like(world_normals[:, :1]), world_normals), dim=-1)  # [M, 4]
    return torch.einsum("mj,mjc->mc", basis, coefficients)
