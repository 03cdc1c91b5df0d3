"""Turn a synthetic scene into what a person's capture looks like: images and cameras only.

Used by the tests and the benchmark; the ground truth is kept beside it for scoring.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

GROUND_TRUTH_FRAME_KEYS = ("instance_mask_path", "depth_file_path")
GROUND_TRUTH_KEYS = ("instances", "sim", "depth_unit_scale_factor")


def strip_ground_truth(scene: Path, out: Path) -> Path:
    """Copies a sim scene's images, cameras, point cloud and clicks; drops masks, depth and instances.

    Args:
        scene: a ``splatreplace sim`` folder.
        out: the capture-like copy (replaced if it exists).

    Returns:
        ``out / "transforms.json"``.
    """
    scene, out = Path(scene), Path(out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    shutil.copytree(scene / "images", out / "images")
    meta = json.loads((scene / "transforms.json").read_text())
    for key in GROUND_TRUTH_KEYS:
        meta.pop(key, None)
    for frame in meta["frames"]:
        for key in GROUND_TRUTH_FRAME_KEYS:
            frame.pop(key, None)
    if "ply_file_path" in meta:
        shutil.copy2(scene / meta["ply_file_path"], out / meta["ply_file_path"])
    clicks = json.loads((scene / "clicks.json").read_text())
    (out / "clicks.json").write_text(json.dumps([{k: c[k] for k in ("file_path", "xy", "class")} for c in clicks], indent=2) + "\n")
    (out / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out / "transforms.json"
