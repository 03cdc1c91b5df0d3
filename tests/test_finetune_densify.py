"""Densification during fine-tuning (``model.finetune_densify``, off by default): with ``background`` only
Gaussians outside the templates grow, as the baseline's do through its longer schedule; when nothing is replaced,
the segmented scene densifies and its instance labels follow their Gaussians; between refinements nothing changes
(gsplat's opacity reset at step 0 must not fire at the start of fine-tuning)."""

from __future__ import annotations

import torch

from splatreplace_ns.tools.bench import oracle
from splatreplace_ns.method.pipeline import SplatReplacePipeline
from splatreplace_ns.method.model import SplatReplaceModel
from splatreplace_ns.method.pipeline import SplatReplacePipeline
from splatreplace_ns.method.train import make_trainer_config
from splatreplace_ns.tools.sim import make_scene
from scenes import train_patched

FINETUNE = 120  # refinements at fine-tuning steps 24, 36 and 48, the check after fine-tuning at 60


def _train(tmp_path_factory, register) -> tuple:
    """Trains the tiny scene with ``register`` as the registration hook; returns (trainer, at the start of
    fine-tuning: {"template", "background": stored Gaussians of each kind, "points": all, "labels": instance
    label per stored Gaussian, "quiet_changes": for each densification call that added or removed nothing, the
    largest change it made to any stored opacity})."""
    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 400, 250, FINETUNE)
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    config.pipeline.model.finetune_densify = "background"
    at_start = {}
    build = SplatReplacePipeline.build_shared_templates

    def counting_build(self, start_step):
        build(self, start_step)
        classes = self.model.gauss_params["template_class"][:, 0].round().long()
        at_start.update(template=int((classes > 0).sum()), background=int((classes == 0).sum()),
                        labels=self.model.instance_labels.clone(), points=self.model.num_points)

    densify = SplatReplaceModel._finetune_densify
    at_start["quiet_changes"] = []

    def watched_densify(self, step):
        before = self.opacities.detach().clone()
        densify(self, step)
        if self.num_points == len(before):
            at_start["quiet_changes"].append(float((self.opacities.detach() - before).abs().max()))

    trainer = train_patched(config, (SplatReplaceModel, "_finetune_densify", watched_densify),
                            (SplatReplacePipeline, "register_instances", register),
                            (SplatReplacePipeline, "build_shared_templates", counting_build))
    return trainer, at_start


def ground_truth_registration(self, instances, classes, config):
    return oracle.ground_truth_registration(instances, classes, oracle.dataset_poses(self.datamanager))


def no_registration(self, instances, classes, config):
    results = oracle.ground_truth_registration(instances, classes, oracle.dataset_poses(self.datamanager))
    for result in results.values():
        result.success = False
    return results


def test_only_the_background_grows_when_instances_are_replaced(tmp_path_factory):
    trainer, at_start = _train(tmp_path_factory, ground_truth_registration)
    model = trainer.pipeline.model
    assert model.stage == "finetune" and model.has_templates
    classes = model.gauss_params["template_class"][:, 0].round().long()
    # templates only lose Gaussians (opacity pruning); the background gained some
    assert int((classes > 0).sum()) <= at_start["template"]
    assert int((classes == 0).sum()) > at_start["background"]
    for name, param in model.gauss_params.items():
        assert len(param) == len(classes), name
    scene = model.composed_scene()
    assert torch.isfinite(scene.means).all() and len(scene.means) == int((classes == 0).sum()) + sum(
        int((classes == c).sum()) for c in model.instance_table.class_index.tolist())
    # between refinements densification only gathers statistics: no opacity reset, at the first step either
    assert at_start["quiet_changes"] and max(at_start["quiet_changes"]) == 0.0


def test_the_segmented_scene_densifies_and_keeps_its_labels_when_nothing_is_replaced(tmp_path_factory):
    trainer, at_start = _train(tmp_path_factory, no_registration)
    model = trainer.pipeline.model
    assert not model.has_templates and model.stage == "segmented"
    assert at_start["template"] == 0 and at_start["points"] == at_start["background"]  # nothing was replaced
    labels = model.instance_labels
    assert len(labels) == model.num_points != at_start["points"]
    # a split or duplicated Gaussian carries its parent's label: the same instances, each still labelled
    assert set(labels.unique().tolist()) == set(at_start["labels"].unique().tolist())
    truth = oracle.dataset_poses(trainer.pipeline.datamanager)
    for iid in set(labels.unique().tolist()) - {0}:
        centre = model.means.detach()[labels.to(model.device) == iid].median(dim=0).values.cpu()
        pose = torch.as_tensor(truth[iid], dtype=torch.float32)
        assert (centre - pose[:3, 3]).norm() < pose[:3, :3].norm(dim=0).mean(), iid
