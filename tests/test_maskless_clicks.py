"""A click that made no instance mask at the masks step selects no instance at segmentation.

The contrastive features learn instances apart from the masks. A click left out at the masks step (on a plane, on
empty space) has no mask, so the features never learnt its instance: the rendered feature at its pixel is that of
another instance or of the background, and its query would select another click's Gaussians under its own name.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from splatreplace_ns.datamanager.clicks import Click, clicks_digest
from splatreplace_ns.datamanager.mask_writer import write_dataset_masks
from splatreplace_ns.method.masks_stage import MasksStage


def dataset(folder: Path, frames: int = 2) -> Path:
    meta = {"fl_x": 10.0, "fl_y": 10.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6,
            "frames": [{"file_path": f"images/{k:04d}.png", "transform_matrix": np.eye(4).tolist()}
                       for k in range(frames)]}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def stage_on(folder: Path) -> MasksStage:
    stage = MasksStage()
    stage.datamanager = SimpleNamespace(get_datapath=lambda: folder, has_instance_masks=True)
    return stage


def clicks(n: int = 3):
    return [Click(k, f"images/{k % 2:04d}.png", (1.0 + k, 2.0), "crate") for k in range(n)]


def test_the_click_the_masks_step_left_out_is_named(tmp_path):
    folder = dataset(tmp_path)
    given = clicks()
    masks = [np.zeros((6, 8), np.uint16) for _ in range(2)]
    # click 0 made no mask (its id 1 is absent), clicks 1 and 2 made ids 2 and 3
    write_dataset_masks(folder, masks, [{"id": 2, "class": "crate"}, {"id": 3, "class": "crate"}], clicks_digest(given))
    assert stage_on(folder)._clicks_without_masks(given) == {0}


def test_every_click_with_a_mask_is_kept(tmp_path):
    folder = dataset(tmp_path)
    given = clicks()
    masks = [np.zeros((6, 8), np.uint16) for _ in range(2)]
    write_dataset_masks(folder, masks, [{"id": k + 1, "class": "crate"} for k in range(3)], clicks_digest(given))
    assert stage_on(folder)._clicks_without_masks(given) == set()


def test_masks_made_from_other_clicks_leave_none_out(tmp_path):
    """Masks from other clicks (or given masks) say nothing of these clicks: none is left out on their account."""
    folder = dataset(tmp_path)
    masks = [np.zeros((6, 8), np.uint16) for _ in range(2)]
    write_dataset_masks(folder, masks, [{"id": 2, "class": "crate"}], clicks_digest(clicks(2)))
    assert stage_on(folder)._clicks_without_masks(clicks(3)) == set()
