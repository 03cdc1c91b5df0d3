"""A tiny two-box scene for the tests of poses judged against the training images: a floor, the template box
(instance 1) and a copy (instance 2) turned about the up axis, rendered from a ring of training views."""

from __future__ import annotations

import math

import numpy as np
import torch

from splatreplace_ns.poses.candidates import yaw_rotation
from splatreplace_ns.poses.virtual_cameras import intrinsics
from splatreplace_ns.render import rasterize
from splatreplace_ns.render.cameras import look_at

W, H = 64, 48
K = torch.tensor(intrinsics(W, H, 60.0), dtype=torch.float32)
BACKGROUND = torch.tensor([0.2, 0.25, 0.3])


def _object(with_handle: bool, seed: int):
    """Gaussians of a box 0.4 × 0.4 × 0.5 m on the floor, centred at the origin, with a red handle on its +x side."""
    g = torch.Generator().manual_seed(seed)
    n = 400
    pts = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([0.4, 0.4, 0.5]) + torch.tensor([0.0, 0.0, 0.25])
    colours = torch.tensor([0.85, 0.8, 0.6]).expand(n, 3).clone()
    colours[pts[:, 1] > 0] = torch.tensor([0.3, 0.5, 0.8])  # two-tone, so that turns are seen in colour too
    if with_handle:
        handle = torch.rand(120, 3, generator=g) * torch.tensor([0.12, 0.3, 0.15]) + torch.tensor([0.2, -0.15, 0.2])
        pts = torch.cat((pts, handle))
        colours = torch.cat((colours, torch.tensor([0.9, 0.1, 0.1]).expand(len(handle), 3)))
    return pts, colours


def _scene(with_handle: bool, yaw_i: float):
    """Background floor + the template instance (id 1) at x=-1 + instance 2 at x=+1 turned by ``yaw_i``."""
    g = torch.Generator().manual_seed(7)
    floor = torch.cat(((torch.rand(1500, 2, generator=g) - 0.5) * 5.0, torch.zeros(1500, 1)), dim=1)
    floor_col = 0.4 + 0.2 * torch.rand(1500, 1, generator=g).expand(1500, 3)
    obj, obj_col = _object(with_handle, 1)
    a = obj + torch.tensor([-1.0, 0.0, 0.0])
    Rz = yaw_rotation(torch.tensor([0.0, 0.0, 1.0]), yaw_i, torch.zeros(3))[:3, :3]
    b = obj @ Rz.T + torch.tensor([1.0, 0.0, 0.0])
    means = torch.cat((floor, a, b))
    colours = torch.cat((floor_col, obj_col, obj_col))
    labels = torch.cat((torch.zeros(len(floor)), torch.ones(len(a)), 2 * torch.ones(len(b)))).long()
    n = len(means)
    scene = {
        "means": means, "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone(),
        "log_scales": torch.full((n, 3), math.log(0.04)), "logit_opacities": torch.full((n,), 4.0),
        "sh": colours[:, None, :],  # degree 0: the "SH" is the colour itself in this test's renderer
    }
    # instance 2 → template (instance 1): undo the turn, then move from x=+1 to x=-1
    T = torch.eye(4)
    T[:3, :3] = Rz.T
    T[:3, 3] = torch.tensor([-1.0, 0.0, 0.0]) - Rz.T @ torch.tensor([1.0, 0.0, 0.0])
    return scene, labels, T


def _views():
    views = []
    for k in range(8):  # a ring around both copies, from above
        ang = 2 * math.pi * k / 8
        eye = np.array([3.2 * math.cos(ang), 3.2 * math.sin(ang), 1.8])
        views.append(torch.tensor(look_at(eye, np.array([0.0, 0.0, 0.25])), dtype=torch.float32))
    return views


def _render_fn(viewmats):
    def render(view, g, extra):
        colours = g["sh"][:, 0]
        out = rasterize(g["means"], g["quats"], torch.exp(g["log_scales"]), torch.sigmoid(g["logit_opacities"]).reshape(-1),
                        torch.cat((colours, extra), dim=-1), viewmats[view], K, W, H, backend="torch")
        rgb = out.image[..., :3] + (1 - out.alpha) * BACKGROUND
        return rgb.clamp(0, 1), out.image[..., 3:]
    return render


def _images(scene, viewmats):
    render = _render_fn(viewmats)
    return [render(v, scene, torch.zeros(len(scene["means"]), 0))[0] for v in range(len(viewmats))]
