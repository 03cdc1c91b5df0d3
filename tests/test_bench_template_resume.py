"""``bench template``'s ablations resume from ours' checkpoint at the end of segmentation; the oracle
``gt_instances`` swaps in the ground-truth labelling and poses (tiny scene, a few hundred iterations)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from splatreplace_ns.tools.bench.template import run_ablation
from splatreplace_ns.method.train import make_trainer_config, run_training
from splatreplace_ns.tools.sim import make_scene

B, C, F = 150, 100, 40


@pytest.fixture(scope="module")
def segmented(tmp_path_factory):
    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    out = tmp_path_factory.mktemp("runs")
    config = make_trainer_config(data, out, B, C, 0, experiment_name="ours", steps_per_save=B + C - 1)
    config.save_only_latest_checkpoint = False
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    trainer = run_training(config)
    assert trainer.pipeline.model.stage == "segmented"
    return data, out, config.get_checkpoint_dir()


def test_gt_instances_ablation_replaces_every_instance_with_ground_truth(segmented):
    from nerfstudio.utils import writer

    data, out, checkpoints = segmented
    result = run_ablation("gt_instances", data, out, B, C, F, checkpoints)
    assert result["replaced"] == [1, 2, 3]
    assert all("ground-truth pose" in m for m in result["registration"].values())
    assert [i["source"] for i in result["instances"]] == ["ground truth"] * 3
    assert all(math.isfinite(result[k]) for k in ("psnr", "psnr_masked", "ssim", "ssim_masked"))
    # the progress line of a resumed run counts to the run's total, not past 100 %
    assert writer.GLOBAL_BUFFER["max_iter"] == B + C + F


def test_unknown_ablation_is_a_clear_error(segmented):
    data, out, checkpoints = segmented
    with pytest.raises(ValueError, match="unknown ablation 'bogus'"):
        run_ablation("bogus", data, out, B, C, F, checkpoints)
