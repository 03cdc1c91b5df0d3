"""A capture whose clicks make no instance on the base model: ns-train goes on without instances (nothing is
replaced; the scene trains as the base model to the end) rather than ending after the base stage."""

from __future__ import annotations

import json


def test_clicks_that_make_no_instance_leave_the_scene_as_it_was_and_training_goes_on(tmp_path):
    from splatreplace_ns.method.train import make_trainer_config, run_training
    from splatreplace_ns.tools.sim import make_scene
    from splatreplace_ns.tools.sim.capture import strip_ground_truth

    scene = tmp_path / "scene"
    make_scene("tiny", scene, n_train=12)
    capture = tmp_path / "capture"
    strip_ground_truth(scene, capture)
    clicks = json.loads((capture / "clicks.json").read_text())
    # the top-left corner of each click's view: wall or nothing, no crate
    (capture / "clicks.json").write_text(json.dumps([dict(c, xy=[1, 1]) for c in clicks]))
    B, C, F = 120, 20, 40
    config = make_trainer_config(capture, tmp_path / "runs", B, contrastive_iterations=C, finetune_iterations=F)
    config.max_num_iterations = config.pipeline.total_iterations
    steps = []
    pipeline = run_training(config, after_step=lambda trainer, step: steps.append(step)).pipeline
    assert steps[-1] == B + C + F - 1  # trained to the end
    assert "no click makes an instance" in pipeline.masks_report["error"]
    assert pipeline.segmentation_report["instances"] == [] and "made an instance" in pipeline.segmentation_report["unsegmented"]
    model = pipeline.model
    assert not model.has_templates and model.instances == []
    assert model.finetune_start == B  # the steps meant for the contrastive features train the scene instead
    assert pipeline.registration_report.get("skipped") == "no instance was selected"
