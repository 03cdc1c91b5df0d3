"""Real spherical-harmonics evaluation (degrees 0..4), following the
convention used by 3D Gaussian Splatting / gsplat:

    colour = sum_k  Y_k(normalize(dir)) * coeffs[k]

The caller is responsible for the ``+ 0.5`` offset and the clamp that 3DGS
applies afterwards (see :func:`sh_to_color`).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["spherical_harmonics", "sh_to_color", "num_sh_bases", "MAX_SH_DEGREE", "SH_C0"]

MAX_SH_DEGREE = 4

# Normalisation constants of the real SH basis (standard values).
_C0 = 0.28209479177387814
SH_C0 = _C0
"""The degree-0 basis constant: ``rgb = SH_C0 · dc + 0.5`` for a Gaussian without higher terms."""
_C1 = 0.4886025119029199
_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
_C4 = (
    2.5033429417967046,
    -1.7701307697799304,
    0.9461746957575601,
    -0.6690465435572892,
    0.10578554691520431,
    -0.6690465435572892,
    0.47308734787878004,
    -1.7701307697799304,
    0.6258357354491761,
)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Evaluate the SH basis functions up to ``degree`` at unit directions.

    Args:
        degree: 0..4.
        dirs: [..., 3] unit vectors.

    Returns:
        [..., (degree + 1) ** 2]
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            _C2[0] * xy,
            _C2[1] * yz,
            _C2[2] * (2.0 * zz - xx - yy),
            _C2[3] * xz,
            _C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _C3[0] * y * (3.0 * xx - yy),
            _C3[1] * xy * z,
            _C3[2] * y * (4.0 * zz - xx - yy),
            _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            _C3[4] * x * (4.0 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3.0 * yy),
        ]
    if degree >= 4:
        out += [
            _C4[0] * xy * (xx - yy),
            _C4[1] * yz * (3.0 * xx - yy),
            _C4[2] * xy * (7.0 * zz - 1.0),
            _C4[3] * yz * (7.0 * zz - 3.0),
            _C4[4] * (zz * (35.0 * zz - 30.0) + 3.0),
            _C4[5] * xz * (7.0 * zz - 3.0),
            _C4[6] * (xx - yy) * (7.0 * zz - 1.0),
            _C4[7] * xz * (xx - 3.0 * yy),
            _C4[8] * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy)),
        ]
    return torch.stack(out, dim=-1)


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Evaluate SH colours.

    Args:
        degree: SH degree to use (0..4); only the first (degree+1)^2
            coefficients are read.
        dirs: [..., 3] view directions (need not be normalised).
        coeffs: [..., K, 3] coefficients with K >= (degree+1)^2.

    Returns:
        [..., 3] raw SH values (no offset, no clamping).
    """
    nb = num_sh_bases(degree)
    if coeffs.shape[-2] < nb:
        raise ValueError(
            f"sh_degree={degree} needs at least {nb} coefficients, got {coeffs.shape[-2]}"
        )
    norm = dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, dirs / norm)  # [..., nb]
    return (basis.unsqueeze(-1) * coeffs[..., :nb, :]).sum(dim=-2)


def sh_to_color(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """gsplat/3DGS colour convention: clamp_min(SH(dirs) + 0.5, 0)."""
    return torch.clamp_min(spherical_harmonics(degree, dirs, coeffs) + 0.5, 0.0)
