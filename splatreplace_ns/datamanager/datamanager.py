"""Full-image datamanager that runs on CPU and carries depth and instance masks."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type

import cv2
import numpy as np
import torch

from nerfstudio.cameras.cameras import Cameras

from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig

from splatreplace_ns.datamanager.click_masks import with_click_masks
from splatreplace_ns.datamanager.dataparser import SplatReplaceDataParser, SplatReplaceDataParserConfig
from splatreplace_ns.datamanager.dataset import SplatReplaceDataset
from splatreplace_ns.datamanager.undistort import captured_to_undistorted_pixel, remap_nearest, undistortion_maps
from splatreplace_ns.datamanager.sampling import sample_contrastive_pixels
from splatreplace_ns.datamanager.clicks import resized_pixel


@dataclass
class SplatReplaceDataManagerConfig(FullImageDatamanagerConfig):
    _target: Type = field(default_factory=lambda: SplatReplaceDataManager)
    dataparser: SplatReplaceDataParserConfig = field(default_factory=SplatReplaceDataParserConfig)
    cache_images_type: Literal["uint8", "float32"] = "uint8"
    contrastive_uniform_samples: int = 4096
    """M_u: pixels sampled uniformly per image for the contrastive stage."""
    contrastive_mask_samples: int = 4096
    """M_s: pixels sampled inside each mask (and the background) per image."""


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
        cameras = (self.train_dataset if split == "train" else self.eval_dataset).cameras
        # nerfstudio undistorts the images in place of these cameras' intrinsics: keep the captured ones
        captured = CapturedCameras(
            cameras.get_intrinsics_matrices().clone(),
            None if cameras.distortion_params is None else cameras.distortion_params.clone(),
            cameras.width.reshape(-1).clone(), cameras.height.reshape(-1).clone(),
        )
        cached = super()._load_images(split, cache_images_device)
        if not hasattr(self, "captured_cameras"):  # nerfstudio may cache images inside its own __init__
            self.captured_cameras: Dict[str, CapturedCameras] = {}
        self.captured_cameras[split] = captured
        self._undistort(cached, cameras, split, ("instance_mask", "depth"))
        return cached

    def _undistort(self, cached: List[Dict], cameras: Cameras, split: str, keys: Tuple[str, ...]) -> None:
        """Warps each cached image's per-pixel ``keys`` (read in the captured geometry) as nerfstudio warped it."""
        for idx, data in enumerate(cached):
            keys_here = [key for key in keys if key in data]
            maps = self._undistortion_maps(split, cameras, idx, data["image"]) if keys_here else None
            if maps is None:
                continue
            for key in keys_here:
                data[key] = remap_nearest(data[key], maps).to(data[key].device)

    def _undistortion_maps(self, split: str, cameras: Cameras, idx: int, image: torch.Tensor):
        """The captured → cached pixel maps of view ``idx`` of ``split`` (``image``: its cached [h, w, 3] image),
        or None when its camera has no distortion."""
        captured = self.captured_cameras[split]
        if captured.distortion is None:
            return None
        size = (int(image.shape[1]), int(image.shape[0]))
        K_after = cameras[idx : idx + 1].get_intrinsics_matrices()[0]
        return undistortion_maps(int(cameras.camera_type[idx].item()), captured.K[idx].numpy(),
                                 captured.distortion[idx].numpy(), K_after.numpy(), size)

    def train_instance_mask(self, index: int) -> torch.Tensor:
        """[H, W] instance mask of training image ``index`` in the geometry it is trained in (undistorted and
        cropped like its image when the camera has distortion; ``train_dataset.get_data`` gives the captured one)."""
        return self.instance_mask_as_rendered(self.train_dataset, index)

    def _split_of(self, dataset) -> Optional[str]:
        return "train" if dataset is self.train_dataset else "eval" if dataset is self.eval_dataset else None

    def _cached(self, split: str) -> List[Dict]:
        return self.cached_train if split == "train" else self.cached_eval

    def instance_mask_as_rendered(self, dataset, index: int) -> torch.Tensor:
        """[H, W] instance mask of view ``index`` of ``dataset`` in the geometry its camera renders: for this
        datamanager's train or eval dataset the cached mask (undistorted and cropped like its image); for any
        other dataset the mask as stored."""
        split = self._split_of(dataset)
        data = self._cached(split)[index] if split else dataset.get_data(index, image_type="uint8")
        if "instance_mask" not in data:
            raise ValueError(f"{dataset.image_filenames[index]}: no instance mask")
        return data["instance_mask"][..., 0]

    def mask_as_rendered(self, dataset, index: int, mask: np.ndarray) -> torch.Tensor:
        """[H, W] instance ids over view ``index``'s captured picture (a reference mask; another size of it is
        resized, nearest) → [h, w] int64 in the geometry its camera renders, as :meth:`instance_mask_as_rendered`
        (only resized for a dataset not of this datamanager or a camera without distortion)."""
        split = self._split_of(dataset)
        cameras = dataset.cameras
        if split is None:
            height, width = int(cameras.height[index]), int(cameras.width[index])
        else:
            self._cached(split)  # nerfstudio caches the eval images when first asked; the captured cameras with them
            captured = self.captured_cameras[split]
            height, width = int(captured.height[index]), int(captured.width[index])
        if mask.shape[:2] != (height, width):
            mask = cv2.resize(mask.astype(np.uint16), (width, height), interpolation=cv2.INTER_NEAREST)
        values = torch.from_numpy(mask.astype(np.int64))
        if split is None:
            return values
        maps = self._undistortion_maps(split, cameras, index, self._cached(split)[index]["image"])
        return values if maps is None else remap_nearest(values[..., None], maps)[..., 0]

    @property
    def image_downscale(self) -> int:
        """The factor nerfstudio's dataparser scaled the images and cameras down by (it reads ``images_<f>/``)."""
        return int(getattr(self.dataparser, "downscale_factor", None) or 1)

    def train_pixel(self, index: int, xy: Tuple[float, float]) -> Tuple[float, float]:
        """A pixel of training image ``index`` as stored (a click of clicks.json) → the same ray's pixel in the
        image as cached: read from ``images_<f>/`` when nerfstudio downscales the images by f, then undistorted
        and cropped when the camera has distortion."""
        _ = self.cached_train  # caching is where nerfstudio undistorts, and where the captured cameras are kept
        if self.image_downscale > 1:
            xy = resized_pixel(xy, 1.0 / self.image_downscale)
        captured = self.captured_cameras["train"]
        if captured.distortion is None or not bool(captured.distortion[index].any()):
            return float(xy[0]), float(xy[1])
        cameras = self.train_dataset.cameras
        return captured_to_undistorted_pixel(
            xy, int(cameras.camera_type[index].item()), captured.K[index].numpy(), captured.distortion[index].numpy(),
            cameras.get_intrinsics_matrices()[index].numpy(),
        )

    def reload_instance_masks(self) -> None:
        """Points the datasets at the masks written beside ``transforms.json`` during this run (after the base
        stage, ``instance_masks/``) and puts them into the images already cached."""
        transforms = self.dataparser.config.data
        transforms = transforms if transforms.suffix == ".json" else transforms / "transforms.json"
        meta = with_click_masks(json.loads(transforms.read_text()), transforms.parent)
        for split, dataset in (("train", self.train_dataset), ("eval", self.eval_dataset)):
            outputs = dataset._dataparser_outputs
            filenames, instances, source = SplatReplaceDataParser.split_masks(meta, transforms.parent, outputs)
            outputs.metadata.update(instance_mask_filenames=filenames, instances=instances, instance_masks_source=source)
            dataset.use_instance_masks(filenames, instances, source)
            cached = self.__dict__.get("cached_train" if split == "train" else "cached_eval")
            if cached is None:  # not cached yet: it reads the masks when it is
                continue
            captured = self.captured_cameras[split]
            for idx, data in enumerate(cached):
                height, width = int(captured.height[idx]), int(captured.width[idx])
                data["instance_mask"] = dataset.read_instance_mask(idx, height, width)
            self._undistort(cached, dataset.cameras, split, ("instance_mask",))

    def next_train(self, step: int) -> Tuple[Cameras, Dict]:
        camera, data = super().next_train(step)
        for key in ("instance_mask", "depth"):
            if key in data:
                data[key] = data[key].to(self.device)
        return camera, data

    @property
    def has_instance_masks(self) -> bool:
        return self.train_dataparser_outputs.metadata.get("instance_mask_filenames") is not None

    def sample_contrastive_pixels(
        self, batch: Dict, generator: Optional[torch.Generator] = None
    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """M_u uniform plus M_s per-mask pixels of one training batch.

        Returns:
            flat pixel indices [P] and their mask labels [P] (0 = background), on the batch's device.
        """
        if "instance_mask" not in batch:
            raise ValueError(
                "the contrastive stage needs instance masks (frames[].instance_mask_path in transforms.json); "
                "ns-train splat-replace makes them from clicks.json after the base stage, `splatreplace masks DATA` "
                "makes them on its own, or set --pipeline.contrastive-iterations 0 to train the base stage only"
            )
        return sample_contrastive_pixels(
            batch["instance_mask"][..., 0],
            self.config.contrastive_uniform_samples,
            self.config.contrastive_mask_samples,
            generator=generator,
        )

    def training_view_cameras(self, width: int, height: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """The training cameras as world→camera (OpenCV) matrices with intrinsics scaled to ``width × height``.

        Returns:
            viewmats [V, 4, 4], Ks [V, 3, 3] (CPU, float32).
        """
        from splatreplace_ns.render.cameras import world_to_camera

        cameras = self.train_dataset.cameras
        viewmats = world_to_camera(cameras.camera_to_worlds.float())
        Ks = cameras.get_intrinsics_matrices().float().clone()
        Ks[:, 0] *= width / cameras.width.float().reshape(-1, 1)
        Ks[:, 1] *= height / cameras.height.float().reshape(-1, 1)
        return viewmats, Ks


@dataclass
class CapturedCameras:
    """Intrinsics of a split's captured images, kept before nerfstudio undistorts them in place."""

    K: torch.Tensor
    """[F, 3, 3]"""
    distortion: Optional[torch.Tensor]
    """[F, 6] nerfstudio distortion parameters, or None."""
    width: torch.Tensor
    """[F]"""
    height: torch.Tensor
    """[F]"""
