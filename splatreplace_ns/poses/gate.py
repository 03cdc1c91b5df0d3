"""The check of a registered pose before replacement (``--pipeline.gate.enabled``, off by default).

Registration scores a pose by how well Gaussians overlap (inliers, ICP fitness); nothing in it looks at what
the capture saw. Here each registered instance ``i`` is checked by analysis by synthesis: the class's template
instance ``a`` (its Gaussians, as the base stage trained them) is placed at ``i`` under the registered pose,
the scene is rendered with ``i``'s own Gaussians swapped for that copy, and the render is compared with the
training images on ``i``'s pixels. The same is done for the pose turned about the up axis through the
instance (``turns`` evenly spaced yaw angles). The instance is replaced only when

* the registered pose explains its pixels nearly as well as ``i``'s own Gaussians do
  (``psnr_pose ≥ psnr_own − margin_own_db``): a pose that breaks the instance's look is refused, and
* no turned pose explains them clearly better (``psnr_pose ≥ best turned − margin_turn_db``): a copy whose
  one-sided detail (a drawer, a lamp's arm) lands on the wrong side is refused, or, with ``adopt_turns``,
  replaced under the better turn when that one passes the first test. Each turned pose is placed by
  an upright ICP onto the instance's own Gaussians, so it is judged at its best. Turns that look alike (a
  symmetric class) tie and refuse nothing.

Both scores use a per-channel gain fitted on the compared pixels, the role the per-copy colour offsets play in
fine-tuning: a copy lit differently from the template is not refused for its lighting.

An instance that is refused stays as it was (its own Gaussians, not replaced). The template instance of each
class is not checked (it is the reference the others are placed from).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from splatreplace_ns.poses.evidence import RenderFn, explain_scores, instance_id_maps, instance_views, subset


@dataclass
class ReplacementGateConfig:
    """Settings of :func:`gate_registrations`."""

    enabled: bool = False
    """Check every registered pose against the training images before the instance is replaced (off by default:
    on the dev split it has not paid yet, see docs/deviations.md)."""
    margin_own_db: float = 6.0
    """dB: the template copy under the registered pose may explain the instance's training pixels this much
    worse than its own Gaussians (which were fitted to exactly those pixels) before the instance is refused."""
    margin_turn_db: float = 0.5
    """dB: a turned pose must explain the pixels this much better than the registered one to refuse it."""
    turns: int = 8
    """Yaw angles tried about the up axis through the instance (evenly spaced, the registered pose included)."""
    max_views: int = 6
    """Training views compared per instance (those where it covers most pixels)."""
    min_pixels: int = 16
    """A view counts only where the instance covers at least this many pixels."""
    adopt_turns: bool = False
    """When a turned pose explains the pixels clearly better and passes the own margin, replace the instance
    under that pose instead of leaving it as it is."""
    icp_distance: float = 0.1
    """ICP correspondence distance that places each turned pose, as a fraction of the template's radius."""

    def __post_init__(self) -> None:
        if self.turns < 1 or self.max_views < 1:
            raise ValueError("ReplacementGateConfig: turns and max_views must be >= 1")
        if self.margin_own_db < 0 or self.margin_turn_db < 0:
            raise ValueError("ReplacementGateConfig: margins are in dB and must be >= 0")


@dataclass
class GateScore:
    """How well instance ``instance_id``'s training pixels are explained (PSNR, dB, after the colour fit)."""

    instance_id: int
    template_id: int
    psnr_own: Optional[float]
    """By the instance's own Gaussians (the scene as it is)."""
    psnr_pose: Optional[float]
    """By the template copy under the registered pose."""
    psnr_best_turn: Optional[float]
    """By the template copy under the best of the other turns (None with ``turns=1``)."""
    best_turn_deg: Optional[float]
    views: int
    pixels: int
    passed: bool
    reason: str
    transform: Optional[List[List[float]]] = None
    """With a turned pose adopted: the new [4, 4] instance → template transform (template ≈ T · instance)."""

    def as_dict(self) -> Dict:
        return asdict(self)


def yaw_rotation(axis: Tensor, angle: float, centre: Tensor) -> Tensor:
    """[4, 4] rotation by ``angle`` (radians, right-handed) about the line through ``centre`` [3] along ``axis`` [3]."""
    x, y, z = (axis / axis.norm().clamp_min(1e-12)).tolist()
    K = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=axis.dtype)
    R = torch.eye(3, dtype=axis.dtype) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)
    T = torch.eye(4, dtype=axis.dtype)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre
    return T


def turned_pose(pose: Tensor, template_means: Tensor, instance_means: Tensor, up: Tensor, angle: float,
                relative_distance: float) -> Tensor:
    """The pose turned by ``angle`` about ``up`` through the placed copy's centre, then fitted to the instance's
    own Gaussians by upright ICP (a turn and a translation), so that a turn is judged at its best placement.

    Args:
        pose: [4, 4] template → instance (world); template_means [N, 3]; instance_means [M, 3]; up [3].
        relative_distance: ICP correspondence distance as a fraction of the template's radius.
    Returns:
        [4, 4] pose.
    """
    from splatreplace_ns.poses.icp import refine_icp_upright

    placed = template_means @ pose[:3, :3].T.to(template_means) + pose[:3, 3].to(template_means)
    centre = placed.mean(0).cpu().float()
    start = yaw_rotation(up.float(), angle, centre) @ pose.float()
    if len(instance_means) < 10 or len(template_means) < 10:
        return start
    radius = float((template_means - template_means.mean(0)).norm(dim=-1).max())
    fitted, _ = refine_icp_upright(template_means.cpu().double().numpy(), instance_means.cpu().double().numpy(),
                                   start.double().numpy(), up.cpu().double().numpy(),
                                   max_distance=max(relative_distance * radius, 1e-6))
    return torch.as_tensor(fitted, dtype=torch.float32)


def judge(psnr_own: Optional[float], psnr_pose: Optional[float], psnr_best_turn: Optional[float],
          cfg: ReplacementGateConfig) -> Tuple[bool, str]:
    """The gate's verdict from the three scores (None: not seen in any training view)."""
    if psnr_own is None or psnr_pose is None:
        return True, "not seen well in any training view: nothing to check against, replaced"
    better_turn = psnr_best_turn is not None and psnr_best_turn > psnr_pose + cfg.margin_turn_db
    if better_turn and cfg.adopt_turns and psnr_best_turn >= psnr_own - cfg.margin_own_db:
        return True, (f"a turned pose explains its training pixels {psnr_best_turn - psnr_pose:.1f} dB better "
                      f"(margin {cfg.margin_turn_db:g} dB): replaced under that pose")
    if psnr_pose < psnr_own - cfg.margin_own_db:
        return False, (f"the template under this pose explains its training pixels {psnr_own - psnr_pose:.1f} dB worse "
                       f"than the instance itself (margin {cfg.margin_own_db:g} dB)")
    if better_turn:
        return False, (f"a turned pose explains its training pixels {psnr_best_turn - psnr_pose:.1f} dB better "
                       f"(margin {cfg.margin_turn_db:g} dB): the registered turn is ambiguous or wrong")
    return True, "the registered pose explains its training pixels"


def gate_registrations(
    scene: Mapping[str, Tensor],
    labels: Tensor,
    classes: Mapping[int, str],
    transforms: Mapping[int, Tensor],
    templates: Mapping[str, int],
    images: Sequence[Tensor],
    render: RenderFn,
    up: Sequence[float],
    cfg: ReplacementGateConfig,
) -> Dict[int, GateScore]:
    """Checks every registered instance's pose against the training images (see the module docstring).

    Args:
        scene: the segmented scene's Gaussians (N): means [N, 3], quats [N, 4], log_scales [N, 3],
            logit_opacities [N] or [N, 1], sh [N, K, 3].
        labels: [N] long instance id per Gaussian (0 = background).
        classes: {instance id: class name}.
        transforms: {instance id: [4, 4] rigid, template ≈ T · instance (world)} of the registered instances.
        templates: {class name: template instance id}.
        images: training images, [H, W, 3] float in [0, 1] (or uint8), indexed like ``render``'s views.
        render: see :data:`RenderFn`.
        up: the scene's up direction (world).
        cfg: margins and budget.
    Returns:
        {instance id: GateScore} for every checked instance (the templates themselves are not checked).
    """
    checked = [i for i in sorted(transforms) if i in classes and templates.get(classes[i]) != i]
    if not checked:
        return {}
    labels = labels.to(scene["means"].device)
    rgb_before, id_maps = instance_id_maps(scene, labels, range(len(images)), render)
    up_t = torch.as_tensor(up, dtype=torch.float32)
    out: Dict[int, GateScore] = {}
    for i in checked:
        anchor = int(templates[classes[i]])
        views = instance_views(id_maps, i, cfg.max_views, cfg.min_pixels)
        if not views:
            passed, reason = judge(None, None, None, cfg)
            out[i] = GateScore(i, anchor, None, None, None, None, 0, 0, passed, reason)
            continue
        template = subset(scene, labels == anchor)
        pose = torch.linalg.inv(torch.as_tensor(transforms[i], dtype=torch.float32))  # template → instance i
        poses = [pose] + [
            turned_pose(pose, template["means"], scene["means"][labels == i], up_t, 2 * math.pi * k / cfg.turns,
                        cfg.icp_distance)
            for k in range(1, cfg.turns)
        ]
        own, scores, pixels = explain_scores(scene, labels, i, anchor, poses, images, render, views, id_maps, rgb_before)
        best_k = max(range(1, len(scores)), key=lambda k: scores[k], default=None)
        best_turn = None if best_k is None else scores[best_k]
        passed, reason = judge(own, scores[0], best_turn, cfg)
        adopted = None
        if passed and best_turn is not None and best_turn > scores[0] + cfg.margin_turn_db:
            adopted = torch.linalg.inv(poses[best_k]).tolist()
        out[i] = GateScore(i, anchor, own, scores[0], best_turn,
                           None if best_k is None else 360.0 * best_k / cfg.turns, len(views), pixels,
                           passed, reason, adopted)
    return out
