"""In-process training and evaluation through nerfstudio's own Trainer (used by the CLI and tests)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Dict, Optional, Tuple

from nerfstudio.engine.trainer import Trainer, TrainerConfig

from splatreplace_ns.method.config import splat_replace_trainer_config


def make_trainer_config(
    data: Path,
    output_dir: Path,
    base_iterations: int,
    contrastive_iterations: int = 0,
    finetune_iterations: int = 0,
    *,
    experiment_name: Optional[str] = None,
    steps_per_save: Optional[int] = None,
    progress: bool = False,
    resume_from: Optional[Tuple[Path, int]] = None,
    train_on_every_frame: bool = False,
) -> TrainerConfig:
    """splat-replace's TrainerConfig set up for an unattended run (no viewer, no evaluation mid-run).

    ``resume_from=(checkpoint_dir, step)`` continues a run from its checkpoint at ``step`` up to the same
    total as a fresh run: nerfstudio's Trainer runs ``max_num_iterations`` steps *after* the loaded one,
    so only the steps that are left are asked for. ``train_on_every_frame`` ignores the dataset's train/test
    split (a base model for masks only).
    """
    config = splat_replace_trainer_config(base_iterations, contrastive_iterations, finetune_iterations)
    max_num_iterations = config.pipeline.total_iterations
    if resume_from is not None:
        config.load_dir, config.load_step = Path(resume_from[0]), int(resume_from[1])
        if not 0 <= config.load_step < max_num_iterations - 1:
            raise ValueError(f"resume step {config.load_step} is not inside a run of {max_num_iterations} steps")
        config.max_num_iterations = max_num_iterations - (config.load_step + 1)
    config.pipeline.datamanager.data = Path(data)
    config.pipeline.datamanager.dataparser.train_on_every_frame = train_on_every_frame
    config.output_dir = Path(output_dir)
    config.experiment_name = experiment_name or Path(data).name
    config.timestamp = "run"
    config.vis = "tensorboard"
    config.steps_per_eval_image = max_num_iterations + 1
    config.steps_per_eval_all_images = max_num_iterations + 1
    config.steps_per_save = steps_per_save or max_num_iterations
    # the local writer prints step, time per step and ETA: the progress display of long runs
    config.logging.local_writer.enable = progress
    config.logging.steps_per_log = max(1, max_num_iterations // 50)
    return config


def setup_trainer(config: TrainerConfig) -> Trainer:
    """What ``ns-train`` does before training: saves ``config.yml``, seeds ``random``, numpy and torch with
    ``machine.seed`` (so a run does not depend on what ran before it in this process), sets the trainer up
    (loading a checkpoint when the config names one)."""
    from nerfstudio.scripts.train import _set_random_seed

    config.set_timestamp()
    config.save_config()
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def run_training(
    config: TrainerConfig,
    after_step: Optional[Callable[[Trainer, int], None]] = None,
    before_train: Optional[Callable[[Trainer], None]] = None,
) -> Trainer:
    """Sets up like ``ns-train`` does (:func:`setup_trainer`), trains, and returns the trainer.

    ``before_train(trainer)`` runs once after setup (checkpoint loaded), before the first step: the oracle
    ablations of ``bench template`` swap in ground-truth stages with it.

    ``after_step(trainer, step)`` runs after every training iteration, after the pipeline's own callbacks
    (so after the segmentation that ends the contrastive stage): benchmarks time stages and keep extra
    checkpoints with it.
    """
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    trainer = setup_trainer(config)
    if trainer._start_step > 0:  # resumed: nerfstudio's progress line counts from the loaded step
        from nerfstudio.utils import writer

        writer.GLOBAL_BUFFER["max_iter"] = trainer._start_step + config.max_num_iterations
    if before_train is not None:
        before_train(trainer)
    if after_step is not None:
        trainer.callbacks.append(
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], lambda step: after_step(trainer, step))
        )
    trainer.train()
    return trainer


def evaluate_test_views(trainer: Trainer) -> Dict[str, float]:
    """Average image metrics over the eval split (what ``ns-eval`` reports)."""
    trainer.pipeline.eval()
    return trainer.pipeline.get_average_eval_image_metrics()
