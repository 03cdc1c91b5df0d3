"""Rendering (every stage renders through here). In: Gaussians (means, quats, scales, opacities, colours or SH) and
a camera. Out: image, depth, alpha, screen-space means and radii. A vectorised pure-PyTorch rasteriser (CPU or GPU,
autograd backward) with gsplat's conventions, and gsplat (CUDA) behind the same interface."""

from .cameras import world_to_camera
from .projection import ProjectedGaussians, project_gaussians, quat_to_rotmat
from .rasterize import BACKEND_ENV_VAR, RenderOutput, rasterize, resolve_backend
from .sh import sh_to_color, spherical_harmonics

__all__ = [
    "BACKEND_ENV_VAR",
    "ProjectedGaussians",
    "RenderOutput",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
    "resolve_backend",
    "sh_to_color",
    "spherical_harmonics",
    "world_to_camera",
]
