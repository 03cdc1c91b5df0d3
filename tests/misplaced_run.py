"""A whole tiny run whose registration is the ground truth except for one copy, lifted twice its size above its
instance: the stage tests of the two checks against the training images (before replacement, after fine-tuning)."""

from __future__ import annotations

from typing import Callable, Dict

import numpy as np

from splatreplace_ns.tools.bench import oracle
from splatreplace_ns.method.pipeline import SplatReplacePipeline
from splatreplace_ns.method.train import make_trainer_config
from splatreplace_ns.tools.sim import make_scene
from scenes import train_patched


def train_with_one_misplaced_copy(tmp_path_factory, finetune_iterations: int, configure: Callable) -> tuple:
    """Trains the tiny scene (400 base, 250 contrastive steps) with one non-template copy misplaced.

    Returns:
        (trainer, the misplaced instance id).
    """
    misplaced: Dict[str, int] = {}

    def misregistered(self, instances, classes, config):
        results = oracle.ground_truth_registration(instances, classes, oracle.dataset_poses(self.datamanager))
        victim = next(i for i, r in sorted(results.items()) if r.template_id != i and r.success)
        size = float(np.ptp(np.asarray(instances[victim].means, dtype=np.float64), axis=0).max())
        T = np.array(results[victim].transform, dtype=np.float64)
        T[:3, 3] -= T[:3, :3] @ np.array([0.0, 0.0, 2.0 * size])  # the inverse pose lifts the copy by 2 sizes
        results[victim].transform = T
        misplaced["id"] = victim
        return results

    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 400, 250, finetune_iterations)
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    configure(config)
    trainer = train_patched(config, (SplatReplacePipeline, "register_instances", misregistered))
    return trainer, misplaced["id"]
