"""The check after fine-tuning inside a whole run: an instance registered to a wrong place is put back as it was
part-way through fine-tuning, named as not replaced in the registration record, in ``ns-eval``'s report and in
the viewer's instance list; the other copies stay replaced and training goes on to the end."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from splatreplace_ns.bench import oracle
from splatreplace_ns.datamanager.datamanager import SplatReplaceDataManager
from splatreplace_ns.eval.report import replacement_report
from splatreplace_ns.method.train import make_trainer_config, run_training
from splatreplace_ns.sim import make_scene

MISPLACED = {}


def misregistered(self, instances, classes, config):
    """Ground-truth poses, except for one non-template instance whose copy is placed twice its size above it."""
    results = oracle.ground_truth_registration(instances, classes, oracle.dataset_poses(self))
    victim = next(i for i, r in sorted(results.items()) if r.template_id != i and r.success)
    size = float(np.ptp(np.asarray(instances[victim].means, dtype=np.float64), axis=0).max())
    T = np.array(results[victim].transform, dtype=np.float64)
    T[:3, 3] -= T[:3, :3] @ np.array([0.0, 0.0, 2.0 * size])  # the inverse pose lifts the copy by 2 sizes
    results[victim].transform = T
    MISPLACED["id"] = victim
    return results


@pytest.fixture(scope="module")
def reverted(tmp_path_factory):
    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 400, 250, 20)
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    assert config.pipeline.revert.enabled and not config.pipeline.gate.enabled  # the defaults
    # this scene's base model fits its own crates at ~20 dB only (see test_gate_stage): the ground-truth copies
    # may lose a little to their own Gaussians here, the lifted copy loses far more
    config.pipeline.revert.margin_db = 3.0
    patch = pytest.MonkeyPatch()
    patch.setattr(SplatReplaceDataManager, "register_instances", misregistered)
    try:
        trainer = run_training(config)
    finally:
        patch.undo()
    return trainer


def test_the_misplaced_instance_is_put_back_and_the_others_stay_replaced(reverted):
    pipeline = reverted.pipeline
    model = pipeline.model
    victim = MISPLACED["id"]
    entry = model.registration[victim]
    assert not entry["success"] and "put back" in entry["message"], entry
    check = entry["check_after_finetune"]
    assert check["revert"] and check["loss_db"] > pipeline.config.revert.margin_db
    assert victim in pipeline.registration_report["revert"]["reverted"]
    table = model.instance_table
    assert victim not in table.ids.tolist() and victim in table.kept_in_background
    kept = [i for i, r in model.registration.items() if r["success"]]
    assert sorted(table.ids.tolist()) == sorted(kept) and len(kept) >= 2
    for i in kept:  # each kept one was checked and passed
        assert model.registration[i]["check_after_finetune"]["loss_db"] <= pipeline.config.revert.margin_db
    assert model.own_gaussians == {}  # dropped once the check has run
    composed = model.composed_scene()
    assert int((composed.instance_id == victim).sum()) == 0
    assert len(composed.means) > 0 and torch.isfinite(composed.means).all()
    assert model.instance_pose_delta.shape == (len(table.ids), 6)


def test_training_went_on_after_the_check(reverted):
    model = reverted.pipeline.model
    assert model.stage == "finetune" and model.has_templates
    outputs = model.get_outputs(reverted.pipeline.datamanager.train_dataset.cameras[0:1].to(model.device))
    assert torch.isfinite(outputs["rgb"]).all()


def test_the_report_and_the_viewer_name_it(reverted):
    pipeline = reverted.pipeline
    victim = MISPLACED["id"]
    report = replacement_report(pipeline.model)
    assert report[str(victim)]["replaced"] is False and "put back" in report[str(victim)]["why"]
    assert report[str(victim)]["check_after_finetune"]["revert"] is True
    listing = pipeline.selection_controls._listing(pipeline.model.instances, pipeline._not_replaced())
    assert f"{victim}: " in listing and listing.count("(not replaced)") == 1
