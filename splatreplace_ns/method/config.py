"""``ns-train splat-replace``: the method specification registered with nerfstudio."""

from __future__ import annotations

import torch

from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from splatreplace_ns.datamanager.datamanager import SplatReplaceDataManagerConfig
from splatreplace_ns.method.model import SplatReplaceModelConfig


def _adam(lr: float) -> dict:
    return {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15), "scheduler": None}


def splat_replace_trainer_config(max_num_iterations: int = 30000) -> TrainerConfig:
    """The full trainer configuration (also used in-process by the CLI, tests and benchmarks)."""
    return TrainerConfig(
        method_name="splat-replace",
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=max_num_iterations,
        mixed_precision=False,
        # CPU-first: pick the device that exists so `ns-train splat-replace --data DIR` just works.
        machine=MachineConfig(device_type="cuda" if torch.cuda.is_available() else "cpu"),
        pipeline=VanillaPipelineConfig(
            datamanager=SplatReplaceDataManagerConfig(),
            model=SplatReplaceModelConfig(),
        ),
        optimizers={
            "means": {
                "optimizer": AdamOptimizerConfig(lr=1.6e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max_num_iterations),
            },
            "features_dc": _adam(0.0025),
            "features_rest": _adam(0.0025 / 20),
            "opacities": _adam(0.05),
            "scales": _adam(0.005),
            "quats": _adam(0.001),
            "exposure": _adam(1e-3),
            "camera_opt": {
                "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(
                    lr_final=5e-7, max_steps=max_num_iterations, warmup_steps=1000, lr_pre_warmup=0
                ),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


splat_replace_method = MethodSpecification(
    config=splat_replace_trainer_config(),
    description="Splat and Replace: shared Gaussian templates for repeated objects (base 3DGS* stage on CPU or CUDA)",
)
