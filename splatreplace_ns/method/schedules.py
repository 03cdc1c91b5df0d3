"""Learning-rate schedules that follow the run's stage lengths.

nerfstudio builds a method's schedulers from the config registered with the method, so a schedule written there
with a fixed ``max_steps`` ignores ``--pipeline.base-iterations`` on the command line. The trainer
(:class:`splatreplace_ns.method.config.SplatReplaceTrainer`) sets the decays to the base stage's length before the
optimizers are made (:func:`follow_stage_lengths`), so ``ns-train`` and a run built in-process get the same schedule.
"""

from __future__ import annotations

from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig


def follow_stage_lengths(optimizers: dict, base_steps: int) -> None:
    """Sets every exponential decay in a trainer's ``optimizers`` config (the positions', the camera optimiser's) to
    end with the base stage; after it the rate stays at its final value, through fine-tuning (as 3DGS's schedule
    does past its last step)."""
    for entry in optimizers.values():
        scheduler = entry.get("scheduler")
        if isinstance(scheduler, ExponentialDecaySchedulerConfig):
            scheduler.max_steps = max(base_steps, scheduler.warmup_steps + 1)
