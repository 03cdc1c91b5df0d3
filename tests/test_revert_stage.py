"""The check after fine-tuning inside a whole run: an instance registered to a wrong place is put back as it was
part-way through fine-tuning, named as not replaced in the registration record, in ``ns-eval``'s report and in
the viewer's instance list; the other copies stay replaced and training goes on to the end."""

from __future__ import annotations

import pytest
import torch

from splatreplace_ns.eval.report import replacement_report

from misplaced_run import train_with_one_misplaced_copy


@pytest.fixture(scope="module")
def reverted(tmp_path_factory):
    def configure(config):
        assert config.pipeline.revert.enabled  # the defaults
        # this scene's base model fits its own crates at ~20 dB only: the ground-truth copies
        # may lose a little to their own Gaussians here, the lifted copy loses far more
        config.pipeline.revert.margin_db = 3.0

    return train_with_one_misplaced_copy(tmp_path_factory, 20, configure)


def test_the_misplaced_instance_is_put_back_and_the_others_stay_replaced(reverted):
    trainer, victim = reverted
    pipeline = trainer.pipeline
    model = pipeline.model
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
    trainer, victim = reverted
    model = trainer.pipeline.model
    assert model.stage == "finetune" and model.has_templates
    outputs = model.get_outputs(trainer.pipeline.datamanager.train_dataset.cameras[0:1].to(model.device))
    assert torch.isfinite(outputs["rgb"]).all()


def test_the_report_and_the_viewer_name_it(reverted):
    trainer, victim = reverted
    pipeline = trainer.pipeline
    report = replacement_report(pipeline.model)
    assert report[str(victim)]["replaced"] is False and "put back" in report[str(victim)]["why"]
    assert report[str(victim)]["check_after_finetune"]["revert"] is True
    listing = pipeline.selection_controls._listing(pipeline.model.instances, pipeline._not_replaced())
    assert f"{victim}: " in listing and listing.count("(not replaced)") == 1
