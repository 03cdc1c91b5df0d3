"""Write the masks made from clicks beside ``transforms.json`` (``instance_masks/``), never into it: files replaced
atomically, same bytes on a rerun."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Sequence

import cv2
import numpy as np

from splatreplace_ns.datamanager.click_masks import index_path, make_index
from splatreplace_ns.datamanager.files import write_atomically


def encode_mask(mask: np.ndarray) -> bytes:
    """[H, W] uint16 → 16-bit single-channel PNG bytes."""
    if mask.dtype != np.uint16 or mask.ndim != 2:
        raise TypeError(f"instance masks are [H, W] uint16, got {mask.shape} {mask.dtype}")
    ok, buffer = cv2.imencode(".png", mask)
    if not ok:
        raise OSError("could not encode a 16-bit PNG")
    return buffer.tobytes()


def write_dataset_masks(data: Path, masks: Sequence[np.ndarray], instances: List[Dict], clicks_digest: str = "") -> Path:
    """Writes ``instance_masks/NNNN.png`` for every frame of ``transforms.json`` and ``instance_masks/index.json``.

    ``transforms.json`` is read, never written. Each file goes to a temporary name and is renamed, and the index
    last, so a crash leaves the old index (or none) pointing at complete masks, never half of a file.

    Args:
        data: dataset folder holding transforms.json.
        masks: one [H, W] uint16 mask per frame, in ``frames`` order.
        instances: ``[{"id", "class"}, ...]``.
        clicks_digest: fingerprint of the clicks the masks were made from (recorded when given).

    Returns:
        the path of the written index.
    """
    meta = json.loads((Path(data) / "transforms.json").read_text())
    file_paths = [str(f["file_path"]) for f in meta["frames"]]
    if len(file_paths) != len(masks):
        raise ValueError(f"{len(masks)} masks for {len(file_paths)} frames")
    index = make_index(file_paths, instances, clicks_digest)
    path = index_path(data)
    path.parent.mkdir(exist_ok=True)
    for frame, mask in zip(index["frames"], masks):
        write_atomically(Path(data) / frame["instance_mask_path"], encode_mask(mask))
    write_atomically(path, (json.dumps(index, indent=2) + "\n").encode())
    return path
