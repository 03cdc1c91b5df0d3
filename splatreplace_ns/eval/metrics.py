"""Image metrics on full images and inside masks: one PSNR and one SSIM definition for everything we report.

PSNR = ``10 · log10(1 / MSE)`` with data range 1, the MSE taken over all pixels and channels (or over the
masked pixels). A zero MSE is floored at ``MSE_FLOOR`` so that identical images give a finite
``MAX_PSNR`` (100 dB) instead of infinity, which JSON cannot hold.

SSIM is the standard Gaussian-window SSIM of Wang et al. (2004): 11×11 window, σ = 1.5, K1 = 0.01,
K2 = 0.03, data range 1, population (not sample) covariances, computed per channel and averaged over the
channels. The image score is the mean of the SSIM map over the pixels whose whole window lies inside
the image (a 5-pixel border is left out). This is exactly
``skimage.metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
data_range=1, channel_axis=-1)`` and what ``pytorch_msssim.SSIM`` (splatfacto's ``ssim``) computes.
torchmetrics' ``StructuralSimilarityIndexMeasure`` (nerfstudio's NeRF models) differs slightly: it mirrors
the image at the borders and averages the map over every pixel, border included.
Masked SSIM = mean of the same map over the masked pixels of that interior, so an all-true mask gives
the full-image SSIM.

Masked metrics return ``None`` ("not available") when the mask selects no pixel (no pixel of the
interior, for SSIM) — never NaN.
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Tuple

import torch
import torch.nn.functional as F

MSE_FLOOR = 1e-10
"""Smallest MSE used by :func:`psnr`, so identical images give ``MAX_PSNR``."""
MAX_PSNR = -10.0 * math.log10(MSE_FLOOR)
"""PSNR of identical images (dB)."""

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _as_hwc(image: torch.Tensor, name: str) -> torch.Tensor:
    """(H, W, 3) or (1, 3, H, W) → (H, W, 3) float64."""
    if image.dim() == 4:
        if image.shape[0] != 1:
            raise ValueError(f"{name}: expected one image (1, C, H, W), got a batch of shape {tuple(image.shape)}")
        image = image[0].permute(1, 2, 0)
    if image.dim() != 3:
        raise ValueError(f"{name}: expected (H, W, C) or (1, C, H, W), got shape {tuple(image.shape)}")
    return image.double()


def _as_hw_mask(mask: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """(H, W), (H, W, 1) or (1, 1, H, W) → (H, W) bool, checked against the image size."""
    H, W = int(shape[0]), int(shape[1])
    if tuple(mask.shape) not in ((H, W), (H, W, 1), (1, H, W), (1, 1, H, W)):
        raise ValueError(f"mask of shape {tuple(mask.shape)} does not match the image size {H}x{W} (HxW)")
    return mask.reshape(H, W).bool()


def _check_pair(pred: torch.Tensor, gt: torch.Tensor) -> None:
    if pred.shape != gt.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ in shape")


def mse_to_psnr(mse: float) -> float:
    """PSNR (dB, data range 1) of a mean squared error, floored at ``MSE_FLOOR``."""
    return -10.0 * math.log10(max(float(mse), MSE_FLOOR))


def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None) -> Optional[float]:
    """PSNR of ``pred`` against ``gt`` (data range 1), optionally only over the masked pixels.

    Args:
        pred, gt: (H, W, C) or (1, C, H, W), values in [0, 1].
        mask: optional (H, W), (H, W, 1) or (1, 1, H, W) bool; the MSE is taken over these pixels
            (all channels).

    Returns:
        PSNR in dB (at most ``MAX_PSNR``); ``None`` when the mask is empty.
    """
    pred, gt = _as_hwc(pred, "pred"), _as_hwc(gt, "gt")
    _check_pair(pred, gt)
    squared = (pred - gt) ** 2
    if mask is not None:
        keep = _as_hw_mask(mask.to(pred.device), pred.shape)
        if not bool(keep.any()):
            return None
        squared = squared[keep]
    return mse_to_psnr(float(squared.mean()))


def squared_error_by_label(pred: torch.Tensor, gt: torch.Tensor, labels: torch.Tensor) -> Dict[int, Tuple[float, int]]:
    """Sum of squared error and pixel count per label, to pool over views (per-instance PSNR).

    Args:
        pred, gt: (H, W, C) in [0, 1]; labels: (H, W) integer (0 = background, k = instance k).

    Returns:
        {label: (sum over its pixels of the channel-mean squared error, number of pixels)}; the pooled
        PSNR of a label is ``mse_to_psnr(sum / count)``, which for one view equals ``psnr(pred, gt, labels == k)``.
    """
    pred, gt = _as_hwc(pred, "pred"), _as_hwc(gt, "gt")
    _check_pair(pred, gt)
    labels = labels.reshape(pred.shape[:2]).to(pred.device).long()
    per_pixel = ((pred - gt) ** 2).mean(-1).double()
    ids, inverse = torch.unique(labels, return_inverse=True)
    sums = torch.zeros(len(ids), dtype=torch.float64, device=pred.device).index_add_(0, inverse.reshape(-1), per_pixel.reshape(-1))
    counts = torch.bincount(inverse.reshape(-1), minlength=len(ids))
    return {int(i): (float(sse), int(n)) for i, sse, n in zip(ids.tolist(), sums.tolist(), counts.tolist())}


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """Normalised 1D Gaussian taps, (size,) float64, centred on the middle tap."""
    offsets = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    taps = torch.exp(-(offsets**2) / (2.0 * sigma**2))
    return taps / taps.sum()


def ssim_map(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (mean over channels) on the interior where the window fits.

    Args:
        pred, gt: (H, W, C) or (1, C, H, W), values in [0, 1]; H, W ≥ 11.

    Returns:
        (H − 10, W − 10) float64: entry (i, j) is the SSIM of the window centred on pixel (i + 5, j + 5).
    """
    pred, gt = _as_hwc(pred, "pred"), _as_hwc(gt, "gt")
    _check_pair(pred, gt)
    H, W, C = pred.shape
    if min(H, W) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {W}x{H}")
    taps = gaussian_window().to(pred.device)
    x = pred.permute(2, 0, 1)[:, None]  # (C, 1, H, W): channels filtered independently
    y = gt.permute(2, 0, 1)[:, None]

    def blur(t: torch.Tensor) -> torch.Tensor:  # separable valid convolution
        t = F.conv2d(t, taps.view(1, 1, -1, 1))
        return F.conv2d(t, taps.view(1, 1, 1, -1))

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2  # data range 1
    per_channel = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return per_channel[:, 0].mean(dim=0)


def ssim(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None) -> Optional[float]:
    """SSIM (module docstring definition) of ``pred`` against ``gt``, optionally inside a mask.

    Args:
        pred, gt: (H, W, C) or (1, C, H, W), values in [0, 1]; H, W ≥ 11.
        mask: optional (H, W), (H, W, 1) or (1, 1, H, W) bool; the SSIM map is averaged over the masked
            pixels at least 5 pixels from the border.

    Returns:
        SSIM in [-1, 1]; ``None`` when no masked pixel lies in that interior.
    """
    values = ssim_map(pred, gt)
    if mask is None:
        return float(values.mean())
    shape = _as_hwc(pred, "pred").shape
    keep = _as_hw_mask(mask.to(values.device), shape)
    half = SSIM_WINDOW // 2
    keep = keep[half : shape[0] - half, half : shape[1] - half]
    if not bool(keep.any()):
        return None
    return float(values[keep].mean())
