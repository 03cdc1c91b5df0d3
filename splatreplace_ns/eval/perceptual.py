"""LPIPS and KID built only from weights already on disk; otherwise reported as unavailable.

LPIPS needs ImageNet AlexNet weights and KID the InceptionV3 weights of torch-fidelity; no pip package
ships either. torchvision / torch-fidelity would download them on first use, which fails offline and
would be slow online, so we look in the torch hub cache (``torch.hub.get_dir()/checkpoints``, i.e.
``$TORCH_HOME/hub/checkpoints``) first and never fall back to random weights.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Optional, Tuple

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


def inception_weights_path() -> Path:
    """Where torch-fidelity keeps the InceptionV3 weights that KID ('inception-v3-compat') loads."""
    from torch_fidelity.feature_extractor_inceptionv3 import URL_INCEPTION_V3

    return Path(torch.hub.get_dir()) / "checkpoints" / Path(URL_INCEPTION_V3).name


class LocalKID:
    """Kernel Inception Distance between the ground-truth and the rendered images of a set of views.

    KID is a set metric: feed every view with :meth:`update`, then :meth:`compute`. Features are the
    2048-d InceptionV3 pool features (torchmetrics' ``KernelInceptionDistance``, cubic polynomial kernel);
    the subset size is the number of views (at most ``max_subset_size``). ``None`` and a reason when the
    weights are not on disk or fewer than two views were given.
    """

    def __init__(self, subsets: int = 100, max_subset_size: int = 1000) -> None:
        self.subsets = subsets
        self.max_subset_size = max_subset_size
        self._metric = None
        self._checked = False
        self._count = 0
        self.unavailable_reason: Optional[str] = None

    @property
    def available(self) -> bool:
        self._build()
        return self._metric is not None

    def _build(self) -> None:
        if self._checked:
            return
        self._checked = True
        try:
            weights = inception_weights_path()
        except ImportError:
            self.unavailable_reason = "KID unavailable: torch-fidelity is not installed"
            return
        if not weights.exists():
            self.unavailable_reason = f"KID unavailable: InceptionV3 weights not found at {weights}"
            warnings.warn(self.unavailable_reason + " (metric omitted, never computed with random weights)")
            return
        from torchmetrics.image.fid import NoTrainInceptionV3
        from torchmetrics.image.kid import KernelInceptionDistance

        # the weights are passed by path, so nothing is fetched from the network
        inception = NoTrainInceptionV3("inception-v3-compat", ["2048"], feature_extractor_weights_path=str(weights))
        self._metric = KernelInceptionDistance(feature=inception, subsets=self.subsets, subset_size=2)

    @staticmethod
    def _to_uint8(image: torch.Tensor) -> torch.Tensor:
        return (image.clamp(0, 1) * 255).round().to(torch.uint8)

    def update(self, gt: torch.Tensor, pred: torch.Tensor) -> None:
        """Adds one view. gt, pred: [1, 3, H, W] in [0, 1]."""
        self._build()
        if self._metric is None:
            return
        self._metric = self._metric.to(gt.device)
        self._metric.update(self._to_uint8(gt), real=True)
        self._metric.update(self._to_uint8(pred), real=False)
        self._count += 1

    def compute(self) -> Optional[Tuple[float, float]]:
        """(mean, std) of KID over random subsets of the views; None (see ``unavailable_reason``) if not possible."""
        self._build()
        if self._metric is None:
            return None
        if self._count < 2:
            self.unavailable_reason = f"KID unavailable: needs at least 2 views, got {self._count}"
            return None
        self._metric.subset_size = min(self._count, self.max_subset_size)
        mean, std = self._metric.compute()
        return float(mean), float(std)
