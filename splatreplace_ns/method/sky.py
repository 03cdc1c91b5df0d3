"""The sky as a background that depends only on the elevation of the viewing ray.

Where a dataset says depth 0 is the sky (``"depth_zero": "far"``), the base stage supervises its inverse depth
as 0. Gaussians cannot be both infinitely far and opaque, so with splatfacto's random training background the
colour loss and the depth loss pull against each other and the model hangs a bright, half-transparent sky
somewhere in between. Here the sky is instead the background behind every ray: a smooth function of the ray's
elevation, learned with the Gaussians, while the accumulated opacity is asked to be 0 on
sky pixels and 1 on pixels with a surface. From a new viewpoint the sky keeps its colour gradient instead of
showing the viewer's background colour.
"""

from __future__ import annotations

import torch


def pixel_directions(camera_to_world: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Unit world-space direction of the ray through each pixel centre.

    Args:
        camera_to_world: [3, 4] nerfstudio (OpenGL) camera pose: x right, y up, the camera looks along −z.
        K: [3, 3] pinhole intrinsics in pixels.
        width, height: image size in pixels.
    Returns:
        [H, W, 3] unit directions.
    """
    dtype, device = camera_to_world.dtype, camera_to_world.device
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype) + 0.5,
        torch.arange(width, device=device, dtype=dtype) + 0.5,
        indexing="ij",
    )
    x = (u - K[0, 2]) / K[0, 0]
    y = -(v - K[1, 2]) / K[1, 1]  # image rows grow downwards, camera y upwards
    in_camera = torch.stack([x, y, -torch.ones_like(x)], dim=-1)
    world = in_camera @ camera_to_world[:3, :3].T
    return world / world.norm(dim=-1, keepdim=True)


def legendre_basis(u: torch.Tensor, degree: int) -> torch.Tensor:
    """Legendre polynomials P_0 … P_degree (Bonnet's recurrence).

    Args:
        u: [...] values in [−1, 1].
        degree: highest degree, ≥ 0.
    Returns:
        [..., degree + 1] P_l(u).
    """
    basis = [torch.ones_like(u), u][: degree + 1]
    for l in range(1, degree):
        basis.append(((2 * l + 1) * u * basis[l] - l * basis[l - 1]) / (l + 1))
    return torch.stack(basis, dim=-1)


def sky_colour(coefficients: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Colour of the sky seen along each direction, a function of its elevation only.

    The sky is modelled as the same at every azimuth (a zonal function of the up component z): a capture sees
    the sky on one side, and new views from the other side must get a sky from it. A full spherical-harmonic
    sky fitted on one half of the sphere is free to be anything on the other half.

    Args:
        coefficients: [L + 1, 3] Legendre coefficients per RGB channel over z (nerfstudio's dataparsers
            orient the world with z up).
        directions: [..., 3] unit directions.
    Returns:
        [..., 3] colour in (0, 1) (a sigmoid of the expansion, so any coefficients are valid).
    """
    if coefficients.ndim != 2 or coefficients.shape[0] < 1 or coefficients.shape[1] != 3:
        raise ValueError(f"sky coefficients must be [degree + 1, 3], got {tuple(coefficients.shape)}")
    basis = legendre_basis(directions[..., 2].clamp(-1.0, 1.0), coefficients.shape[0] - 1)
    return torch.sigmoid(basis @ coefficients)


def sky_opacity_l1(alpha: torch.Tensor, target_depth: torch.Tensor, min_depth: float = 1e-3) -> torch.Tensor:
    """Accumulated opacity against what the depth says: 0 where the ray sees the sky, 1 where it hits a surface.

    Args:
        alpha: [H, W, 1] accumulated opacity.
        target_depth: [H, W, 1] ground-truth depth: +inf for the sky, 0 (or below ``min_depth``) where unknown.
    Returns:
        scalar: mean alpha over sky pixels plus mean (1 − alpha) over surface pixels (each 0 when absent).
    """
    sky = torch.isinf(target_depth)
    surface = (target_depth > min_depth) & ~sky
    loss = alpha.sum() * 0.0
    if bool(sky.any()):
        loss = loss + alpha[sky].mean()
    if bool(surface.any()):
        loss = loss + (1.0 - alpha[surface]).mean()
    return loss
