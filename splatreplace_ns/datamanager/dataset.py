"""Dataset returning the image plus, when the frame carries them, z-depth and the instance mask."""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List

import cv2
import numpy as np
import torch

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.utils.data_utils import get_depth_image_from_path

from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.datamanager.file_checks import mask_size_problem


def read_instance_mask(path: Path, height: int, width: int, valid_ids: set | None = None) -> torch.Tensor:
    """Reads a 16-bit instance mask (0 = background, k > 0 = instance id).

    Returns:
        [H, W, 1] int32 tensor.
    """
    if not Path(path).exists():
        raise DatasetFormatError(f"{path}: instance mask file not found")
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise DatasetFormatError(f"{path}: not a readable image")
    if mask.ndim == 3:
        raise DatasetFormatError(f"{path}: instance masks must be single-channel (16-bit PNG), got {mask.shape[2]} channels")
    if mask.shape != (height, width):
        problem = mask_size_problem((mask.shape[1], mask.shape[0]), (width, height))
        if problem:
            raise DatasetFormatError(f"{path}: {problem}")
        # the image is read at another scale (nerfstudio's images_<f>/, or masks made at such a scale): labels
        # take the nearest pixel, never a blend of two ids
        mask = cv2.resize(mask, (width, height), interpolation=cv2.INTER_NEAREST)
    if valid_ids is not None:
        unknown = sorted(set(np.unique(mask).tolist()) - {0} - valid_ids)
        if unknown:
            raise DatasetFormatError(
                f"{path}: ids {unknown[:10]} are not listed in transforms.json 'instances' (listed: {sorted(valid_ids)})"
            )
    return torch.from_numpy(mask.astype(np.int32))[..., None]


class SplatReplaceDataset(InputDataset):
    """InputDataset with ``depth`` ([H, W, 1] metres in the normalised frame; 0 = unknown, or +inf where the
    dataset says depth 0 means no surface) and ``instance_mask``."""

    exclude_batch_keys_from_device = InputDataset.exclude_batch_keys_from_device + ["instance_mask", "depth"]

    def __init__(self, dataparser_outputs: DataparserOutputs, scale_factor: float = 1.0):
        super().__init__(dataparser_outputs, scale_factor)
        self.depth_filenames = self.metadata.get("depth_filenames")
        self.depth_unit_scale_factor = self.metadata.get("depth_unit_scale_factor", 1e-3)
        self.depth_zero_is_far = bool(self.metadata.get("depth_zero_is_far", False))
        self.instance_mask_filenames = self.metadata.get("instance_mask_filenames")
        self.instance_masks_source = self.metadata.get("instance_masks_source", "ground_truth")
        instances = self.metadata.get("instances") or []
        self.instance_ids = {int(inst["id"]) for inst in instances} if instances else None

    def get_metadata(self, data: Dict) -> Dict:
        idx = data["image_idx"]
        height, width = data["image"].shape[:2]
        out: Dict[str, torch.Tensor] = {}
        if self.depth_filenames is not None:
            path = Path(self.depth_filenames[idx])
            if not path.exists():
                raise DatasetFormatError(f"{path}: depth file not found")
            scale = self.depth_unit_scale_factor * self._dataparser_outputs.dataparser_scale
            depth = get_depth_image_from_path(filepath=path, height=height, width=width, scale_factor=scale)
            if self.depth_zero_is_far:  # no surface (sky): infinitely far, so its inverse depth is supervised as 0
                depth = torch.where(depth > 0, depth, torch.full_like(depth, float("inf")))
            out["depth"] = depth
        if self.instance_mask_filenames is not None:
            out["instance_mask"] = self.read_instance_mask(idx, height, width)
        return out

    def read_instance_mask(self, idx: int, height: int, width: int) -> torch.Tensor:
        """[H, W, 1] int32 instance mask of image ``idx``, checked against its size and the listed ids."""
        return read_instance_mask(Path(self.instance_mask_filenames[idx]), height, width, self.instance_ids)

    def use_instance_masks(self, filenames: List[Path], instances: List[Dict], source: str = "clicks") -> None:
        """Masks written after this dataset was made (``ns-train`` making them from the clicks)."""
        self.metadata.update(instance_mask_filenames=filenames, instances=instances, instance_masks_source=source)
        self.instance_mask_filenames = filenames
        self.instance_masks_source = source
        self.instance_ids = {int(inst["id"]) for inst in instances} if instances else None
