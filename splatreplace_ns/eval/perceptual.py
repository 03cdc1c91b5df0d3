"""LPIPS built only from weights already on disk; otherwise reported as unavailable.

LPIPS needs ImageNet AlexNet weights that no pip package ships. torchvision would download them
on first use, which fails offline and would be slow online, so we look in the torch hub cache
first and never fall back to random weights.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Optional

import torch


def alexnet_weights_path() -> Path:
    """Where torchvision keeps the AlexNet weights that LPIPS ('alex') loads."""
    from torchvision.models import AlexNet_Weights

    return Path(torch.hub.get_dir()) / "checkpoints" / Path(AlexNet_Weights.IMAGENET1K_V1.url).name


class LocalLPIPS:
    """LPIPS on [1, 3, H, W] images in [0, 1]; ``None`` when the weights are not on disk."""

    def __init__(self) -> None:
        self._metric = None
        self._checked = False
        self.unavailable_reason: Optional[str] = None

    @property
    def available(self) -> bool:
        self._build()
        return self._metric is not None

    def _build(self) -> None:
        if self._checked:
            return
        self._checked = True
        weights = alexnet_weights_path()
        if not weights.exists():
            self.unavailable_reason = f"LPIPS unavailable: AlexNet weights not found at {weights}"
            warnings.warn(self.unavailable_reason + " (metric omitted, never computed with random weights)")
            return
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        self._metric = LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True)

    def __call__(self, img_a: torch.Tensor, img_b: torch.Tensor) -> Optional[float]:
        self._build()
        if self._metric is None:
            return None
        self._metric = self._metric.to(img_a.device)
        return float(self._metric(img_a.clamp(0, 1), img_b.clamp(0, 1)))
