"""A viewer click ray as a tiny pinhole camera, so the renderer can say what lies along it."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from nerfstudio.cameras.cameras import Cameras, CameraType

from splatreplace_ns.render.cameras import OPENCV_TO_OPENGL, look_at


def ray_camera(origin: Sequence[float], direction: Sequence[float], focal: float, size: int = 33) -> Cameras:
    """A ``size`` × ``size`` pinhole camera at ``origin`` whose centre pixel ``(size // 2, size // 2)`` is
    centred on the ray; its depth there is the distance along the (unit) ray direction.

    Args:
        origin: [3] ray origin (world, the viewer camera's centre).
        direction: [3] ray direction (world; normalised here).
        focal: focal length in pixels (use the training cameras' so Gaussians blend as in training).
        size: odd image size.
    Returns:
        one-camera ``Cameras`` (OpenGL camera→world), CPU.
    """
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    norm = float(np.linalg.norm(direction))
    if not np.isfinite(norm) or norm < 1e-12 or not np.isfinite(origin).all():
        raise ValueError(f"not a ray: origin {origin.tolist()}, direction {direction.tolist()}")
    viewmat = look_at(origin, origin + direction / norm)  # world→camera, OpenCV
    c2w = torch.from_numpy(np.linalg.inv(viewmat) @ OPENCV_TO_OPENGL).float()[:3]
    centre = size // 2
    return Cameras(
        camera_to_worlds=c2w[None], fx=focal, fy=focal, cx=centre + 0.5, cy=centre + 0.5, width=size, height=size,
        camera_type=CameraType.PERSPECTIVE,
    )
