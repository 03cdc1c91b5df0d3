"""Full-image datamanager that runs on CPU and carries depth and instance masks."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Literal, Type

import torch

from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig

from splatreplace_ns.datamanager.dataparser import SplatReplaceDataParserConfig
from splatreplace_ns.datamanager.dataset import SplatReplaceDataset


@dataclass
class SplatReplaceDataManagerConfig(FullImageDatamanagerConfig):
    _target: Type = field(default_factory=lambda: SplatReplaceDataManager)
    dataparser: SplatReplaceDataParserConfig = field(default_factory=SplatReplaceDataParserConfig)
    cache_images_type: Literal["uint8", "float32"] = "uint8"


class SplatReplaceDataManager(FullImageDatamanager[SplatReplaceDataset]):
    """FullImageDatamanager that works without CUDA.

    nerfstudio pins cached images with ``pin_memory()`` when ``cache_images="cpu"``, which needs a
    CUDA driver; without one we cache on the model's device instead (the CPU).
    """

    config: SplatReplaceDataManagerConfig

    def _load_images(
        self, split: Literal["train", "eval"], cache_images_device: Literal["cpu", "gpu"]
    ) -> List[Dict[str, torch.Tensor]]:
        if cache_images_device == "cpu" and not torch.cuda.is_available():
            cache_images_device = "gpu"  # "gpu" means "the model's device", which is the CPU here
        return super()._load_images(split, cache_images_device)
