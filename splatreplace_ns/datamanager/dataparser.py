"""Dataparser for the splatreplace data format (nerfstudio ``transforms.json``, extended).

Adds to nerfstudio's parser, for the frames of the requested split and in the same order:
``instance_mask_filenames`` (16-bit instance masks), the ``instances`` list with ground-truth
object→world poses moved into the dataparser's normalised frame, ``depth_unit_scale_factor``
read from ``transforms.json`` when present there, and ``depth_zero_is_far`` (its optional ``depth_zero``:
``"unknown"`` or ``"far"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Type
from unittest.mock import patch

import numpy as np
import torch

from nerfstudio.data.dataparsers import nerfstudio_dataparser
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.utils.rich_utils import CONSOLE

from splatreplace_ns.datamanager.click_masks import (
    EVALUATION_INSTANCES_KEY,
    EVALUATION_MASK_KEY,
    MASKS_SOURCE_KEY,
    with_click_masks,
)
from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.datamanager.validate import SPLIT_LISTS, check_dataset, with_both_eval_splits

__all__ = ["SPLIT_LISTS", "DatasetFormatError", "SplatReplaceDataParser", "SplatReplaceDataParserConfig",
           "normalise_object_pose", "saved_to_normalised"]


def normalise_object_pose(
    object_to_world: np.ndarray, dataparser_transform: np.ndarray, dataparser_scale: float
) -> np.ndarray:
    """Moves an object→world pose into nerfstudio's normalised world frame.

    Args:
        object_to_world: [4, 4] rigid pose in the dataset's world frame.
        dataparser_transform: [3, 4] the parser's world transform (rotation + translation).
        dataparser_scale: scalar applied to positions after the transform.

    Returns:
        [4, 4] similarity object→normalised-world (rotation block scaled by ``dataparser_scale``).
    """
    transform = np.eye(4)
    transform[:3, :4] = dataparser_transform
    scaled = np.diag([dataparser_scale, dataparser_scale, dataparser_scale, 1.0]) @ transform
    return scaled @ np.asarray(object_to_world, dtype=np.float64)


def applied_transform(meta: Dict, data_dir: Path) -> Optional[np.ndarray]:
    """[3, 4] nerfstudio's ``applied_transform``: from the coordinates of the original data (a COLMAP model) to
    those of the poses as ``transforms.json`` saves them; None when there is none.

    ``ns-process-data`` writes it; without it nerfstudio assumes its older COLMAP convention when the folder holds
    ``colmap/sparse/0`` (the same rule as nerfstudio's own parser).
    """
    if "applied_transform" in meta:
        value = np.asarray(meta["applied_transform"], dtype=np.float64)
        if value.shape != (3, 4) or not np.isfinite(value).all():
            raise DatasetFormatError(f"{data_dir / 'transforms.json'}: 'applied_transform' must be a 3x4 matrix of "
                                     f"numbers, got shape {value.shape}")
        return value
    if (Path(data_dir) / "colmap" / "sparse" / "0").exists():
        return np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]])
    return None


def saved_to_normalised(dataparser_transform: np.ndarray, meta: Dict, data_dir: Path) -> np.ndarray:
    """[4, 4] the rigid transform nerfstudio applied to the poses as ``transforms.json`` saves them (cameras' and
    objects'), before its scale.

    nerfstudio's stored ``dataparser_transform`` maps the *original* data's coordinates: it already holds
    ``applied_transform``, which the saved poses have had applied once. Applying it to them again (what every
    place that rendered from ``transforms.json`` did) puts an ``ns-process-data`` capture's cameras somewhere the
    trained model is not.

    Args:
        dataparser_transform: [3, 4] the parser's ``dataparser_transform``.
        meta: the transforms.json contents; data_dir: its folder.
    """
    transform = np.eye(4)
    transform[:3] = np.asarray(dataparser_transform, dtype=np.float64)
    applied = applied_transform(meta, data_dir)
    if applied is None:
        return transform
    applied4 = np.eye(4)
    applied4[:3] = applied
    return transform @ np.linalg.inv(applied4)


@dataclass
class SplatReplaceDataParserConfig(NerfstudioDataParserConfig):
    """nerfstudio's parser plus instance masks, instances and ground-truth poses."""

    _target: Type = field(default_factory=lambda: SplatReplaceDataParser)
    load_3D_points: bool = True
    """Initialise from the dataset's point cloud (``ply_file_path``) when there is one."""
    train_on_every_frame: bool = False
    """Train on every frame of ``transforms.json``, ignoring its ``train_filenames`` / ``val_filenames`` /
    ``test_filenames`` and ``eval_mode`` (evaluation then sees the same frames). For a model that only serves
    to make every frame's masks (``splatreplace masks``): a frame held out for evaluation would get masks from
    a model that never saw it."""


@dataclass
class SplatReplaceDataParser(Nerfstudio):
    config: SplatReplaceDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train") -> DataparserOutputs:
        transforms_path = self.config.data if self.config.data.suffix == ".json" else self.config.data / "transforms.json"
        if not transforms_path.exists() and self.config.data.suffix != ".json":
            from splatreplace_ns.datamanager.colmap_input import colmap_to_transforms, find_sparse_model

            if find_sparse_model(self.config.data) is not None:  # a COLMAP capture: written once, then reused
                CONSOLE.log(f"{self.config.data}: no transforms.json; writing it from the COLMAP model")
                colmap_to_transforms(self.config.data)
        if not transforms_path.exists():
            raise DatasetFormatError(
                f"{transforms_path}: file not found (expected a nerfstudio transforms.json, or a COLMAP model in "
                "sparse/0)"
            )
        meta = self._checked_meta(transforms_path)
        meta = with_click_masks(meta, transforms_path.parent)  # masks made from clicks live beside the file
        if "depth_unit_scale_factor" in meta:
            self.config.depth_unit_scale_factor = float(meta["depth_unit_scale_factor"])
        if self.config.train_on_every_frame:  # nerfstudio's parser obeys split lists before its eval_mode
            self.config.eval_mode = "all"
            parsed = {key: value for key, value in meta.items() if key not in SPLIT_LISTS}
        else:
            parsed = with_both_eval_splits(meta)
        # nerfstudio's parser reads the file again: hand it the checked contents
        with patch.object(nerfstudio_dataparser, "load_from_json", lambda _path: dict(parsed)):
            outputs = super()._generate_dataparser_outputs(split)
        data_dir = transforms_path.parent

        filenames, instances, source = self.split_masks(meta, data_dir, outputs)
        outputs.metadata.update(instance_mask_filenames=filenames, instances=instances, instance_masks_source=source)
        outputs.metadata["depth_zero_is_far"] = self._depth_zero_is_far(meta)
        return outputs

    def _checked_meta(self, transforms_path: Path) -> Dict:
        """``transforms.json`` checked with its files and ``clicks.json`` (:func:`check_dataset`), once per parser:
        nerfstudio parses each split with the same parser, and decoding every file again would only cost time."""
        cached = getattr(self, "_checked", None)
        if cached is None or cached[0] != transforms_path:
            cached = (transforms_path, check_dataset(transforms_path, transforms_path.parent / "clicks.json"))
            self._checked = cached
        return cached[1]

    @classmethod
    def split_masks(cls, meta: Dict, data_dir: Path, outputs: DataparserOutputs) -> Tuple[Optional[List[Path]], List[Dict], str]:
        """A split's instance masks, the instances they hold and where they come from, from ``meta`` as
        :func:`with_click_masks` gives it: the evaluation masks for a split of evaluation frames when the dataset
        gives them (:mod:`splatreplace_ns.datamanager.click_masks`), else the frames' ``instance_mask_path``.

        Returns:
            (mask file per image or None, the instances, ``"ground_truth"`` or ``"clicks"``).
        """
        by_name = {Path(f["file_path"]).name: data_dir / f[EVALUATION_MASK_KEY]
                   for f in meta.get("frames", []) if EVALUATION_MASK_KEY in f}
        names = [Path(p).name for p in outputs.image_filenames]
        if by_name and names and all(name in by_name for name in names):
            given = dict(meta, instances=meta.get(EVALUATION_INSTANCES_KEY, []))
            return [by_name[name] for name in names], cls._instances(given, outputs, data_dir), "ground_truth"
        return (cls._instance_mask_filenames(meta, data_dir, outputs.image_filenames),
                cls._instances(meta, outputs, data_dir), cls._instance_masks_source(meta))

    @staticmethod
    def _instance_masks_source(meta: Dict) -> str:
        """Where the instance masks come from: ``"ground_truth"`` (default) or ``"clicks"`` (``splatreplace masks``
        or ``ns-train`` made them; evaluation then scores no segmentation against them)."""
        return meta.get(MASKS_SOURCE_KEY, "ground_truth")

    @staticmethod
    def _depth_zero_is_far(meta: Dict) -> bool:
        """What depth 0 means: ``"unknown"`` (default: a sensor's hole, no supervision there) or ``"far"`` (the
        ray hits no surface, e.g. the sky: supervised as infinitely far, inverse depth 0)."""
        return meta.get("depth_zero", "unknown") == "far"

    @staticmethod
    def _instance_mask_filenames(meta: Dict, data_dir: Path, image_filenames: List[Path]) -> Optional[List[Path]]:
        frames = meta.get("frames", [])
        if not any("instance_mask_path" in f for f in frames):  # the schema: every frame has one, or none
            return None
        # nerfstudio may point images at a downscaled folder (images_2/...), so match by file name (unique: the
        # schema's rule)
        by_name = {Path(f["file_path"]).name: data_dir / f["instance_mask_path"] for f in frames}
        return [by_name[Path(p).name] for p in image_filenames]

    @staticmethod
    def _instances(meta: Dict, outputs: DataparserOutputs, data_dir: Path) -> List[Dict]:
        transform = saved_to_normalised(outputs.dataparser_transform.numpy(), meta, data_dir)[:3]
        instances = []
        for inst in meta.get("instances", []):
            entry = {
                "id": int(inst["id"]),
                "class": str(inst.get("class", "object")),
                "symmetry": str(inst.get("symmetry", "none")),
            }
            if "size" in inst:  # bounding-box diagonal in the object's frame (relative translation errors)
                entry["size"] = float(inst["size"])
            if "transform_matrix" in inst:
                entry["transform_matrix"] = torch.from_numpy(
                    normalise_object_pose(np.array(inst["transform_matrix"]), transform, outputs.dataparser_scale)
                ).float()
            instances.append(entry)
        return instances


splatreplace_dataparser = DataParserSpecification(
    config=SplatReplaceDataParserConfig(),
    description="nerfstudio transforms.json with instance masks, instances and ground-truth poses (splatreplace_ns)",
)
