"""The pose check inside a whole run: an instance registered to a wrong place is left as it was, named as not
replaced in the registration record, in ``ns-eval``'s report and in the viewer's instance list, and the other
copies are still replaced."""

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
def gated(tmp_path_factory):
    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 400, 250, 10)
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    config.pipeline.gate.enabled = True
    config.pipeline.gate.turns = 1  # the refusal itself, not the search for a better turn
    # this scene's base model fits its own crates at ~20 dB only, so the lifted copy costs 3-9 dB there (the
    # ground-truth copies at most 2); the default margin is chosen on the dev split's sharper scenes
    config.pipeline.gate.margin_own_db = 3.0
    patch = pytest.MonkeyPatch()
    patch.setattr(SplatReplaceDataManager, "register_instances", misregistered)
    try:
        trainer = run_training(config)
    finally:
        patch.undo()
    return trainer


def test_the_misplaced_instance_stays_as_it_was_and_the_others_are_replaced(gated):
    pipeline = gated.pipeline
    model = pipeline.model
    victim = MISPLACED["id"]
    entry = model.registration[victim]
    assert not entry["success"] and "not replaced" in entry["message"], (entry["message"], entry.get("gate"))
    assert entry["gate"]["psnr_pose"] < entry["gate"]["psnr_own"] - pipeline.config.gate.margin_own_db
    assert victim in pipeline.registration_report["gate"]["refused"]
    table = model.instance_table
    assert victim not in table.ids.tolist() and victim in table.kept_in_background
    replaced = [i for i, r in model.registration.items() if r["success"]]
    assert sorted(table.ids.tolist()) == sorted(replaced) and len(replaced) >= 2
    # its own Gaussians are still in the scene, as background, where the instance is
    composed = model.composed_scene()
    assert int((composed.instance_id == victim).sum()) == 0
    assert torch.isfinite(composed.means).all()


def test_the_report_and_the_viewer_name_it(gated):
    pipeline = gated.pipeline
    victim = MISPLACED["id"]
    report = replacement_report(pipeline.model)
    assert report[str(victim)]["replaced"] is False and "not replaced" in report[str(victim)]["why"]
    assert report[str(victim)]["pose_check"]["psnr_own"] is not None
    assert all(row["replaced"] for key, row in report.items() if key != str(victim))
    listing = pipeline.selection_controls._listing(pipeline.model.instances, pipeline._not_replaced())
    assert f"{victim}: " in listing and "(not replaced)" in listing
    assert listing.count("(not replaced)") == 1
