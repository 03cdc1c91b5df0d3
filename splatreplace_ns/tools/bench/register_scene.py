"""The scene ``bench register`` measures on: a trained (or reused) base model, its instances' Gaussians labelled from
the ground-truth masks or from segmentation, and the ground-truth poses; pose errors against them. ``cfg`` is
the command's ``BenchRegisterConfig`` (``tools.bench.register``)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import numpy as np
import torch

from splatreplace_ns.poses.errors import rotation_error_deg, translation_error_rel
from splatreplace_ns.poses.instance import InstanceGaussians
from splatreplace_ns.tools.bench.gt_labels import label_gaussians_from_ground_truth


def rigid_part(pose: np.ndarray) -> Tuple[np.ndarray, float]:
    """Splits a similarity object→world pose into its rigid part and its scale.

    Args:
        pose: [4, 4] ``[s R | t]`` (the dataparser's normalised pose: rotation block scaled by s > 0).
    Returns:
        [4, 4] ``[R | t]`` and s.
    """
    pose = np.asarray(pose, dtype=np.float64)
    scale = float(np.cbrt(np.linalg.det(pose[:3, :3])))
    if not scale > 0:
        raise ValueError(f"pose has a non-positive scale (det {np.linalg.det(pose[:3, :3]):.3g})")
    rigid = pose.copy()
    rigid[:3, :3] /= scale
    return rigid, scale


def pose_errors(
    T_est: np.ndarray, P_source: np.ndarray, P_template: np.ndarray, symmetry: str, bbox_diag: float
) -> Tuple[float, float]:
    """Errors of a registration ``template ≈ T_est · source`` against ground-truth object poses.

    The source's estimated pose is ``T_est⁻¹ · P_template``; it is compared with ``P_source``.

    Args:
        T_est: [4, 4] rigid estimate.
        P_source, P_template: [4, 4] object→world poses (similarities with the same scale s, e.g. in the
            dataparser's normalised frame; s = 1 for rigid poses).
        symmetry: the object's symmetry ("none", "rot_z:N", "rot_z:inf").
        bbox_diag: bounding-box diagonal of the object in object units (the scale s is applied here).
    Returns:
        rotation error (degrees, modulo symmetry), translation error (fraction of the diagonal).
    """
    source, scale = rigid_part(P_source)
    template, _ = rigid_part(P_template)
    estimate = np.linalg.inv(np.asarray(T_est, dtype=np.float64)) @ template
    return (
        rotation_error_deg(estimate, source, symmetry),
        translation_error_rel(estimate, source, bbox_diag * scale),
    )


def scale_intrinsics(Ks: torch.Tensor, from_size: Tuple[int, int], to_size: Tuple[int, int]) -> torch.Tensor:
    """Intrinsics of the same cameras at another image size.

    Args:
        Ks: [V, 3, 3] at ``from_size`` (W, H).
        to_size: (W, H).
    Returns:
        [V, 3, 3] (focal lengths and principal point scaled per axis).
    """
    sx, sy = to_size[0] / from_size[0], to_size[1] / from_size[1]
    scale = torch.tensor([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]], dtype=Ks.dtype, device=Ks.device)
    return scale @ Ks


def match_segments_to_ground_truth(
    seg_labels: torch.Tensor, gt_labels: torch.Tensor
) -> Dict[int, Tuple[Optional[int], float]]:
    """Ground-truth instance of each segmented instance by majority overlap.

    Args:
        seg_labels: [N] segmented instance per Gaussian (0 = background).
        gt_labels: [N] ground-truth instance per Gaussian (0 = background).
    Returns:
        {segmented id: (ground-truth id with the most shared Gaussians, or None when none of its Gaussians
        has a ground-truth instance; the fraction of its Gaussians with that id)}; ties go to the smaller id.
    """
    if seg_labels.shape != gt_labels.shape:
        raise ValueError(f"label shapes differ: {tuple(seg_labels.shape)} vs {tuple(gt_labels.shape)}")
    out: Dict[int, Tuple[Optional[int], float]] = {}
    for seg_id in sorted(int(i) for i in torch.unique(seg_labels) if int(i) > 0):
        inside = gt_labels[seg_labels == seg_id]
        counts = torch.bincount(inside[inside > 0])
        if counts.numel() == 0 or int(counts.max()) == 0:
            out[seg_id] = (None, 0.0)
            continue
        gt_id = int(counts.argmax())
        out[seg_id] = (gt_id, float(counts[gt_id]) / float(inside.numel()))
    return out


@dataclass
class GroundTruthInstance:
    """One instance of the scene: class, symmetry, object→normalised-world pose, class bbox diagonal."""

    id: int
    cls: str
    symmetry: str
    pose: np.ndarray
    """[4, 4] similarity object→world in the model's normalised frame."""
    bbox_diag: float
    """Diagonal of the class mesh's bounding box in object units (metres)."""


@dataclass
class BenchScene:
    """A trained model with what the rows need."""

    pipeline: Any
    data: Path
    config_path: Path
    ground_truth: Dict[int, GroundTruthInstance]
    gt_labels: torch.Tensor
    """[N] ground-truth instance of each Gaussian of the model (0 = background)."""
    time_s: Dict[str, float]
    reused: bool


def scene_folder(cfg) -> Path:
    from splatreplace_ns.tools.bench.scenes import cached_scene

    return cached_scene(cfg.preset, cfg.res, cfg.n_train, cfg.n_test, cfg.data_root, cfg.light)


def shown_path(path: Path) -> str:
    """``path`` relative to the working directory when it lies below it (results stay free of machine paths)."""
    path = Path(path).resolve()
    try:
        return str(path.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def finished_run(config_path: Path) -> bool:
    models = config_path.parent / "nerfstudio_models"
    return config_path.exists() and models.is_dir() and any(models.glob("step-*.ckpt"))


def load_pipeline(config_path: Path, step: Optional[int] = None):
    """A finished run's pipeline (eval mode) from its config.yml, with a clear error when it is not one.

    Args:
        step: the checkpoint step to load (default: the latest).
    """
    from nerfstudio.utils.eval_utils import eval_setup

    config_path = Path(config_path)
    if not finished_run(config_path):
        raise FileNotFoundError(
            f"{config_path}: not a finished run (need config.yml with nerfstudio_models/step-*.ckpt beside it)"
        )
    update = None
    if step is not None:
        ckpt = config_path.parent / "nerfstudio_models" / f"step-{step:09d}.ckpt"
        if not ckpt.exists():
            have = sorted(p.name for p in ckpt.parent.glob("step-*.ckpt"))
            raise FileNotFoundError(f"{ckpt}: no checkpoint of step {step} (the run has {', '.join(have)})")

        def update(config):
            config.load_step = step
            return config

    _, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=update)
    pipeline.eval()
    return pipeline


def train_or_load_base(cfg, data: Path) -> Tuple[Any, Path, float, bool]:
    """The base-stage model of the preset: reused from ``out_dir`` when finished there, else trained.

    Returns:
        pipeline (eval mode), its config.yml, seconds spent (training or loading), whether it was reused.
    """
    from splatreplace_ns.method.train import make_trainer_config, run_training

    name = f"base_{data.name}_{cfg.base_iterations}it"
    out = (cfg.out_dir / cfg.preset).resolve()
    config = make_trainer_config(
        data.resolve(), out, cfg.base_iterations, contrastive_iterations=0, experiment_name=name
    )
    config_path = config.get_base_dir() / "config.yml"
    t0 = time.perf_counter()
    if finished_run(config_path):
        return load_pipeline(config_path), config_path, time.perf_counter() - t0, True
    trainer = run_training(config)
    pipeline = trainer.pipeline
    pipeline.eval()
    return pipeline, config_path, time.perf_counter() - t0, False


def ground_truth_instances(pipeline) -> Dict[int, GroundTruthInstance]:
    """The dataset's instances with their poses in the model's normalised frame."""
    from splatreplace_ns.tools.sim import class_mesh

    out = {}
    diag_of: Dict[str, float] = {}
    for inst in pipeline.datamanager.train_dataparser_outputs.metadata.get("instances", []):
        if "transform_matrix" not in inst:
            raise ValueError(f"instance {inst['id']} has no ground-truth transform_matrix in transforms.json")
        cls = inst["class"]
        if cls not in diag_of:
            diag_of[cls] = float(np.linalg.norm(class_mesh(cls).get_axis_aligned_bounding_box().get_extent()))
        out[int(inst["id"])] = GroundTruthInstance(
            int(inst["id"]), cls, inst.get("symmetry", "none"), inst["transform_matrix"].double().numpy(), diag_of[cls]
        )
    if not out:
        raise ValueError("the dataset lists no instances (transforms.json 'instances')")
    return out


def instance_gaussians(
    model, labels: torch.Tensor, ids, sh_degree: Optional[int]
) -> Dict[int, InstanceGaussians]:
    """The Gaussians of each labelled instance, activated (linear scales, opacities in [0, 1]), SH colours.

    Args:
        model: a SplatReplaceModel.
        labels: [N] instance per Gaussian.
        ids: instance ids to extract.
        sh_degree: SH degree the model renders with (None: plain RGB from sigmoid(features_dc)).
    """
    with torch.no_grad():
        means = model.means.detach().cpu()
        quats = model.quats.detach().cpu()
        scales = torch.exp(model.scales.detach().cpu())
        opacities = torch.sigmoid(model.opacities.detach().cpu()).squeeze(-1)
        if sh_degree is None:
            colors = torch.sigmoid(model.features_dc.detach().cpu())
        else:
            sh = torch.cat([model.features_dc.detach().cpu()[:, None, :], model.features_rest.detach().cpu()], dim=1)
            colors = sh[:, : (sh_degree + 1) ** 2]
    labels = labels.cpu()
    out = {}
    for iid in ids:
        keep = labels == int(iid)
        out[int(iid)] = InstanceGaussians(
            means[keep], quats[keep], scales[keep], opacities[keep], colors[keep], sh_degree=sh_degree, id=int(iid)
        )
    return out


def model_sh_degree(pipeline) -> Optional[int]:
    """SH degree the model renders with after its base stage (splatfacto raises it every interval)."""
    model_cfg = pipeline.model.config
    if model_cfg.sh_degree <= 0:
        return None
    steps = int(pipeline.config.base_iterations)
    return min(steps // model_cfg.sh_degree_interval, model_cfg.sh_degree)


def load_bench_scene(cfg) -> BenchScene:
    """Scene, base model (trained or reused), ground-truth poses and ground-truth labels of the Gaussians."""
    torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
    t0 = time.perf_counter()
    data = scene_folder(cfg)
    sim_s = time.perf_counter() - t0
    pipeline, config_path, train_s, reused = train_or_load_base(cfg, data)
    t1 = time.perf_counter()
    gt_labels = label_gaussians_from_ground_truth(pipeline, cfg.depth_tolerance)
    return BenchScene(
        pipeline, data, config_path, ground_truth_instances(pipeline), gt_labels,
        {"sim": sim_s, "load" if reused else "train": train_s, "labels": time.perf_counter() - t1}, reused,
    )
