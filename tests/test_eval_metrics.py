"""Evaluation metrics: PSNR/SSIM against skimage, masked metrics with known answers, LPIPS/KID without weights,
registration errors from hand-made registrations, and what ``ns-eval`` reports for a segmented model."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from splatreplace_ns.eval.metrics import MAX_PSNR, mse_to_psnr, psnr, squared_error_by_label, ssim
from splatreplace_ns.eval.perceptual import LocalKID, LocalLPIPS
from splatreplace_ns.eval.registration import registration_errors
from splatreplace_ns.eval.report import EvalViewRecorder, json_safe

H, W = 48, 64


def skimage_ssim(pred: torch.Tensor, gt: torch.Tensor, full: bool = False):
    return structural_similarity(
        pred.double().numpy(), gt.double().numpy(), gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
        data_range=1.0, channel_axis=-1, full=full,
    )


def image_pairs():
    """(name, pred, gt): noise, blur-like smoothing, a brightness shift, and a structured image."""
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(H, W, 3, generator=g)
    yield "noise", (gt + 0.1 * torch.randn(H, W, 3, generator=g)).clamp(0, 1), gt
    smooth = torch.nn.functional.avg_pool2d(gt.permute(2, 0, 1)[None], 3, stride=1, padding=1)[0].permute(1, 2, 0)
    yield "smoothed", smooth, gt
    yield "brighter", (gt * 0.8 + 0.15).clamp(0, 1), gt
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    pattern = torch.stack((xx, yy, 0.5 + 0.5 * torch.sin(12 * xx) * torch.cos(9 * yy)), dim=-1)
    yield "pattern", (pattern + 0.03 * torch.randn(H, W, 3, generator=g)).clamp(0, 1), pattern


@pytest.mark.parametrize("name,pred,gt", list(image_pairs()), ids=[p[0] for p in image_pairs()])
def test_psnr_and_ssim_match_skimage(name, pred, gt):
    ref_psnr = peak_signal_noise_ratio(gt.double().numpy(), pred.double().numpy(), data_range=1.0)
    ref_ssim = skimage_ssim(pred, gt)
    assert psnr(pred, gt) == pytest.approx(ref_psnr, abs=1e-4)
    assert ssim(pred, gt) == pytest.approx(ref_ssim, abs=1e-4)
    # the (1, 3, H, W) layout gives the same figures
    nchw = lambda t: t.permute(2, 0, 1)[None]  # noqa: E731
    assert psnr(nchw(pred), nchw(gt)) == pytest.approx(ref_psnr, abs=1e-4)
    assert ssim(nchw(pred), nchw(gt)) == pytest.approx(ref_ssim, abs=1e-4)


def box_mask(top: int, left: int, height: int, width: int) -> torch.Tensor:
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[top : top + height, left : left + width] = True
    return mask


def test_masked_psnr_known_answers():
    gt = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 0.8 + 0.1
    mask = box_mask(10, 20, 15, 25)
    # identical inside the mask, wrong outside: the masked PSNR is the cap, the full PSNR is not
    pred = gt.clone()
    pred[~mask] = 1.0 - pred[~mask]
    assert psnr(pred, gt, mask) == MAX_PSNR == pytest.approx(100.0)
    assert psnr(pred, gt) < 30
    # an error of exactly 0.1 on every channel, only inside the mask: 20 dB inside,
    # and over the whole image the MSE is diluted by the mask's share of the pixels
    pred = gt.clone()
    pred[mask] += 0.1
    share = float(mask.float().mean())
    assert psnr(pred, gt, mask) == pytest.approx(20.0, abs=1e-9)
    assert psnr(pred, gt) == pytest.approx(-10 * math.log10(0.01 * share), abs=1e-9)
    # masks given as (H, W, 1) int like the dataset's, or (1, 1, H, W), mean the same
    assert psnr(pred, gt, mask[..., None].int() > 0) == pytest.approx(20.0, abs=1e-9)
    assert psnr(pred, gt, mask[None, None]) == pytest.approx(20.0, abs=1e-9)


def test_squared_error_by_label_pools_to_the_masked_psnr():
    gt = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    labels = torch.zeros(H, W, dtype=torch.long)
    labels[10:20, 15:25] = 3
    labels[30:35, :] = 7
    pred = gt.clone()
    pred[labels == 3] += 0.1  # 20 dB inside instance 3
    pred[labels == 7] += 0.01  # 40 dB inside instance 7; the background is exact
    out = squared_error_by_label(pred, gt, labels)
    assert set(out) == {0, 3, 7}
    assert out[3][1] == 100 and out[7][1] == 5 * W and out[0][0] == 0.0
    assert mse_to_psnr(out[3][0] / out[3][1]) == pytest.approx(20.0, abs=1e-9)
    assert mse_to_psnr(out[7][0] / out[7][1]) == pytest.approx(40.0, abs=1e-9)
    assert mse_to_psnr(out[3][0] / out[3][1]) == pytest.approx(psnr(pred, gt, labels == 3), abs=1e-9)


def test_masked_ssim_is_the_skimage_map_over_the_mask():
    g = torch.Generator().manual_seed(2)
    gt = torch.rand(H, W, 3, generator=g)
    pred = (gt + 0.08 * torch.randn(H, W, 3, generator=g)).clamp(0, 1)
    mask = box_mask(3, 2, 30, 20) | box_mask(25, 40, 20, 20)  # touches the border on purpose
    _, full_map = skimage_ssim(pred, gt, full=True)
    interior = (slice(5, H - 5), slice(5, W - 5))
    expected = full_map.mean(axis=-1)[interior][mask.numpy()[interior]].mean()
    assert ssim(pred, gt, mask) == pytest.approx(expected, abs=1e-4)
    # an all-true mask is the full-image SSIM
    assert ssim(pred, gt, torch.ones(H, W, dtype=torch.bool)) == pytest.approx(ssim(pred, gt), abs=1e-12)
    # errors more than 5 px (half the window) away from the mask leave its SSIM at exactly 1
    inside = box_mask(15, 20, 12, 16)
    far = ~box_mask(9, 14, 24, 28)
    damaged = gt.clone()
    damaged[far] = torch.rand(int(far.sum()), 3, generator=g)
    assert ssim(damaged, gt, inside) == pytest.approx(1.0, abs=1e-12)
    assert ssim(damaged, gt) < 0.9


def test_empty_mask_is_not_available_rather_than_nan():
    gt = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(3))
    pred = gt * 0.9
    empty = torch.zeros(H, W, dtype=torch.bool)
    assert psnr(pred, gt, empty) is None
    assert ssim(pred, gt, empty) is None
    # only border pixels: PSNR has them, SSIM (window centred 5 px inside) has none
    border = box_mask(0, 0, H, 3)
    assert psnr(pred, gt, border) is not None and math.isfinite(psnr(pred, gt, border))
    assert ssim(pred, gt, border) is None
    with pytest.raises(ValueError, match="does not match the image size"):
        psnr(pred, gt, torch.ones(W, H, dtype=torch.bool))


def test_lpips_and_kid_are_unavailable_without_local_weights(tmp_path):
    previous = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "empty_hub"))
    try:
        img = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(4))
        with pytest.warns(UserWarning, match="never computed with random weights"):
            lpips = LocalLPIPS()
            assert not lpips.available
        assert lpips(img, img * 0.5) is None
        assert "AlexNet weights not found" in lpips.unavailable_reason and str(tmp_path) in lpips.unavailable_reason
        with pytest.warns(UserWarning, match="never computed with random weights"):
            kid = LocalKID()
            kid.update(img, img * 0.5)
        assert kid.compute() is None
        assert "InceptionV3 weights not found" in kid.unavailable_reason and str(tmp_path) in kid.unavailable_reason
        assert not any((tmp_path / "empty_hub").rglob("*.pth")), "nothing may be downloaded"
    finally:
        torch.hub.set_dir(previous)


def test_masked_averages_skip_views_without_instances():
    recorder = EvalViewRecorder(model=None)
    recorder.views = [
        {"psnr": 20.0, "psnr_masked": 30.0, "ssim_masked": 0.9},
        {"psnr": 22.0},  # no instance in this view
        {"psnr": 24.0, "psnr_masked": 34.0, "ssim_masked": 0.7},
    ]
    out = recorder.masked_averages(get_std=True)
    assert out["psnr_masked"] == pytest.approx(32.0) and out["ssim_masked"] == pytest.approx(0.8)
    assert out["psnr_masked_std"] == pytest.approx(np.std([30.0, 34.0], ddof=1))
    assert out["masked_views"] == 2
    assert EvalViewRecorder(model=None).masked_averages() == {}
    recorder.views = recorder.views[:1]  # one view: a mean and no spread, and no warning from torch
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        one = recorder.masked_averages(get_std=True)
    assert one["psnr_masked"] == 30.0 and math.isnan(one["psnr_masked_std"])


def test_json_safe_replaces_non_finite_and_tensors():
    value = {1: float("nan"), "a": [torch.tensor(2.5), np.float32(1.5), float("inf")], "t": torch.ones(2)}
    safe = json_safe(value)
    assert json.loads(json.dumps(safe, allow_nan=False)) == {"1": None, "a": [2.5, 1.5, None], "t": [1.0, 1.0]}


# --------------------------------------------------------------------------- registration errors


def rotation(axis, degrees: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()


def similarity(R: np.ndarray, t, s: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = s * R
    pose[:3, 3] = t
    return pose


def rigid_about(R: np.ndarray, centre) -> np.ndarray:
    """Rotation R about the point ``centre`` (4×4)."""
    centre = np.asarray(centre, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = centre - R @ centre
    return out


def test_registration_errors_from_hand_made_registrations():
    s = 0.37  # dataparser scale inside the ground-truth poses
    gt_poses = {
        10: similarity(rotation([0, 0, 1], 30), [0.1, 0.2, 0.0], s),
        20: similarity(rotation([0.2, 0.1, 1], 75), [-0.4, 0.3, 0.05], s),
        30: similarity(rotation([0, 0, 1], -110), [0.5, -0.2, 0.0], s),
        40: similarity(rotation([1, 0, 0], 5), [0.0, 0.6, 0.0], s),
    }
    model_to_gt = {1: 10, 2: 20, 3: 30, 4: 40}
    symmetries = {10: "rot_z:4", 20: "rot_z:4", 30: "rot_z:4", 40: "rot_z:4"}
    sizes = {k: 0.5 * s for k in gt_poses}

    def exact(src: int) -> np.ndarray:  # template ≈ T · source
        return gt_poses[10] @ np.linalg.inv(gt_poses[model_to_gt[src]])

    t_src = {k: gt_poses[model_to_gt[k]][:3, 3] for k in model_to_gt}
    z_axis_of = lambda k: gt_poses[model_to_gt[k]][:3, 2] / s  # noqa: E731  object z in the world
    # source 2: off by 7° about a tilted axis through its origin → 7°, no translation error
    off_rot = exact(2) @ rigid_about(rotation([1, 1, 0], 7), t_src[2])
    # source 3: a quarter turn about its own (symmetry) z axis → 0° under rot_z:4, shifted by 0.03
    quarter = rigid_about(rotation(z_axis_of(3), 90), t_src[3])
    shift = np.eye(4)
    shift[:3, 3] = [0.03, 0.0, 0.0]
    off_sym = exact(3) @ np.linalg.inv(shift) @ quarter
    registration = {
        "1": {"template": 1, "transform": np.eye(4).tolist(), "success": True},  # the template itself
        "2": {"template": 1, "transform": off_rot.tolist(), "success": True},
        "3": {"template": 1, "transform": off_sym.tolist(), "success": True},
        "4": {"template": 1, "transform": (exact(4) @ rigid_about(rotation([0, 1, 0], 40), t_src[4])).tolist(), "success": False},
        "5": {"template": 1, "transform": np.eye(4).tolist(), "success": True},  # no ground truth for it
    }
    report = registration_errors(registration, model_to_gt, gt_poses, symmetries, sizes)
    rows = {r["instance"]: r for r in report["per_instance"]}
    assert set(rows) == {2, 3, 4}
    assert rows[2]["rotation_error_deg"] == pytest.approx(7.0, abs=1e-6)
    assert rows[2]["translation_error_rel"] == pytest.approx(0.0, abs=1e-9)
    assert rows[3]["rotation_error_deg"] == pytest.approx(0.0, abs=1e-5)
    assert rows[3]["translation_error_rel"] == pytest.approx(0.03 / (0.5 * s), abs=1e-9)
    assert rows[4]["rotation_error_deg"] == pytest.approx(40.0, abs=1e-5) and not rows[4]["success"]
    assert [r["instance"] for r in report["skipped"]] == [5]
    # the summary is over the successful registrations (2 and 3)
    assert report["num_registered"] == 3 and report["num_success"] == 2
    assert report["success_rate"] == pytest.approx(2 / 3)
    assert report["rotation_error_deg_mean"] == pytest.approx(3.5, abs=1e-5)
    # a refusal keeps the identity as its transform; what it refused is scored from proposed_transform, and
    # every candidate the registration considered from its own transform
    refused = dict(registration)
    refused["2"] = {"template": 1, "transform": np.eye(4).tolist(), "success": False,
                    "proposed_transform": off_rot.tolist(),
                    "candidates": [{"transform": off_rot.tolist(), "fitness": 0.15, "colour": 0.3, "inliers": 0,
                                    "pair": [-1, 0]},
                                   {"transform": (exact(2) @ rigid_about(rotation(z_axis_of(2), 180), t_src[2])).tolist(),
                                    "fitness": 0.1, "colour": 0.05, "inliers": 9, "pair": [3, 4]}]}
    row2 = {r["instance"]: r for r in registration_errors(refused, model_to_gt, gt_poses, symmetries, sizes)["per_instance"]}[2]
    assert not row2["success"] and row2["rotation_error_deg"] > 10.0  # the identity is far from source 2's pose
    assert row2["proposed_rotation_error_deg"] == pytest.approx(7.0, abs=1e-6)
    assert [c["rotation_error_deg"] for c in row2["candidates"]] == pytest.approx([7.0, 0.0], abs=1e-5)  # 180° ≡ 0° under rot_z:4
    assert row2["candidates"][1]["inliers"] == 9 and row2["candidates"][0]["pair"] == [-1, 0]
    assert "proposed_rotation_error_deg" not in rows[3] and "candidates" not in rows[3]
    # with no symmetry the quarter turn counts in full
    asym = registration_errors(registration, model_to_gt, gt_poses, {}, sizes)
    assert {r["instance"]: r for r in asym["per_instance"]}[3]["rotation_error_deg"] == pytest.approx(90.0, abs=1e-5)


# --------------------------------------------------------------------------- ns-eval on a segmented model


@pytest.fixture(scope="module")
def segmented_run(tmp_path_factory):
    """The tiny sim scene through the base and contrastive stages and the click segmentation (short budget,
    as in test_segmentation_stage; no carving, which does not matter here)."""
    from splatreplace_ns.method.train import make_trainer_config, run_training
    from splatreplace_ns.tools.sim import make_scene

    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 300, contrastive_iterations=200)
    config.pipeline.model.num_downscales = 0
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    config.pipeline.segmentation.carve = False
    trainer = run_training(config)
    return data, config, trainer


def hand_made_registration(pipeline, data: Path, error_deg: float):
    """Instance 2 registered exactly onto instance 1, instance 3 off by ``error_deg`` about its own x axis.

    Uses the ground-truth poses from transforms.json moved into the model's frame independently of the
    dataparser's instance list, and the click ids to know which model instance is which object.
    """
    from splatreplace_ns.datamanager.dataparser import normalise_object_pose

    outputs = pipeline.datamanager.train_dataparser_outputs
    meta = json.loads((data / "transforms.json").read_text())
    clicks = json.loads((data / "clicks.json").read_text())
    gt_pose = {
        int(i["id"]): normalise_object_pose(
            np.array(i["transform_matrix"]), outputs.dataparser_transform.numpy(), outputs.dataparser_scale
        )
        for i in meta["instances"]
    }
    model_pose = {k + 1: gt_pose[int(c["id"])] for k, c in enumerate(clicks)}  # instance k+1 ← click k
    exact = {k: model_pose[1] @ np.linalg.inv(model_pose[k]) for k in (2, 3)}
    pose3 = model_pose[3]
    x_axis = pose3[:3, 0] / np.linalg.norm(pose3[:3, 0])
    off = exact[3] @ rigid_about(rotation(x_axis, error_deg), pose3[:3, 3])
    return {
        1: {"template": 1, "transform": np.eye(4).tolist(), "success": True},
        2: {"template": 1, "transform": exact[2].tolist(), "success": True},
        3: {"template": 1, "transform": off.tolist(), "success": True},
    }


def independent_view_metrics(pipeline):
    """Per eval view: PSNR and SSIM (skimage), masked PSNR (numpy) and masked SSIM (skimage's map)."""
    model = pipeline.model
    model.eval()
    rows = []
    for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
        with torch.no_grad():
            outputs = model.get_outputs_for_camera(camera)
        pred = outputs["rgb"].double().cpu().numpy()
        gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"]).double().cpu().numpy()
        mask = batch["instance_mask"][..., 0].numpy() > 0
        ssim_value, ssim_full = structural_similarity(
            pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
            channel_axis=-1, full=True,
        )
        interior = (slice(5, -5), slice(5, -5))
        labels = batch["instance_mask"][..., 0].numpy()
        squared = ((pred - gt) ** 2).mean(-1)
        rows.append({
            "squared_error": {int(k): (float(squared[labels == k].sum()), int((labels == k).sum())) for k in np.unique(labels)},
            "psnr": peak_signal_noise_ratio(gt, pred, data_range=1.0),
            "ssim": ssim_value,
            "psnr_masked": -10 * np.log10(np.mean((pred[mask] - gt[mask]) ** 2)) if mask.any() else None,
            "ssim_masked": ssim_full.mean(-1)[interior][mask[interior]].mean() if mask[interior].any() else None,
        })
    model.train()
    return rows


def test_eval_report_of_a_segmented_model(segmented_run, tmp_path):
    data, _, trainer = segmented_run
    pipeline = trainer.pipeline
    previous_hub = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "empty_hub"))
    try:
        pipeline.model.lpips = LocalLPIPS()  # checks the (empty) hub directory afresh
        pipeline.model.registration = hand_made_registration(pipeline, data, error_deg=10.0)
        with pytest.warns(UserWarning, match="never computed with random weights"):
            report = pipeline.get_average_eval_image_metrics()
    finally:
        torch.hub.set_dir(previous_hub)
        pipeline.model.registration = {}
    json.dumps(report, allow_nan=False)  # strict JSON: no NaN, no tensors

    expected = independent_view_metrics(pipeline)
    for key in ("psnr", "ssim", "psnr_masked", "ssim_masked"):
        values = [row[key] for row in expected if row[key] is not None]
        assert report[key] == pytest.approx(float(np.mean(values)), abs=1e-4), key
    assert report["masked_views"] == sum(row["psnr_masked"] is not None for row in expected) > 0
    # every view on its own, in the eval dataset's order, named by its image
    names = [p.name for p in pipeline.datamanager.eval_dataset.image_filenames]
    assert [row["image"] for row in report["per_view"]] == names and len(names) == len(expected)
    for row, truth in zip(report["per_view"], expected):
        assert row["psnr"] == pytest.approx(truth["psnr"], abs=1e-4)
        if truth["psnr_masked"] is None:
            assert row["psnr_masked"] is None
        else:
            assert row["psnr_masked"] == pytest.approx(truth["psnr_masked"], abs=1e-4)
    # the masked region is a subset of the image: its figure is not the full-image one
    assert report["psnr_masked"] != pytest.approx(report["psnr"], abs=1e-3)
    # per instance: the error pooled over its pixels in every view (numpy, independently)
    pooled = {}
    for row in expected:
        for k, (sse, n) in row["squared_error"].items():
            pooled[k] = (pooled.get(k, (0.0, 0))[0] + sse, pooled.get(k, (0.0, 0))[1] + n)
    assert set(report["psnr_per_instance"]) == {str(k) for k in pooled} and "0" in report["psnr_per_instance"]
    for k, (sse, n) in pooled.items():
        assert report["psnr_per_instance"][str(k)] == pytest.approx(-10 * math.log10(sse / n), abs=1e-4), k

    assert set(report["versions"]) >= {"splatreplace_ns", "nerfstudio", "torch", "gsplat"}
    assert report["versions"]["nerfstudio"] == "1.1.5" and report["versions"]["torch"] == torch.__version__
    unavailable = report["unavailable"]
    assert "lpips" not in report and "AlexNet weights not found" in unavailable["lpips"]
    assert "kid" not in report and "InceptionV3 weights not found" in unavailable["kid"]

    assert report["instance_masks"] == "ground truth"
    segmentation = report["segmentation"]
    clicks = json.loads((data / "clicks.json").read_text())
    assert set(segmentation["iou"]) == {str(c["id"]) for c in clicks}
    assert segmentation["miou"] == pytest.approx(np.mean(list(segmentation["iou"].values())))
    assert segmentation["click_failures"] == []
    # the clicked instances are found in the test views: mIoU 0.736 with the fixture's seed (the same at 1 and 2
    # torch threads), 0.73-0.76 with machine.seeds 1-4, the lowest crate 0.63 in those five runs. Empty masks
    # score 0, and the queries of the wrong instances about 0 (0.001-0.002 with the ids swapped in
    # test_segmentation_stage's test_scores_against_a_reference_scene)
    assert 0.6 < segmentation["miou"] <= 1.0 and min(segmentation["iou"].values()) > 0.5, segmentation["iou"]
    assert 0.0 < segmentation["macc"] <= 1.0
    assert segmentation["views"] == len(pipeline.datamanager.eval_dataset)

    registration = report["registration"]
    rows = {r["instance"]: r for r in registration["per_instance"]}
    assert set(rows) == {2, 3}
    assert rows[2]["gt_id"] == clicks[1]["id"] and rows[2]["template_gt_id"] == clicks[0]["id"]
    assert rows[2]["rotation_error_deg"] == pytest.approx(0.0, abs=1e-3)
    assert rows[2]["translation_error_rel"] == pytest.approx(0.0, abs=1e-5)
    assert rows[3]["rotation_error_deg"] == pytest.approx(10.0, abs=1e-3)
    assert rows[3]["translation_error_rel"] == pytest.approx(0.0, abs=1e-5)
    assert registration["rotation_error_deg_mean"] == pytest.approx(5.0, abs=1e-3)


def test_training_time_eval_returns_only_numbers(segmented_run):
    _, _, trainer = segmented_run
    pipeline = trainer.pipeline
    averaged = pipeline.get_average_eval_image_metrics(step=1)
    assert {"psnr", "ssim", "psnr_masked", "ssim_masked"} <= set(averaged)
    assert all(isinstance(v, (int, float)) and math.isfinite(v) for v in averaged.values()), averaged
    single, images = pipeline.get_eval_image_metrics_and_images(step=1)  # what the Trainer logs as scalars
    assert all(isinstance(v, (int, float)) for v in single.values()), single
    assert "img" in images


def test_view_without_instances_has_no_masked_metrics(segmented_run):
    _, _, trainer = segmented_run
    model = trainer.pipeline.model
    camera, batch = trainer.pipeline.datamanager.fixed_indices_eval_dataloader[0]
    model.eval()
    with torch.no_grad():
        outputs = model.get_outputs_for_camera(camera)
    model.train()
    batch = dict(batch, instance_mask=torch.zeros_like(batch["instance_mask"]))
    metrics, _ = model.get_image_metrics_and_images(outputs, batch)
    assert "psnr_masked" not in metrics and "ssim_masked" not in metrics
    assert all(math.isfinite(v) for v in metrics.values())


def test_ns_eval_writes_one_strict_json_with_every_figure(segmented_run, tmp_path):
    _, config, _ = segmented_run
    out = tmp_path / "eval.json"
    env = dict(os.environ, TORCH_HOME=str(tmp_path / "torch_home"))  # no LPIPS/KID weights there
    result = subprocess.run(
        [str(Path(sys.executable).parent / "ns-eval"), "--load-config", str(config.get_base_dir() / "config.yml"),
         "--output-path", str(out)],
        capture_output=True, text=True, timeout=600, env=env,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]

    def no_constants(name):
        raise AssertionError(f"{out} holds {name}, which is not JSON")

    results = json.loads(out.read_text(), parse_constant=no_constants)["results"]
    for key in ("psnr", "ssim", "psnr_masked", "ssim_masked", "psnr_std", "psnr_masked_std"):
        assert isinstance(results[key], float), key
    assert 0 < results["ssim_masked"] <= 1 and results["masked_views"] >= 1
    assert results["versions"]["splatreplace_ns"]
    assert set(results["unavailable"]) >= {"lpips", "kid"}
    # the same model from its checkpoint: the segmentation scores as in test_eval_report_of_a_segmented_model
    assert results["segmentation"]["miou"] > 0.6 and results["segmentation"]["click_failures"] == [], results["segmentation"]
