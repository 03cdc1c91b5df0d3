"""Write the masks and the new ``transforms.json``: backup kept, files replaced atomically, same bytes on a rerun."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Dict, List, Sequence

import cv2
import numpy as np

from splatreplace_ns.datamanager.files import write_atomically

BACKUP_SUFFIX = ".before-masks"
MASKS_SOURCE_KEY = "instance_masks_source"
"""transforms.json key saying where the instance masks come from: ``"clicks"`` (written here, from one click per
instance and the base model) or ``"ground_truth"`` (the default when absent: a synthetic scene's, or a person's)."""
CLICKS_DIGEST_KEY = "instance_masks_clicks"
"""transforms.json key: the fingerprint (``segment.clicks.clicks_digest``) of the clicks the masks were made from."""


def mask_path(frame_index: int) -> str:
    """``masks/NNNN.png`` for a frame (relative to the dataset folder)."""
    return f"masks/{frame_index:04d}.png"


def encode_mask(mask: np.ndarray) -> bytes:
    """[H, W] uint16 → 16-bit single-channel PNG bytes."""
    if mask.dtype != np.uint16 or mask.ndim != 2:
        raise TypeError(f"instance masks are [H, W] uint16, got {mask.shape} {mask.dtype}")
    ok, buffer = cv2.imencode(".png", mask)
    if not ok:
        raise OSError("could not encode a 16-bit PNG")
    return buffer.tobytes()


def updated_transforms(meta: Dict, mask_paths: Sequence[str], instances: List[Dict], clicks_digest: str = "") -> Dict:
    """``meta`` with ``frames[i].instance_mask_path``, ``instances`` and ``instance_masks_source`` set (other keys and
    their order kept).

    Depends only on ``meta`` without those entries, so a rerun on its own output gives the same JSON.
    """
    out = json.loads(json.dumps(meta))
    if len(out["frames"]) != len(mask_paths):
        raise ValueError(f"{len(mask_paths)} masks for {len(out['frames'])} frames")
    for frame, path in zip(out["frames"], mask_paths):
        frame["instance_mask_path"] = path
    out["instances"] = instances
    out[MASKS_SOURCE_KEY] = "clicks"  # ns-eval must not score a segmentation against masks made from it
    out.pop(CLICKS_DIGEST_KEY, None)
    if clicks_digest:  # which clicks made them: ns-train remakes them when clicks.json has changed since
        out[CLICKS_DIGEST_KEY] = clicks_digest
    return out


def write_dataset_masks(data: Path, masks: Sequence[np.ndarray], instances: List[Dict], clicks_digest: str = "") -> Path:
    """Writes ``masks/NNNN.png`` for every frame and points ``transforms.json`` at them.

    The first run keeps the original as ``transforms.json.before-masks``; each file is written to a
    temporary name and renamed, so a crash leaves either the old or the new file, never half of one.

    Args:
        data: dataset folder holding transforms.json.
        masks: one [H, W] uint16 mask per frame, in ``frames`` order.
        instances: ``[{"id", "class"}, ...]``.
        clicks_digest: fingerprint of the clicks the masks were made from (recorded when given).

    Returns:
        the path of the written transforms.json.
    """
    transforms = Path(data) / "transforms.json"
    raw = transforms.read_bytes()
    meta = json.loads(raw)
    paths = [mask_path(i) for i in range(len(meta["frames"]))]
    new_meta = updated_transforms(meta, paths, instances, clicks_digest)
    backup = transforms.with_name(transforms.name + BACKUP_SUFFIX)
    if not backup.exists():
        shutil.copy2(transforms, backup)
    (Path(data) / "masks").mkdir(exist_ok=True)
    for path, mask in zip(paths, masks):
        write_atomically(Path(data) / path, encode_mask(mask))
    write_atomically(transforms, (json.dumps(new_meta, indent=2) + "\n").encode())
    return transforms
