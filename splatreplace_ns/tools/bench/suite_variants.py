"""``bench suite``'s configurations: the regime, the variant's label and run folder, ours' settings; and the variants
that reuse the defaults' run of a scene: resumed from its segmentation (``--from-segmentation``), or trained whole
against its baseline (``--reuse-baseline``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Dict, Tuple

import torch

from splatreplace_ns.tools.bench.user_inputs import scene_of


def regime(cfg: "BenchSuiteConfig") -> str:
    """The ``user_inputs`` regime of a configuration: ``--inputs``, or ``user+colmap`` with ``--poses colmap``."""
    if cfg.poses == "exact":
        return cfg.inputs
    if cfg.inputs != "user":
        raise ValueError(f"--poses colmap goes with --inputs user (COLMAP poses a user's photos), not {cfg.inputs}")
    return "user+colmap"


def variant_label(cfg: "BenchSuiteConfig") -> str:
    """The empty string for the defaults; else what differs, e.g. ``reg-paper`` or
    ``reg-ours+pipeline.revert.enabled=False``."""
    parts = [] if cfg.registration == "ours" and not cfg.overrides else [f"reg-{cfg.registration}", *cfg.overrides]
    return "+".join(parts + ([f"oracle-{cfg.oracle}"] if cfg.oracle else []))


def run_folder(cfg: "BenchSuiteConfig", data_name: str, default: bool = False) -> Path:
    """The folder of one scene's runs (ours, baseline, result.json) for this configuration, or with
    ``default=True`` for the defaults at the same budget."""
    B, C, F = cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations
    label = "" if default else variant_label(cfg)
    safe = "".join(c if c.isalnum() or c in "-_.=+" else "_" for c in label)
    seed = "" if cfg.training_seed is None else f"_seed{cfg.training_seed}"
    inputs = "" if regime(cfg) == "exact" else f"_{regime(cfg).replace('+', '-')}"
    return cfg.out_dir / (f"{data_name}{inputs}_{B}-{C}-{F}" + (f"_{safe}" if safe else "") + seed)


def configure_ours(cfg: "BenchSuiteConfig"):
    """``configure(trainer_config)``: ours' registration variant and overrides (nothing for the defaults)."""
    from splatreplace_ns.tools.bench.overrides import apply_overrides
    from splatreplace_ns.method.config import splat_replace_trainer_config
    from splatreplace_ns.poses.variants import registration_variant

    # an unknown variant or override stops here, before anything trains
    trial = apply_overrides(splat_replace_trainer_config(1, 1, 1), cfg.overrides)
    registration_variant(cfg.registration, trial.pipeline.registration)

    def configure(trainer_config) -> None:
        pipeline = trainer_config.pipeline
        pipeline.registration = registration_variant(cfg.registration, pipeline.registration)
        apply_overrides(trainer_config, cfg.overrides)

    return configure


def finetune_length(cfg: "BenchSuiteConfig") -> int:
    """Fine-tuning steps of ours: ``--finetune-iterations``, or ``pipeline.finetune_iterations`` where an override
    sets it (a variant of the fine-tuning length resumed from the defaults' segmentation at the same budget)."""
    from splatreplace_ns.method.config import splat_replace_trainer_config
    from splatreplace_ns.tools.bench.overrides import apply_overrides

    trial = splat_replace_trainer_config(cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations)
    return int(apply_overrides(trial, cfg.overrides).pipeline.finetune_iterations)


def forget_click_masks(data: Path) -> None:
    """Removes the masks an earlier run made from the clicks in a folder without masks of its own, so that ours
    makes them again from its own base model (and the masks stage's time is counted)."""
    from splatreplace_ns.datamanager.click_masks import MASKS_DIR

    if (data / MASKS_DIR).is_dir() and not (data / MASKS_DIR).is_symlink():
        import shutil

        shutil.rmtree(data / MASKS_DIR)


def train_variant_from_segmentation(data: Path, cfg: "BenchSuiteConfig") -> Dict:
    """Ours with the variant's settings, resumed from the defaults' run of this scene at the end of segmentation;
    the baseline's metrics and the segmentation's score are that run's (the same segmentation). → the fields of
    ``train_ours_and_baseline``'s result the suite reads, with ``segmentation`` and the ``stages`` of this run
    (base, contrastive and segmentation 0; fine-tuning includes loading and evaluating).

    Raises:
        FileNotFoundError: when the defaults' run or its checkpoint at the end of segmentation is missing.
    """
    from splatreplace_ns.tools.bench.template import _run, test_metrics
    from splatreplace_ns.method.train import make_trainer_config

    if not variant_label(cfg):
        raise ValueError("--from-segmentation needs a variant (--registration or --overrides)")
    B, C, F = cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations
    default = run_folder(cfg, scene_of(data, regime(cfg)).name, default=True)
    checkpoints = default / "ours" / "splat-replace" / "run" / "nerfstudio_models"
    if not (checkpoints / f"step-{B + C - 1:09d}.ckpt").exists():
        raise FileNotFoundError(
            f"{default}: no run with the defaults that kept its checkpoint at the end of segmentation (step "
            f"{B + C - 1}); run `splatreplace bench suite` with the same split, scenes and budget first")
    previous, baseline = defaults_baseline(data, cfg)
    # an override of the fine-tuning length (pipeline.finetune_iterations) sets how many steps are left to run
    F = finetune_length(cfg)
    config = make_trainer_config(data, run_folder(cfg, scene_of(data, regime(cfg)).name), B, C, F, experiment_name="ours", progress=True,
                                 resume_from=(checkpoints, B + C - 1))
    configure_ours(cfg)(config)
    before = None
    if cfg.oracle:
        from splatreplace_ns.tools.bench.oracle import use_ground_truth

        def before(trainer) -> None:
            use_ground_truth(trainer.pipeline, instances_too=cfg.oracle == "gt_instances")

    torch.set_num_threads(os.cpu_count() or 1)  # ours alone
    trainer, seconds = _run(config, before)
    pipeline = trainer.pipeline
    registration_s = float(pipeline.registration_report.get("time_s", float("nan")))
    segmentation = {"miou": previous.get("segmentation_miou"), "unavailable": previous.get("segmentation_unavailable")}
    if cfg.oracle == "gt_instances":  # the defaults' segmentation is not the one fine-tuned here
        segmentation = {"unavailable": "the instances are the ground truth's (--oracle gt_instances)"}
    return {"ours": test_metrics(pipeline), "baseline": baseline, "ours_trainer": trainer, "parallel": False,
            "segmentation": {k: v for k, v in segmentation.items() if v is not None},
            "times": {"ours": seconds, "baseline": previous["time_s"]["baseline"]},
            "stages": {"base": 0.0, "contrastive": 0.0, "segmentation": 0.0, "registration": registration_s,
                       "finetune": seconds - registration_s, "setup_and_eval": 0.0}}


def defaults_baseline(data: Path, cfg: "BenchSuiteConfig") -> Tuple[Dict, Dict]:
    """The row of the same scene's run with the defaults at the same budget, and its baseline's metrics (with the
    per-instance PSNR), for a variant that reuses them.

    Raises:
        FileNotFoundError: when that run has no result.json.
    """
    from splatreplace_ns.eval.coverage_scores import baseline_coverage

    default = run_folder(cfg, scene_of(data, regime(cfg)).name, default=True)
    saved = default / "result.json"
    if not saved.exists():
        raise FileNotFoundError(f"{default}: no run with the defaults; run `splatreplace bench suite` with the same "
                                "split, scenes and budget first")
    previous = json.loads(saved.read_text())["row"]
    baseline = dict(previous["baseline"])
    baseline["psnr_per_instance"] = {k: v["baseline"] for k, v in previous["per_instance"].items()}
    if previous.get("coverage") and "unavailable" not in previous["coverage"]:  # absent from older results
        baseline["coverage"] = baseline_coverage(previous["coverage"])  # with "sharp" where it was measured
    return previous, baseline


def train_variant_reusing_baseline(data: Path, cfg: "BenchSuiteConfig", clock: "StageClock") -> Dict:
    """Ours with the variant's settings trained whole (from step 0) in this process, against the baseline of the
    defaults' run of this scene. → the fields of ``train_ours_and_baseline``'s result the suite reads."""
    from splatreplace_ns.tools.bench.template import _run, test_metrics
    from splatreplace_ns.method.train import make_trainer_config

    if not variant_label(cfg):
        raise ValueError("--reuse-baseline needs a variant (--registration or --overrides)")
    previous, baseline = defaults_baseline(data, cfg)
    forget_click_masks(data)  # a variant of an earlier stage makes its own masks, from its own base model
    config = make_trainer_config(data, run_folder(cfg, scene_of(data, regime(cfg)).name), cfg.base_iterations, cfg.contrastive_iterations,
                                 cfg.finetune_iterations, experiment_name="ours", progress=True)
    configure_ours(cfg)(config)
    trainer, seconds = _run(config, after_step=clock)
    pipeline = trainer.pipeline
    times = {"ours": seconds, "baseline": previous["time_s"]["baseline"],
             "segmentation": float(pipeline.segmentation_report.get("time_s", float("nan"))),
             "registration": float(pipeline.registration_report.get("time_s", float("nan")))}
    return {"ours": test_metrics(pipeline), "baseline": baseline, "ours_trainer": trainer, "parallel": False,
            "times": times}
