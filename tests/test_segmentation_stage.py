"""Contrastive stage + one-click segmentation + carving inside the splat-replace run (tiny sim scene)."""

from __future__ import annotations

import json
import types

import pytest
import torch

from splatreplace_ns.method.train import make_trainer_config, run_training
from splatreplace_ns.datamanager.clicks import Click
from splatreplace_ns.instances.from_clicks import SelectionError
from splatreplace_ns.tools.sim import make_scene
from scenes import (
    click_in_viewer, fire_viewer_click, free_port, lock_is_free, press_viewer_button, train_with_viewer, viewer_psnr, wait_until,
)


@pytest.fixture(scope="module")
def segmented(tmp_path_factory):
    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 400, contrastive_iterations=300)
    config.pipeline.model.num_downscales = 0
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    trainer = run_training(config)
    return data, config, trainer


def gt_masks(pipeline):
    ds = pipeline.datamanager.train_dataset
    return torch.stack([ds.get_data(i, image_type="uint8")["instance_mask"][..., 0] for i in range(len(ds))])


def solid_pixel_of(pipeline, click) -> tuple:
    """(u, v): the pixel of the click's ground-truth instance, in the click's view, where the segmented model
    renders most opacity. The scene's own click can sit where carving thinned this 400-iteration model below
    the alpha threshold (0.49 in one CI run); a test of something else must not hinge on that."""
    idx = pipeline.train_index_of(click["file_path"])
    mask = pipeline.datamanager.train_dataset.get_data(idx, image_type="uint8")["instance_mask"][..., 0]
    with torch.no_grad():
        _, alpha, _ = pipeline.model.render_features(pipeline.train_camera(idx))
    inside = torch.where(mask.to(alpha.device) == click["id"], alpha[..., 0], torch.zeros_like(alpha[..., 0]))
    row, col = divmod(int(inside.argmax()), inside.shape[1])
    assert float(inside[row, col]) >= pipeline.config.segmentation.min_alpha
    return float(col), float(row)


def test_clicks_give_one_instance_each_with_matching_masks(segmented):
    data, _, trainer = segmented
    pipeline = trainer.pipeline
    clicks = json.loads((data / "clicks.json").read_text())
    model = pipeline.model
    assert model.stage == "segmented"
    assert [i["class"] for i in model.instances] == [c["class"] for c in clicks]
    assert model.instance_labels.shape == (model.num_points,)
    for k in range(1, len(clicks) + 1):
        assert (model.instance_labels == k).sum() > 10
    # rendered training-view masks against the ground truth (click k carries the GT id)
    gt = gt_masks(pipeline)
    ours = pipeline.instance_masks_2d.long()
    ious = []
    for k, click in enumerate(clicks, start=1):
        a, b = ours == k, gt == click["id"]
        ious.append(float((a & b).sum()) / float((a | b).sum()))
    assert min(ious) > 0.75, ious
    assert pipeline.segmentation_report["carved"] >= 0
    # each instance's selected Gaussians cover a real share of its rendered masks (0.30-0.55 in the runs so far;
    # below the warning's 0.2 carving would take the rest of it)
    coverage = pipeline.segmentation_report["mask_coverage"]
    assert sorted(coverage) == [1, 2, 3] and all(0.2 <= share <= 1 for share in coverage.values()), coverage


def test_bad_clicks_change_nothing(segmented):
    data, _, trainer = segmented
    pipeline = trainer.pipeline
    pipeline.model.eval()
    selection = pipeline.begin_selection()
    clicks = json.loads((data / "clicks.json").read_text())
    first = Click(0, clicks[0]["file_path"], solid_pixel_of(pipeline, clicks[0]), clicks[0]["class"])
    pipeline.add_click(first)
    before = [i.id for i in selection.instances]

    with pytest.raises(SelectionError, match="same Gaussians as instance 1"):
        pipeline.add_click(Click(1, first.file_path, first.xy, "crate"))
    with pytest.raises(SelectionError, match="outside the 64x48 image"):
        pipeline.add_click(Click(2, first.file_path, (64.0, 10.0), "crate"))
    with pytest.raises(SelectionError, match="not a training image"):
        pipeline.add_click(Click(3, "images/nope.png", (3.0, 3.0), "crate"))
    # a floor/wall pixel: background in the ground-truth mask of that view
    idx = pipeline.train_index_of(first.file_path)
    mask = pipeline.datamanager.train_dataset.get_data(idx, image_type="uint8")["instance_mask"][..., 0]
    rows, cols = torch.nonzero(mask == 0, as_tuple=True)
    with pytest.raises(SelectionError, match="background|nothing is rendered"):
        pipeline.add_click(Click(4, first.file_path, (float(cols[0]), float(rows[0])), "crate"))
    assert [i.id for i in selection.instances] == before


def test_viewer_click_flow_selects_the_clicked_instance(segmented):
    """Drives the viewer's click callback (viser → nerfstudio ViewerClick → our handler) headlessly."""
    import viser

    data, _, trainer = segmented
    pipeline = trainer.pipeline
    pipeline.model.eval()
    selection = pipeline.begin_selection()
    controls = pipeline.selection_controls
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        controls.viewer_control._setup(types.SimpleNamespace(viser_server=server))
        click = json.loads((data / "clicks.json").read_text())[1]
        idx = pipeline.train_index_of(click["file_path"])
        camera = pipeline.datamanager.train_dataset.cameras[idx]
        c2w = camera.camera_to_worlds  # OpenGL
        u, v = solid_pixel_of(pipeline, click)
        ray_cam = torch.tensor([(u + 0.5 - float(camera.cx)) / float(camera.fx), -(v + 0.5 - float(camera.cy)) / float(camera.fy), -1.0])
        direction = c2w[:, :3] @ (ray_cam / ray_cam.norm())
        origin = c2w[:, 3]

        controls.arm_click()
        fire_viewer_click(server, origin, direction)
        assert len(selection.instances) == 1, controls.status.value
        chosen = selection.labels() == 1
        assert int(chosen.sum()) > 10, int(chosen.sum())
        # it is the instance that the finished segmentation gave to this click (the second one). Its Gaussians are
        # those the segmentation selected for it (label 2) and, with carving waiting for registration, the leftovers
        # carving found inside its masks (carve_owner 2): ten times as many, which no feature query selects, so the
        # ray's query is scored against the selected ones (recall) and against both (precision).
        # Measured with machine.seeds 42 (the fixture's) and 1-4: precision 1.0 in every run, recall of the selected
        # ones 0.87 (seed 42), 0.87-0.98 over the five; recall of the other two instances 0. A query of the wrong
        # instance scores 0 on both, a random choice of as many Gaussians has precision 0.04-0.17.
        labels, owner = pipeline.model.instance_labels, pipeline.model.carve_owner
        instance = labels == 2
        if owner is not None:
            instance |= owner == 2
        precision = float((chosen & instance).sum()) / float(chosen.sum())
        recall = float((chosen & (labels == 2)).sum()) / float((labels == 2).sum())
        others = [float((chosen & (labels == k)).sum()) / float((labels == k).sum()) for k in (1, 3)]
        assert precision > 0.95 and recall > 0.6 and max(others) < 0.05, (precision, recall, others)
        assert pipeline.model.highlight is not None and bool(pipeline.model.highlight.any())

        controls.undo()
        assert selection.instances == [] and "(none)" in controls.listing.value
        controls.confirm()  # nothing selected: refuses, stays open
        assert "at least one" in controls.status.value
    finally:
        server.stop()
        pipeline.model.highlight = None


def test_ns_train_waits_for_the_instance_clicks_in_its_viewer(tmp_path):
    """Masks and no clicks.json, nerfstudio's viewer on: at the end of the contrastive stage training waits
    without the trainer's lock (the viewer renders meanwhile); "Select instances" and "Confirm instances"
    pressed through the hooks nerfstudio installed (which take that lock) and click rays fired through viser
    select the clicked instances; the viewer then shows the replaced scene while it fine-tunes."""
    data = tmp_path / "tiny"
    make_scene("tiny", data, n_train=12)
    clicks = json.loads((data / "clicks.json").read_text())
    (data / "clicks.json").unlink()
    config = make_trainer_config(data, tmp_path / "runs", 300, contrastive_iterations=200, finetune_iterations=100)
    config.pipeline.model.num_downscales = 0
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    # the flow ends in a replaced instance; at this budget often one copy alone registers, which the lone-copy rule
    # (min_class_copies 2) would leave as it was
    config.pipeline.registration.min_class_copies = 1

    def user(trainer, result) -> None:
        pipeline = trainer.pipeline
        controls = pipeline.selection_controls
        wait_until(lambda: pipeline.selection is not None and "Select instances" in controls.status.value,
                   what="the selection to open at the end of the contrastive stage")
        result["lock_free_while_waiting"] = lock_is_free(trainer.train_lock)
        result["psnr_waiting"] = viewer_psnr(trainer, clicks[0]["file_path"])
        result["status_after_clicks"] = click_in_viewer(trainer, controls, clicks)
        # the selected instances are tinted in the viewer while selecting: the render moves away from the image
        result["psnr_highlighted"] = viewer_psnr(trainer, clicks[0]["file_path"])
        press_viewer_button(controls.confirm_button)
        wait_until(lambda: pipeline.model.has_templates, what="the fine-tuning stage")
        result["psnr_finetuning"] = viewer_psnr(trainer, clicks[0]["file_path"])

    trainer, result = train_with_viewer(config, user, lambda t: [t.pipeline.selection_controls._confirmed])
    assert "error" not in result, result["error"]
    pipeline = trainer.pipeline
    psnr_end = viewer_psnr(trainer, clicks[0]["file_path"])
    # the replaced scene right after the templates are built is coarser than the base at this tiny budget
    # (17.2-17.7 dB against 27.8 in the runs so far) and fine-tuning brings it back (24.3)
    assert result["lock_free_while_waiting"] and result["psnr_waiting"] > 20 and result["psnr_finetuning"] > 14, result
    assert result["psnr_highlighted"] < result["psnr_waiting"] - 0.5, result
    assert psnr_end > 20, psnr_end
    assert [i["class"] for i in pipeline.model.instances] == [c["class"] for c in clicks], result["status_after_clicks"]
    gt, ours = gt_masks(pipeline), pipeline.instance_masks_2d.long()
    ious = [float(((ours == k) & (gt == c["id"])).sum()) / float(((ours == k) | (gt == c["id"])).sum())
            for k, c in enumerate(clicks, start=1)]
    assert min(ious) > 0.5, ious


def test_a_clicks_file_written_while_training_waits_in_the_viewer_selects_the_instances(tmp_path):
    """Nobody at the viewer (a remote machine): clicks.json written while the segmentation stage waits ends the
    wait, and the instances are selected from it."""
    data = tmp_path / "tiny"
    make_scene("tiny", data, n_train=12)
    clicks_text = (data / "clicks.json").read_text()
    (data / "clicks.json").unlink()
    config = make_trainer_config(data, tmp_path / "runs", 300, contrastive_iterations=200)
    config.pipeline.model.num_downscales = 0
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512

    def user(trainer, result) -> None:
        pipeline = trainer.pipeline
        wait_until(lambda: pipeline.selection is not None and "Select instances" in pipeline.selection_controls.status.value,
                   what="the selection to open at the end of the contrastive stage")
        (data / "clicks.json").write_text(clicks_text)

    trainer, result = train_with_viewer(config, user, lambda t: [t.pipeline.selection_controls._confirmed])
    assert "error" not in result, result["error"]
    clicks = json.loads(clicks_text)
    instances = trainer.pipeline.segmentation_report["instances"]
    assert [i["source"].split(" (")[0] for i in instances] == [f"click {k}" for k in range(len(clicks))], instances
    assert "clicks.json appeared" in trainer.pipeline.selection_controls.status.value


def test_checkpoint_keeps_segmentation(segmented, tmp_path):
    _, config, trainer = segmented
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config.get_base_dir() / "config.yml")
    assert pipeline.model.stage == "segmented"
    assert len(pipeline.model.instances) == 3
    assert pipeline.model.instance_labels.shape == (pipeline.model.num_points,)
    # what the viewer's "Select instances" panel shows for a loaded run (ns-viewer)
    controls = pipeline.selection_controls
    assert controls.listing.value.count(": crate (") == 3 and controls.status.value.startswith("3 instances were selected")


def test_depth_loss_used_when_frames_carry_depth(segmented):
    _, _, trainer = segmented
    pipeline = trainer.pipeline
    pipeline.model.train()
    camera, batch = pipeline.datamanager.next_train(0)
    assert "depth" in batch
    outputs = pipeline.model(camera)
    losses = pipeline.model.get_loss_dict(outputs, batch)
    assert "depth_loss" in losses and torch.isfinite(losses["depth_loss"]) and losses["depth_loss"] > 0
    pipeline.model.eval()


def test_scores_against_a_reference_scene(segmented, tmp_path):
    """A run trained on masks of its own making is scored against another scene's ground truth: with the
    run's own scene as reference the scores are those of its own masks; with the instance ids swapped in the
    reference, the same masks score low."""
    import shutil

    from splatreplace_ns.eval.segmentation import score_views_from_clicks

    data, _, trainer = segmented
    pipeline = trainer.pipeline
    assert pipeline.segmentation_report["skipped_clicks"] == []
    own = score_views_from_clicks(pipeline, data / "clicks.json")
    same = score_views_from_clicks(pipeline, data / "clicks.json", reference_scene=data)
    # test views of a 400+300-iteration run: mIoU 0.806 with the fixture's seed, 0.78-0.81 with machine.seeds 1-4;
    # empty masks score 0 and the swapped ids below 0.001-0.002
    assert own["miou"] > 0.6 and same["miou"] == own["miou"] and same["iou"] == own["iou"], own["iou"]
    swapped = tmp_path / "swapped"
    shutil.copytree(data, swapped)
    clicks = json.loads((data / "clicks.json").read_text())
    ids = [c["id"] for c in clicks]
    for click, other in zip(clicks, ids[1:] + ids[:1]):
        click["id"] = other
    (swapped / "clicks.json").write_text(json.dumps(clicks))
    wrong = score_views_from_clicks(pipeline, data / "clicks.json", reference_scene=swapped)
    assert wrong["miou"] < 0.5 * own["miou"], (wrong["miou"], own["miou"])


def test_when_no_click_selects_an_instance_the_scene_is_left_as_it_was(tmp_path):
    """Every click of clicks.json on the background: the run does not stop; nothing is segmented, registered or
    replaced, and the fine-tuning steps train the scene as it was."""
    import cv2

    data = tmp_path / "tiny"
    make_scene("tiny", data, n_train=8, n_test=2)
    meta = json.loads((data / "transforms.json").read_text())
    mask_of = {f["file_path"]: f["instance_mask_path"] for f in meta["frames"]}
    clicks = json.loads((data / "clicks.json").read_text())
    for click in clicks:
        mask = cv2.imread(str(data / mask_of[click["file_path"]]), cv2.IMREAD_UNCHANGED)
        rows, cols = (mask == 0).nonzero()
        click["xy"] = [int(cols[0]), int(rows[0])]
    (data / "clicks.json").write_text(json.dumps(clicks))
    config = make_trainer_config(data, tmp_path / "runs", 60, contrastive_iterations=30, finetune_iterations=30)
    trainer = run_training(config)
    pipeline = trainer.pipeline
    assert len(pipeline.segmentation_report["skipped_clicks"]) == len(clicks)
    assert pipeline.model.instances == [] and not pipeline.model.has_templates
    assert pipeline.registration_report["skipped"] == "no instance was selected"
    assert int(pipeline.model.instance_labels.sum()) == 0 and pipeline.segmentation_report["carved"] == 0
