"""Carving after registration (``--pipeline.segmentation.carve-only-replaced``): the leftovers of replaced
instances go, those of an instance left as it was stay (tiny scene, ground-truth poses, one registration failed)."""

from __future__ import annotations

import pytest
import torch

from splatreplace_ns.tools.bench import oracle
from splatreplace_ns.method.pipeline import SplatReplacePipeline
from splatreplace_ns.method.pipeline import SplatReplacePipeline
from splatreplace_ns.method.train import make_trainer_config
from splatreplace_ns.instances.carve import carved_instance
from splatreplace_ns.tools.sim import make_scene
from scenes import train_patched


def test_carved_instance_takes_the_mask_seen_in_most_views():
    # two cameras looking down +z from the origin, 8x8 pixels, focal 8: a centre at (x, y, 1) lands at (8x+4, 8y+4)
    viewmats = torch.eye(4).expand(3, 4, 4).clone()
    Ks = torch.tensor([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]).expand(3, 3, 3)
    masks = torch.zeros(3, 8, 8, dtype=torch.long)
    masks[0, :, :4] = 1  # view 0: left half instance 1
    masks[1, :, :4] = 2  # view 1: left half instance 2
    masks[2, :, :4] = 2  # view 2: the same
    means = torch.tensor([[-0.25, 0.0, 1.0],  # left half: 1 in one view, 2 in two → 2
                          [0.25, 0.0, 1.0],   # right half: no mask → 0
                          [-0.25, 0.0, -1.0],  # behind every camera → 0
                          [5.0, 0.0, 1.0]])  # outside every image → 0
    assert carved_instance(means, viewmats, Ks, 8, 8, masks).tolist() == [2, 0, 0, 0]
    masks[1:] = 0
    assert carved_instance(means, viewmats, Ks, 8, 8, masks).tolist() == [1, 0, 0, 0]
    # a centre one pixel right of the mask counts with a tolerance of one pixel
    near_edge = torch.tensor([[0.05, 0.0, 1.0]])  # pixel 4.4 → column 4, right of columns 0-3
    assert carved_instance(near_edge, viewmats, Ks, 8, 8, masks).tolist() == [0]
    assert carved_instance(near_edge, viewmats, Ks, 8, 8, masks, mask_tolerance=1).tolist() == [1]


@pytest.fixture(scope="module")
def one_not_replaced(tmp_path_factory):
    """The tiny scene with carving after registration, ground-truth poses and one non-template instance's
    registration failed; the model's state right before and after the templates are built."""
    state: dict = {}

    def registered_but_one(self, instances, classes, config):
        results = oracle.ground_truth_registration(instances, classes, oracle.dataset_poses(self.datamanager))
        victim = next(i for i, r in sorted(results.items()) if r.template_id != i and r.success)
        results[victim].success = False
        state["victim"] = victim
        return results

    build = SplatReplacePipeline.build_shared_templates

    def recorded_build(self, start_step):
        model = self.model
        state["before"] = {"means": model.means.detach().clone(), "labels": model.instance_labels.clone(),
                           "owner": model.carve_owner.clone(), "report": dict(self.segmentation_report)}
        build(self, start_step)
        state["after"] = {"means": model.means.detach().clone(),
                          "background": (model.gauss_params["template_class"][:, 0] == 0).detach().clone(),
                          "own": {i: int(g["means"].shape[0]) for i, g in model.own_gaussians.items()},
                          "owner": model.carve_owner}

    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 400, 250, 4)
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    config.pipeline.segmentation.carve_only_replaced = True
    config.pipeline.revert.enabled = False
    trainer = train_patched(config, (SplatReplacePipeline, "register_instances", registered_but_one),
                            (SplatReplacePipeline, "build_shared_templates", recorded_build))
    return trainer, state


def test_segmentation_defers_carving(one_not_replaced):
    _, state = one_not_replaced
    before = state["before"]
    report = before["report"]
    assert report["carved"] == 0 and report["carve_deferred"] == int((before["owner"] > 0).sum()) > 0
    assert bool((before["labels"][before["owner"] > 0] == 0).all())  # leftovers are background Gaussians
    assert before["owner"].shape[0] == before["means"].shape[0]


def test_only_the_replaced_instances_leftovers_are_removed(one_not_replaced):
    trainer, state = one_not_replaced
    before, after, victim = state["before"], state["after"], state["victim"]
    labels, owner = before["labels"], before["owner"]
    replaced = [int(i) for i in trainer.pipeline.model.instance_table.ids]
    assert victim not in replaced and replaced
    assert int((owner == victim).sum()) > 0, "the tiny scene's run left no leftover of the failed instance"
    gone = torch.isin(labels, torch.tensor(replaced)) | torch.isin(owner, torch.tensor(replaced))
    # the background after building = every Gaussian of before but the replaced instances and their leftovers
    assert int(after["background"].sum()) == int((~gone).sum())
    kept = before["means"][~gone]
    assert torch.equal(after["means"][after["background"]], kept)  # in order, untouched
    # each replaced instance's own Gaussians (what the check after fine-tuning compares its copy with) are those
    # segmentation selected, without the leftovers
    for i in replaced:
        assert after["own"][i] == int((labels == i).sum())
    assert after["owner"] is None
    assert trainer.pipeline.model.carve_owner is None
