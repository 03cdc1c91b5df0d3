"""`splatreplace masks` end to end on the tiny sim scene with its masks withheld (one base run, shared)."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from splatreplace_ns.masks.capture import strip_ground_truth
from splatreplace_ns.masks.command import MasksCommand, make_masks
from splatreplace_ns.masks.lifting import ClickError
from splatreplace_ns.masks.onnx_sam import OnnxModelError
from splatreplace_ns.sim import make_scene


def mask_iou(scene, capture) -> list:
    """IoU per instance of the written masks against the ground truth, over every frame."""
    gt_meta = json.loads((scene / "transforms.json").read_text())
    ours_meta = json.loads((capture / "transforms.json").read_text())
    clicks = json.loads((scene / "clicks.json").read_text())
    gt = np.stack([cv2.imread(str(scene / f["instance_mask_path"]), -1) for f in gt_meta["frames"]])
    ours = np.stack([cv2.imread(str(capture / f["instance_mask_path"]), -1) for f in ours_meta["frames"]])
    ious = []
    for k, click in enumerate(clicks, start=1):
        a, b = ours == k, gt == click["id"]
        ious.append(float((a & b).sum()) / float((a | b).sum()))
    return ious


@pytest.fixture(scope="module")
def base_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("masks")
    scene = root / "scene"
    make_scene("tiny", scene, n_train=12)
    capture = root / "capture"
    strip_ground_truth(scene, capture)
    report = make_masks(MasksCommand(capture, base_iterations=300, output_dir=root / "runs"))
    return scene, capture, report


def test_masks_for_every_frame_match_the_ground_truth(base_run):
    scene, capture, report = base_run
    meta = json.loads((capture / "transforms.json").read_text())
    assert all(f["instance_mask_path"] == f"masks/{i:04d}.png" for i, f in enumerate(meta["frames"]))
    assert meta["instances"] == [{"id": k, "class": "crate"} for k in (1, 2, 3)]
    assert (capture / "transforms.json.before-masks").exists()
    assert "instances" not in json.loads((capture / "transforms.json.before-masks").read_text())
    for frame in meta["frames"]:
        mask = cv2.imread(str(capture / frame["instance_mask_path"]), cv2.IMREAD_UNCHANGED)
        assert mask.dtype == np.uint16 and mask.shape == (48, 64)
    ious = mask_iou(scene, capture)
    # 300 base iterations at 64x48: the masks are coarse but each one is the clicked crate
    assert min(ious) > 0.3 and np.mean(ious) > 0.45, ious


def test_rerun_with_the_saved_base_gives_the_same_bytes(base_run, tmp_path):
    _, capture, report = base_run
    copy = tmp_path / "again"
    shutil.copytree(capture, copy)
    make_masks(MasksCommand(copy, load_config=report["config"]))
    for path in sorted(capture.glob("masks/*.png")) + [capture / "transforms.json"]:
        assert (copy / path.relative_to(capture)).read_bytes() == path.read_bytes(), path.name


def test_bad_inputs_leave_transforms_untouched(base_run, tmp_path):
    _, capture, report = base_run
    data = tmp_path / "bad"
    shutil.copytree(capture, data)
    before = (data / "transforms.json").read_bytes()
    clicks = json.loads((data / "clicks.json").read_text())

    def run_with(entries, **kwargs):
        path = tmp_path / "clicks.json"
        path.write_text(json.dumps(entries))
        return make_masks(MasksCommand(data, clicks=path, load_config=report["config"], **kwargs))

    sky = dict(clicks[0], xy=[1, 1])  # top-left corner of the view: wall or nothing, no crate
    with pytest.raises(ClickError, match=r"click 1 \(images/"):
        run_with([clicks[0], sky])
    with pytest.raises(ClickError, match="click 1 .*same object as click 0"):
        run_with([clicks[0], dict(clicks[0])])
    with pytest.raises(ClickError, match="click 0 .*not a frame"):
        run_with([dict(clicks[0], file_path="images/missing.png")])
    with pytest.raises(OnnxModelError, match="--sam-decoder"):
        run_with(clicks, backend="onnx-sam", sam_encoder=tmp_path / "e.onnx")
    assert (data / "transforms.json").read_bytes() == before


def test_onnx_sam_backend_with_a_tiny_exported_pair(base_run, tmp_path):
    from test_masks_onnx import export_tiny_sam

    scene, capture, report = base_run
    encoder, decoder = export_tiny_sam(tmp_path / "sam")
    data = tmp_path / "sam_capture"
    shutil.copytree(capture, data)
    make_masks(MasksCommand(data, backend="onnx-sam", sam_encoder=encoder, sam_decoder=decoder, load_config=report["config"]))
    ious = mask_iou(scene, data)
    assert min(ious) > 0.2 and np.mean(ious) > 0.35, ious


def test_splat_replace_trains_on_the_written_masks(base_run, tmp_path):
    from splatreplace_ns.method.train import make_trainer_config, run_training

    _, capture, _ = base_run
    config = make_trainer_config(capture, tmp_path / "runs", 100, contrastive_iterations=60)
    config.pipeline.datamanager.contrastive_uniform_samples = 512
    config.pipeline.datamanager.contrastive_mask_samples = 256
    trainer = run_training(config)
    model = trainer.pipeline.model
    assert model.stage == "segmented"
    assert len(model.instances) >= 1
