"""Camera matrices: world→camera of nerfstudio camera poses, as the rasteriser takes them, and look-at poses.

nerfstudio's own ``splatfacto.get_viewmat`` does the same arithmetic but is wrapped in ``torch.compile``: the
first call on each device (and for a new batch size) compiles it, 9 s on a two-core CPU with an empty compile
cache, and on a GPU machine over two minutes in one training run (a CPU and a CUDA variant, each C++/Triton
builds) — far longer than everything it computes in a whole run.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["OPENCV_TO_OPENGL", "WORLD_UP", "look_at", "world_to_camera"]


def world_to_camera(camera_to_worlds: Tensor) -> Tensor:
    """OpenCV world→camera matrices of nerfstudio camera→world poses.

    nerfstudio's poses are OpenGL-style (y up, the camera looks along −z); the rasteriser uses OpenCV's
    (y down, looking along +z), so the y and z axes flip before the rigid inverse.

    Args:
        camera_to_worlds: [B, 3, 4] (or [B, 4, 4]) camera→world poses.
    Returns:
        [B, 4, 4] world→camera matrices, same dtype and device.
    """
    if camera_to_worlds.dim() != 3 or camera_to_worlds.shape[1] not in (3, 4) or camera_to_worlds.shape[2] != 4:
        raise ValueError(f"camera_to_worlds must be [B, 3, 4] or [B, 4, 4], got {tuple(camera_to_worlds.shape)}")
    flip = torch.tensor([1.0, -1.0, -1.0], device=camera_to_worlds.device, dtype=camera_to_worlds.dtype)
    rotation = camera_to_worlds[:, :3, :3] * flip  # scales the columns: the camera's y and z axes turn round
    rotation_inv = rotation.transpose(1, 2)
    out = torch.zeros(camera_to_worlds.shape[0], 4, 4, device=camera_to_worlds.device, dtype=camera_to_worlds.dtype)
    out[:, :3, :3] = rotation_inv
    out[:, :3, 3:4] = -rotation_inv @ camera_to_worlds[:, :3, 3:4]
    out[:, 3, 3] = 1.0
    return out


WORLD_UP = np.array([0.0, 0.0, 1.0])


# OpenCV camera axes (x right, y down, z forward) → OpenGL (x right, y up, z back), nerfstudio's convention.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
    """World→camera (OpenCV) matrix of a camera at ``eye`` looking at ``target``.

    Image "up" (−y) follows ``up`` projected on the image plane. When the viewing direction is (anti)
    parallel to ``up`` (a pole), the world x axis is used as the reference instead, so the result is always
    a proper rotation.

    Args:
        eye: (3,) camera centre.
        target: (3,) point the optical axis passes through (eye != target).
        up: (3,) world up vector.
    Returns:
        (4, 4) float64 world→camera matrix.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    norm = np.linalg.norm(forward)
    if norm < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward /= norm
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6 * np.linalg.norm(up):  # looking straight up/down: pick another up
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]) if abs(forward[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w_rot = np.stack([right, down, forward], axis=1)  # columns: camera axes in world
    viewmat = np.eye(4)
    viewmat[:3, :3] = c2w_rot.T
    viewmat[:3, 3] = -c2w_rot.T @ eye
    return viewmat
