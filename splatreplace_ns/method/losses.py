"""The 3DGS* base-stage terms (paper §4.1, §5.2) beside splatfacto's: L1 on opacity and scale, per-image affine
exposure, inverse-depth L1, and the nearest-neighbour downscale of a target to the rendered size."""

from __future__ import annotations

from typing import Tuple

import torch


def base_regularisers(opacities: torch.Tensor, scales: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """L1 terms of paper Eq. 1 on the activated parameters.

    Args:
        opacities: [N, 1] opacity logits.
        scales: [N, 3] log-scales.

    Returns:
        (mean sigmoid opacity, mean exp scale), two scalars.
    """
    return torch.sigmoid(opacities).mean(), torch.exp(scales).mean()


def apply_exposure(rgb: torch.Tensor, affine: torch.Tensor) -> torch.Tensor:
    """Per-image affine colour correction ``rgb' = A[:, :3] rgb + A[:, 3]``.

    Args:
        rgb: [H, W, 3] rendered colour.
        affine: [3, 4] exposure matrix (identity = no change).
    """
    return rgb @ affine[:, :3].T + affine[:, 3]


def inverse_depth_l1(pred: torch.Tensor, target: torch.Tensor, min_depth: float = 1e-3) -> torch.Tensor:
    """Mean L1 between inverse depths where the target is valid (> 0).

    Args:
        pred: [H, W, 1] expected depth.
        target: [H, W, 1] ground-truth z-depth, 0 where unknown, +inf where there is no surface (the sky:
            inverse depth 0, which keeps 3DGS from hanging the sky as a wall just behind the scene).
    """
    valid = target > min_depth
    if not bool(valid.any()):
        return pred.sum() * 0.0
    inv_pred = 1.0 / pred.clamp_min(min_depth)
    inv_target = 1.0 / target.clamp_min(min_depth)
    return (inv_pred - inv_target).abs()[valid].mean()


def nearest_downscale(image: torch.Tensor, factor: int, height: int, width: int) -> torch.Tensor:
    """Nearest-neighbour downscale of an [H, W, C] map (keeps invalid depth as 0, unlike averaging)."""
    if factor == 1:
        return image
    return image[factor // 2 :: factor, factor // 2 :: factor][:height, :width]
