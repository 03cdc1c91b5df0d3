"""Learning-rate schedules that follow the run's stage lengths.

nerfstudio builds a method's schedulers from the config registered with the method, so a schedule written there
with a fixed ``max_steps`` ignores ``--pipeline.base-iterations`` on the command line. The trainer
(:class:`splatreplace_ns.method.config.SplatReplaceTrainer`) fills the stage lengths in from the pipeline config
before the optimizers are made (:func:`follow_stage_lengths`), so ``ns-train`` and a run built in-process get the
same schedule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Type

from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig, Scheduler, SchedulerConfig
from torch.optim import Optimizer, lr_scheduler


def position_lr(step: int, lr_init: float, lr_final: float, base_steps: int, finetune_start: int,
                finetune_steps: int, finetune_lr: float) -> float:
    """Learning rate of the Gaussians' positions at a global step.

    Base stage (steps ``[0, base_steps)``): exponential decay from ``lr_init`` to ``lr_final`` (3DGS's schedule).
    Until fine-tuning starts: ``lr_final``. Fine-tuning (from ``finetune_start``, ``finetune_steps`` long): an
    exponential decay of its own from ``finetune_lr`` to ``lr_final`` when ``finetune_lr > 0``, else ``lr_final``
    (positions as good as frozen). All rates > 0.
    """
    def decay(start: float, t: float) -> float:
        t = min(max(t, 0.0), 1.0)
        return math.exp(math.log(start) * (1.0 - t) + math.log(lr_final) * t)

    if step < base_steps:
        return decay(lr_init, step / max(base_steps, 1))
    if step < finetune_start or finetune_lr <= 0:
        return lr_final
    return decay(finetune_lr, (step - finetune_start) / max(finetune_steps, 1))


@dataclass
class StagedPositionSchedulerConfig(SchedulerConfig):
    """The positions' schedule: 3DGS's decay over the base stage and, optionally, a decay of its own over
    fine-tuning. ``base_steps``, ``finetune_start`` and ``finetune_steps`` are set from the pipeline's stage lengths
    when the trainer starts; values given here are replaced."""

    _target: Type = field(default_factory=lambda: StagedPositionScheduler)
    lr_final: float = 1.6e-6
    """Rate at the end of the base stage, kept until fine-tuning and at its end."""
    finetune_lr: float = 0.0
    """Rate of the positions when fine-tuning starts, decaying to lr-final over it; 0 keeps lr-final."""
    base_steps: int = 30000
    """Length of the base stage (from --pipeline.base-iterations)."""
    finetune_start: int = 35000
    """First fine-tuning step (base + contrastive steps)."""
    finetune_steps: int = 7000
    """Length of fine-tuning (from --pipeline.finetune-iterations)."""


class StagedPositionScheduler(Scheduler):
    config: StagedPositionSchedulerConfig

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> lr_scheduler.LRScheduler:
        c = self.config

        def factor(step: int) -> float:  # LambdaLR multiplies the initial rate
            return position_lr(step, lr_init, c.lr_final, c.base_steps, c.finetune_start, c.finetune_steps,
                               c.finetune_lr) / lr_init

        return lr_scheduler.LambdaLR(optimizer, lr_lambda=factor)


def follow_stage_lengths(optimizers: dict, base_steps: int, finetune_start: int, finetune_steps: int) -> None:
    """Sets every schedule in a trainer's ``optimizers`` config to the run's stage lengths: the staged positions'
    schedule gets all three; an exponential decay (camera optimisation) decays over the base stage."""
    for entry in optimizers.values():
        scheduler = entry.get("scheduler")
        if isinstance(scheduler, StagedPositionSchedulerConfig):
            scheduler.base_steps, scheduler.finetune_start = base_steps, finetune_start
            scheduler.finetune_steps = finetune_steps
        elif isinstance(scheduler, ExponentialDecaySchedulerConfig):
            scheduler.max_steps = max(base_steps, scheduler.warmup_steps + 1)
