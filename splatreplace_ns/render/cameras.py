"""World→camera matrices of nerfstudio camera poses, as the rasteriser takes them.

nerfstudio's own ``splatfacto.get_viewmat`` does the same arithmetic but is wrapped in ``torch.compile``: the
first call on each device (and for a new batch size) compiles it, 9 s on a two-core CPU with an empty compile
cache, and on a GPU machine over two minutes in one training run (a CPU and a CUDA variant, each C++/Triton
builds) — far longer than everything it computes in a whole run.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["world_to_camera"]


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
