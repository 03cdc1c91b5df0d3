"""Clicks to 3D and back: lift a pixel with rendered depth, project points, decide visibility by depth.

Conventions: cameras are nerfstudio's (OpenGL camera→world); pixel ``(u, v)`` = (column, row) covers
``[u, u+1) x [v, v+1)``, so a click at integer ``(u, v)`` is the ray through ``(u + 0.5, v + 0.5)``,
the renderer's pixel centre.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch

from nerfstudio.cameras.cameras import Cameras

from splatreplace_ns.render.cameras import world_to_camera
from splatreplace_ns.datamanager.clicks import pixel_index


class ClickError(ValueError):
    """A click that cannot become an instance; the message names the click."""


class OnPlaneClickError(ClickError):
    """A click whose point lies on a supporting plane (the floor, a wall) rather than on an instance."""


class DuplicateClicksError(ClickError):
    """Two clicks on one spot of one object; ``sources`` names both."""

    def __init__(self, message: str, sources: Tuple[str, str]) -> None:
        super().__init__(message)
        self.sources = sources


@dataclass(frozen=True)
class LiftedClick:
    index: int
    """Position in clicks.json."""
    frame: int
    """Frame index in transforms.json."""
    xy: Tuple[float, float]
    cls: str
    point: torch.Tensor
    """[3] the clicked surface point, normalised world frame."""
    source: str
    """Human-readable origin, for messages."""
    camera_centre: Optional[torch.Tensor] = None
    """[3] centre of the clicked frame's camera (the ray the click lies on runs from it through ``point``)."""


def view_and_intrinsics(camera: Cameras) -> Tuple[torch.Tensor, torch.Tensor, int, int]:
    """World→camera (OpenCV) [4, 4], K [3, 3], width, height of a one-camera ``Cameras``."""
    viewmat = world_to_camera(camera.camera_to_worlds.reshape(1, 3, 4))[0]
    K = camera.get_intrinsics_matrices().reshape(3, 3)
    return viewmat, K, int(camera.width.reshape(-1)[0]), int(camera.height.reshape(-1)[0])


def lift_pixel(u: float, v: float, depth: float, viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """The 3D point at z-depth ``depth`` on the ray through pixel ``(u, v)``'s centre.

    Args:
        u, v: pixel (column, row).
        depth: camera-space z of the surface there.
        viewmat: [4, 4] world→camera (OpenCV).
        K: [3, 3] intrinsics.

    Returns:
        [3] world point.
    """
    x = (u + 0.5 - float(K[0, 2])) / float(K[0, 0]) * depth
    y = (v + 0.5 - float(K[1, 2])) / float(K[1, 1]) * depth
    camera_point = torch.tensor([x, y, depth, 1.0], dtype=viewmat.dtype)
    return (torch.linalg.inv(viewmat) @ camera_point)[:3]


def project_points(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (continuous, pixel centres at ``i + 0.5``) and camera z of world points.

    Args:
        points: [P, 3] world points.
        viewmat: [4, 4] world→camera (OpenCV).
        K: [3, 3].

    Returns:
        uv [P, 2], z [P] (z <= 0: behind the camera, uv meaningless).
    """
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    safe = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    u = K[0, 0] * cam[:, 0] / safe + K[0, 2]
    v = K[1, 1] * cam[:, 1] / safe + K[1, 2]
    return torch.stack([u, v], dim=-1), z


def frames_holding(points: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, sizes: torch.Tensor) -> torch.Tensor:
    """How many views hold each point: in front of the camera and inside its image (occlusion not tested).

    Args:
        points: [P, 3] world points.
        viewmats: [F, 4, 4] world→camera (OpenCV).
        Ks: [F, 3, 3].
        sizes: [F, 2] image width, height.

    Returns:
        [P] int64 counts in [0, F].
    """
    counts = torch.zeros(len(points), dtype=torch.int64)
    for viewmat, K, (width, height) in zip(viewmats, Ks, sizes.tolist()):
        uv, z = project_points(points, viewmat, K)
        counts += inside_image(uv, z, width, height).cpu().long()
    return counts


def inside_image(uv: torch.Tensor, z: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[P] bool: in front of the camera (z > 0) and within the image, for [P, 2] pixel coordinates ``uv`` and
    [P] camera z from :func:`project_points`."""
    return (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)


def visible_by_depth(
    points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
    relative_tolerance: float = 0.05, min_alpha: float = 0.5,
) -> torch.Tensor:
    """Whether points are seen in a view: inside the image, in front, and not behind the rendered surface.

    Args:
        points: [P, 3] world points.
        depth: [H, W, 1] rendered z-depth of the view.
        alpha: [H, W, 1] rendered opacity of the view.
        relative_tolerance: a point is hidden when it lies more than this fraction of its depth behind the
            rendered surface.

    Returns:
        [P] bool.
    """
    H, W = depth.shape[:2]
    uv, z = project_points(points, viewmat, K)
    col, row = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
    inside = inside_image(uv, z, W, H)
    col_c, row_c = col.clamp(0, W - 1), row.clamp(0, H - 1)
    surface = depth[row_c, col_c, 0]
    covered = alpha[row_c, col_c, 0] >= min_alpha
    in_front = ~covered | (z <= surface * (1.0 + relative_tolerance))
    return inside & in_front


def nearest_opaque_pixel(alpha: torch.Tensor, row: int, col: int, min_alpha: float, radius: int = 3) -> Optional[Tuple[int, int]]:
    """(row, col) of the pixel nearest (row, col), within ``radius`` pixels, whose [H, W] ``alpha`` reaches
    ``min_alpha``; None when there is none (a click on the sky, not beside an object)."""
    H, W = alpha.shape
    r0, r1, c0, c1 = max(0, row - radius), min(H, row + radius + 1), max(0, col - radius), min(W, col + radius + 1)
    rows, cols = torch.nonzero(alpha[r0:r1, c0:c1] >= min_alpha, as_tuple=True)
    if len(rows) == 0:
        return None
    d2 = (rows + r0 - row) ** 2 + (cols + c0 - col) ** 2
    k = int(torch.argmin(d2))
    if float(d2[k]) > radius**2:
        return None
    return int(rows[k]) + r0, int(cols[k]) + c0


def lift_click(
    index: int, frame: int, xy: Tuple[float, float], cls: str, source: str,
    depth: torch.Tensor, alpha: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, min_alpha: float = 0.5,
) -> LiftedClick:
    """Lifts one click with the base model's rendered depth of its view.

    Args:
        depth: [H, W, 1], alpha: [H, W, 1] rendered in the click's frame.

    Raises:
        ClickError: outside the image, or nothing opaque rendered there (sky, empty space).
    """
    H, W = depth.shape[:2]
    u, v = xy
    pixel = pixel_index(u, v, W, H)
    if pixel is None:
        raise ClickError(f"{source}: pixel {xy} is outside the {W}x{H} image")
    row, col = pixel
    if float(alpha[row, col, 0]) < min_alpha or not bool(torch.isfinite(depth[row, col, 0])):
        near = nearest_opaque_pixel(alpha[..., 0], row, col, min_alpha)
        hint = "" if near is None else f"; the nearest that is lies at [{near[1]}, {near[0]}] (pixel x, y)"
        raise ClickError(
            f"{source}: nothing opaque is rendered at this pixel (alpha {float(alpha[row, col, 0]):.2f} < "
            f"{min_alpha:g}: empty space, sky, or an object's edge{hint}); click on an object"
        )
    point = lift_pixel(u, v, float(depth[row, col, 0]), viewmat.double(), K.double()).float()
    centre = -viewmat[:3, :3].double().T @ viewmat[:3, 3].double()
    return LiftedClick(index, frame, (float(u), float(v)), cls, point, source, centre.float())
