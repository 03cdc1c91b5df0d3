"""``ns-train splat-replace``: the method specification registered with nerfstudio."""

from __future__ import annotations

import torch

from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from dataclasses import dataclass, field
from typing import Any, Dict, List, Type

from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.plugins.types import MethodSpecification
from nerfstudio.utils.rich_utils import CONSOLE

from splatreplace_ns.method.cpu_allocator import keep_freed_buffers
from splatreplace_ns.method.finite_steps import FiniteStepGradScaler
from splatreplace_ns.method.pipeline import SplatReplacePipelineConfig
from splatreplace_ns.method.schedules import follow_stage_lengths


@dataclass
class SplatReplaceTrainerConfig(TrainerConfig):
    _target: Type = field(default_factory=lambda: SplatReplaceTrainer)
    max_num_iterations: int = -1
    """Total iterations; -1 runs every stage (the sum of --pipeline.base-iterations, --pipeline.contrastive-iterations, ...)."""


class SplatReplaceTrainer(Trainer):
    """nerfstudio's Trainer; the run length and the learning-rate schedules follow the stage lengths, on CPU large freed buffers are kept for
    reuse (:mod:`splatreplace_ns.method.cpu_allocator`), and an iteration whose loss or gradients are not finite
    updates nothing (:mod:`splatreplace_ns.method.finite_steps`): its step is listed in ``skipped_steps``."""

    def __init__(self, config: SplatReplaceTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        if config.max_num_iterations <= 0:
            config.max_num_iterations = config.pipeline.total_iterations
        follow_stage_lengths(config.optimizers, config.pipeline.base_iterations)
        if not torch.cuda.is_available() or config.machine.device_type == "cpu":
            keep_freed_buffers()  # CPU steps reuse their large gradient buffers instead of re-faulting them
        super().__init__(config, local_rank, world_size)
        self.grad_scaler = FiniteStepGradScaler(enabled=self.use_grad_scaler)
        self.skipped_steps: List[int] = []

    def setup_optimizers(self) -> Optimizers:
        optimizers = super().setup_optimizers()
        self.grad_scaler.watch(optimizers.optimizers.values())
        load_all = optimizers.load_optimizers

        def load_known(loaded_state: Dict[str, Any]) -> None:
            # a checkpoint from an earlier version may hold the state of a parameter group since deleted
            load_all({name: state for name, state in loaded_state.items() if name in optimizers.optimizers})

        optimizers.load_optimizers = load_known
        return optimizers

    def train_iteration(self, step: int):
        out = super().train_iteration(step)
        if self.grad_scaler.skipped:
            self.skipped_steps.append(step)
            if len(self.skipped_steps) == 1:
                CONSOLE.print(f"[bold yellow]step {step}: the loss or a gradient is not finite; this step updates "
                              "nothing (1 step skipped so far; the total is reported at the end)")
        return out

    def train(self) -> None:
        super().train()
        if self.skipped_steps:
            steps = ", ".join(str(s) for s in self.skipped_steps[:10])
            steps += ", ..." if len(self.skipped_steps) > 10 else ""
            CONSOLE.print(f"[bold yellow]{len(self.skipped_steps)} step(s) skipped because the loss or a gradient was "
                          f"not finite: {steps}")


@dataclass
class FusedAdamOptimizerConfig(AdamOptimizerConfig):
    """nerfstudio's Adam config with torch's fused kernel: the same update, about 8x faster on CPU than the
    default per-tensor loop for the millions of per-Gaussian values (SH offsets) the fine-tuning stage updates."""

    fused: bool = True
    """Use torch.optim.Adam(fused=True) (CPU and CUDA)."""


def _adam(lr: float) -> dict:
    return {"optimizer": FusedAdamOptimizerConfig(lr=lr, eps=1e-15), "scheduler": None}


def splat_replace_trainer_config(
    base_iterations: int = 30000, contrastive_iterations: int = 5000, finetune_iterations: int = 7000
) -> TrainerConfig:
    """The full trainer configuration (also used in-process by the CLI, tests and benchmarks)."""
    return SplatReplaceTrainerConfig(
        method_name="splat-replace",
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=-1,
        mixed_precision=False,
        # CPU-first: pick the device that exists so `ns-train splat-replace --data DIR` just works.
        machine=MachineConfig(device_type="cuda" if torch.cuda.is_available() else "cpu"),
        pipeline=SplatReplacePipelineConfig(
            base_iterations=base_iterations,
            contrastive_iterations=contrastive_iterations,
            finetune_iterations=finetune_iterations,
        ),
        optimizers={
            "means": {
                "optimizer": FusedAdamOptimizerConfig(lr=1.6e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=base_iterations),
            },
            "features_dc": _adam(0.0025),
            "features_rest": _adam(0.0025 / 20),
            "opacities": _adam(0.05),
            "scales": _adam(0.005),
            "quats": _adam(0.001),
            "features_contrastive": _adam(0.005),
            "sh_offsets": _adam(0.0025),
            "instance_poses": _adam(1e-4),
            "instance_colour": _adam(0.0025),  # log gain per copy and channel: the rate of the colours
            "template_class": _adam(0.0),  # a label carried through densification, never optimised
            "exposure": _adam(1e-3),
            "sky": _adam(0.02),
            "camera_opt": {
                "optimizer": FusedAdamOptimizerConfig(lr=1e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(
                    lr_final=5e-7, max_steps=base_iterations, warmup_steps=1000, lr_pre_warmup=0
                ),
            },
        },
        # the viewer's click controls write into the dataset (masks, clicks.json): this machine only, unless the
        # user opens it with --viewer.websocket-host 0.0.0.0
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15, websocket_host="127.0.0.1"),
        vis="viewer",
    )


splat_replace_method = MethodSpecification(
    config=splat_replace_trainer_config(),
    description=(
        "Splat and Replace: base 3DGS*, contrastive features, one-click 3D instance segmentation, registration "
        "and shared-template fine-tuning of repeated objects (CPU or CUDA)"
    ),
)
