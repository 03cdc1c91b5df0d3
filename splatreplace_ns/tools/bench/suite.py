"""``splatreplace bench suite``: the whole method against the 3DGS* baseline on a split of random scenes.

The yardstick the method is measured by (the named presets stay as regression scenes). Scenes come from
``splatreplace sim random`` (:mod:`splatreplace_ns.tools.sim.random_scenes`), in two splits:

* ``dev``: seeds 0–99. Rules and thresholds are chosen on these.
* ``report``: the fixed seeds :data:`REPORT_SEEDS`. Never used to choose anything; the README's headline figures
  come from it.

For every scene, ours (base → contrastive → segmentation → registration → shared templates → fine-tuning) and the
baseline (3DGS*, the same total iterations) train side by side (one core each), and the row gives masked and full
PSNR of both on the test views, the gain, masked SSIM, segmentation mIoU, registration errors and failures, and the
time of every stage. The summary gives the mean gain, the worst scene's gain and the share of scenes where ours is
worse; a plot shows the gain per scene, sorted.
"""

from __future__ import annotations

import gc
import json
import os
import platform
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import torch

from splatreplace_ns.tools.bench.output import publish, write_result_json
from splatreplace_ns.tools.bench.suite_output import WRONG_POSE_DEG, print_suite, write_gain_plot
from splatreplace_ns.tools.bench.stage_clock import StageClock
from splatreplace_ns.tools.bench.suite_variants import (  # noqa: F401  (regime, run_folder: part of this module's API)
    configure_ours, forget_click_masks, regime, run_folder, train_variant_from_segmentation,
    train_variant_reusing_baseline, variant_label,
)
from splatreplace_ns.tools.bench.user_inputs import inputs_report, make_regime_folder
from splatreplace_ns.tools.demo import DemoCommand

DEV_SEEDS: Tuple[int, ...] = tuple(range(100))
REPORT_SEEDS: Tuple[int, ...] = tuple(range(10000, 10008))
QUICK = {"scenes": 4, "res": "96x72"}
"""``--quick``: the first 4 dev scenes at 96x72 (same budget), for iterating."""


@dataclass
class BenchSuiteConfig:
    """Ours vs the 3DGS* baseline on every scene of a split of random scenes: one row per scene and a summary."""

    split: Literal["dev", "report"] = "dev"
    """dev: seeds 0-99 (choose rules and thresholds here); report: seeds 10000-10007 (only report them)."""
    scenes: Optional[int] = None
    """Run the first N scenes of the split (default: 8, the whole report split)."""
    seeds: Optional[Tuple[int, ...]] = None
    """Run these seeds of the split instead (each must belong to it)."""
    quick: bool = False
    """The first 4 dev scenes at 96x72 (overrides --scenes and --res)."""
    res: str = DemoCommand.res
    """Image size WxH of the generated scenes (default: the demo's)."""
    n_train: int = DemoCommand.n_train
    """Training views per scene."""
    n_test: int = DemoCommand.n_test
    """Test views per scene."""
    base_iterations: int = DemoCommand.base_iterations
    """Base 3DGS* iterations of ours (default: the demo's budget; the baseline gets base + contrastive + finetune)."""
    contrastive_iterations: int = DemoCommand.contrastive_iterations
    """Contrastive-feature iterations of ours."""
    finetune_iterations: int = DemoCommand.finetune_iterations
    """Shared-template fine-tuning iterations of ours."""
    json: Optional[Path] = None
    """Where to write the results as JSON (and the plot beside it as PNG)."""
    plot: Optional[Path] = None
    """Gain-per-scene plot (default: beside --json, else benchmarks/results/suite_<split>.png)."""
    data_root: Path = Path("benchmarks/data/suite")
    """Generated scenes are kept here and reused."""
    out_dir: Path = Path("benchmarks/runs/suite")
    """Training outputs, one folder per scene and configuration (with that scene's result.json)."""
    resume: bool = False
    """Reuse a scene's result.json from an earlier run of the same configuration instead of training it again."""
    sequential: bool = False
    """Train the baseline after ours instead of beside it (beside: each on half of the CPU cores)."""
    registration: str = "ours"
    """Registration rule of ours (``splatreplace_ns.poses.variants``): ours (the defaults), paper (§4.2 as
    written: most PnP inliers, rigid ICP, no added rule), or the defaults less one rule: no_upright,
    no_multistart, no_icp, no_fine_turns, no_image_choice (the colour score and the thresholds choose instead of
    the training images), no_lone_copies_rule (a class's one registered copy is replaced too), no_doubt_check
    (no shape's veto on an accepted pose)."""
    overrides: Tuple[str, ...] = ()
    """Settings of ours' trainer config as PATH=VALUE, e.g. pipeline.revert.enabled=False (the baseline keeps its own)."""
    from_segmentation: bool = False
    """For a variant (--registration or --overrides): resume ours from the checkpoint at the end of segmentation
    of the same scene's run with the defaults at the same budget, and reuse that run's baseline, so a variant of
    registration or of a later stage costs its registration and fine-tuning alone. Run the defaults first."""
    reuse_baseline: bool = False
    """For a variant of segmentation or of an earlier stage: train ours whole, alone, and take the baseline's
    figures from the same scene's run with the defaults at the same budget (run the defaults first). Two variants
    started side by side with OMP_NUM_THREADS=1 each run as ours and the baseline do in the suite."""
    oracle: Optional[Literal["gt_poses", "gt_instances"]] = None
    """With --from-segmentation: replace stages by the scene's ground truth (``splatreplace_ns.tools.bench.oracle``).
    gt_poses registers every instance with the pose its transforms.json implies; gt_instances also labels the
    Gaussians from its masks. What fine-tuning reaches when the stages before it are exact: the ceiling of the
    representation at this budget, and the share of the gap each stage leaves."""
    inputs: Literal["exact", "user", "user+masks", "user+depth", "user+points"] = "exact"
    """What both methods are given (``splatreplace_ns.tools.bench.user_inputs``). exact: the images, camera poses and
    clicks, plus the true instance masks and depth of every frame and a point cloud from the true depth. user: what a
    user has: images, camera poses and clicks.json, COLMAP's sparse points; the true masks of the test views only
    score. user+masks / user+depth / user+points: the user's regime with that one exact input given back."""
    poses: Literal["exact", "colmap"] = "exact"
    """Camera poses both methods train with: the scene's (exact) or COLMAP's, from ``ns-process-data`` on the training
    images (colmap, with --inputs user: intrinsics and sparse cloud COLMAP's too; the true test cameras are moved into
    COLMAP's frame to score, ``splatreplace_ns.tools.bench.colmap_poses``)."""
    training_seed: Optional[int] = None
    """Training seed of ours and the baseline: nerfstudio's machine.seed and the order the training views are drawn
    in (default: nerfstudio's 42). The same scenes trained again with another seed give the suite's run-to-run
    spread; the runs go to folders of their own."""

    def main(self) -> Dict:
        return publish(run_suite(self), print_suite, self.json, self.plot,
                       Path(f"benchmarks/results/suite_{self.split}.png"), write_gain_plot)


def split_seeds(cfg: BenchSuiteConfig) -> List[int]:
    """The seeds a configuration runs, checked against its split."""
    pool = DEV_SEEDS if cfg.split == "dev" else REPORT_SEEDS
    if cfg.quick:
        if cfg.split != "dev":
            raise ValueError("--quick is a subset of the dev split; the report split always runs whole")
        return list(pool[: QUICK["scenes"]])
    if cfg.seeds:
        foreign = [s for s in cfg.seeds if s not in pool]
        if foreign:
            raise ValueError(f"seeds {foreign} are not in the {cfg.split} split ({pool[0]}-{pool[-1]})")
        return list(cfg.seeds)
    count = 8 if cfg.scenes is None else cfg.scenes
    if not 1 <= count <= len(pool):
        raise ValueError(f"--scenes must be between 1 and {len(pool)} for the {cfg.split} split, got {count}")
    return list(pool[:count])


def scene_name(seed: int, res: str, n_train: int, n_test: int) -> str:
    """Folder name of a generated suite scene, e.g. ``random_7_128x96_48v8``."""
    return f"random_{seed}_{res}_{n_train}v{n_test}"


def cached_random_scene(seed: int, res: str, n_train: int, n_test: int, root: Path) -> Path:
    """``root/<scene_name>``, generated when absent or written by an older generator."""
    from splatreplace_ns.tools.sim import is_current_scene, make_scene

    data = Path(root) / scene_name(seed, res, n_train, n_test)
    if not is_current_scene(data):
        make_scene("random", data, res=res, seed=seed, n_train=n_train, n_test=n_test)
    return data


def _registration_summary(report: Optional[Dict], model_registration: Dict) -> Dict:
    """Mean and max rotation error of the accepted registrations, failures (not accepted) and wrong ones
    (accepted but more than WRONG_POSE_DEG off)."""
    failures = sorted(int(k) for k, v in model_registration.items() if not v["success"])
    # put back by the check after fine-tuning (also among the failures)
    reverted = sorted(int(k) for k, v in model_registration.items() if (v.get("check_after_finetune") or {}).get("revert"))
    if not report:
        return {"rotation_error_deg_mean": None, "rotation_error_deg_max": None, "failures": failures, "wrong": [],
                "reverted": reverted, "per_instance": []}
    rows = [r for r in report["per_instance"] if r["success"]]
    errors = [r["rotation_error_deg"] for r in rows if r["rotation_error_deg"] is not None]
    refused = [r for r in report["per_instance"] if not r["success"] and r.get("proposed_rotation_error_deg") is not None]
    return {
        "rotation_error_deg_mean": statistics.fmean(errors) if errors else None,
        "rotation_error_deg_max": max(errors) if errors else None,
        "failures": failures,
        "reverted": reverted,
        "wrong": [r["gt_id"] for r in rows if r["rotation_error_deg"] is not None and r["rotation_error_deg"] > WRONG_POSE_DEG],
        # what the acceptance test refused: poses within WRONG_POSE_DEG of the truth, and the others
        "refused_right": [r["gt_id"] for r in refused if r["proposed_rotation_error_deg"] <= WRONG_POSE_DEG],
        "refused_wrong": [r["gt_id"] for r in refused if r["proposed_rotation_error_deg"] > WRONG_POSE_DEG],
        "per_instance": report["per_instance"],
    }


def run_scene(seed: int, cfg: BenchSuiteConfig, res: str) -> Dict:
    """Generate (or reuse) one scene, train ours and the baseline, and score both."""
    from splatreplace_ns.tools.bench.template import test_metrics, train_ours_and_baseline
    from splatreplace_ns.eval.coverage_scores import compare_coverage
    from splatreplace_ns.eval.report import registration_report, segmentation_report
    from splatreplace_ns.tools.sim.scene import class_size

    B, C, F = cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations
    start = time.perf_counter()
    scene = cached_random_scene(seed, res, cfg.n_train, cfg.n_test, cfg.data_root)
    meta = json.loads((scene / "transforms.json").read_text())
    try:
        data = make_regime_folder(scene, regime(cfg))  # what both methods are given
    except RuntimeError as err:  # COLMAP could not pose the photos: a user would have no dataset to train on
        if cfg.poses != "colmap":
            raise
        print(f"[suite] seed {seed}: {err}", flush=True)
        return unposed_row(seed, meta, cfg, str(err), time.perf_counter() - start)
    sim_s = time.perf_counter() - start
    segmentation: Dict = {}

    def score_segmentation(trainer) -> None:  # the selected instances' masks in the test views, before replacement
        report, why_not = segmentation_report(trainer.pipeline)
        segmentation.update(report or {"unavailable": why_not})

    clock = StageClock(B, C, F, at_segmentation=score_segmentation)
    if cfg.from_segmentation:
        pair = train_variant_from_segmentation(data, cfg)
        segmentation.update(pair["segmentation"])
    elif cfg.reuse_baseline:
        pair = train_variant_reusing_baseline(data, cfg, clock)
    else:
        forget_click_masks(data)
        pair = train_ours_and_baseline(data, run_folder(cfg, scene.name), B, C, F, resumable=True,
                                       parallel=not cfg.sequential, after_step=clock, configure=configure_ours(cfg),
                                       seed=cfg.training_seed)
    pipeline = pair["ours_trainer"].pipeline
    registration, _ = registration_report(pipeline, class_size)
    times = pair["times"]
    stages = pair.get("stages") or clock.stages(times["ours"], times.get("segmentation", 0.0),
                                                times.get("registration", 0.0))
    ours, baseline = pair["ours"], pair["baseline"]
    per_instance = {}
    for key, value in (ours.get("psnr_per_instance") or {}).items():
        base_value = (baseline.get("psnr_per_instance") or {}).get(key)
        if key != "0" and base_value is not None:
            per_instance[key] = {"baseline": base_value, "ours": value, "gain": value - base_value}
    row = {
        "seed": seed,
        "scene": meta["sim"]["scene"],
        "effects": [k for k, v in meta["sim"]["effects"].items() if v],
        "instances": len(meta["instances"]),
        "inputs": cfg.inputs,
        **({"poses": cfg.poses} if cfg.poses != "exact" else {}),
        **({"sparse_points": inputs_report(data).get("sparse_points")} if cfg.inputs != "exact" else {}),
        **({"colmap": inputs_report(data).get("colmap")} if cfg.poses == "colmap" else {}),
        "baseline": {k: baseline.get(k) for k in ("psnr", "psnr_masked", "ssim", "ssim_masked")},
        "ours": {k: ours.get(k) for k in ("psnr", "psnr_masked", "ssim", "ssim_masked")},
        "gain_masked": _diff(ours.get("psnr_masked"), baseline.get("psnr_masked")),
        "gain_full": _diff(ours.get("psnr"), baseline.get("psnr")),
        "per_instance": per_instance,
        "coverage": compare_coverage(baseline.get("coverage"), ours.get("coverage")),  # own / shared / unseen pixels
        "segmentation_miou": segmentation.get("miou"),
        "segmentation_unavailable": segmentation.get("unavailable"),
        "registration": _registration_summary(registration, pipeline.model.registration),
        "replaced": pipeline.model.has_templates,
        "time_s": {"sim": sim_s, **stages, "ours": times["ours"], "baseline": times["baseline"],
                   "total": time.perf_counter() - start},
        "baseline_beside_ours": pair["parallel"],
        "variant": variant_label(cfg) or "defaults",
        "resumed_from_segmentation": cfg.from_segmentation,
        "baseline_reused": cfg.from_segmentation or cfg.reuse_baseline,
    }
    del pair, pipeline
    gc.collect()
    return row


def unposed_row(seed: int, meta: Dict, cfg: BenchSuiteConfig, error: str, seconds: float) -> Dict:
    """The row of a scene COLMAP could not pose (``--poses colmap``): no run, no figure, and why."""
    empty = {k: None for k in ("psnr", "psnr_masked", "ssim", "ssim_masked")}
    return {"seed": seed, "scene": meta["sim"]["scene"], "effects": [k for k, v in meta["sim"]["effects"].items() if v],
            "instances": len(meta["instances"]), "inputs": cfg.inputs, "poses": cfg.poses,
            "error": error.splitlines()[0][:300], "baseline": dict(empty), "ours": dict(empty), "gain_masked": None,
            "gain_full": None, "per_instance": {}, "coverage": None, "segmentation_miou": None,
            "segmentation_unavailable": "COLMAP posed no dataset", "registration": _registration_summary(None, {}),
            "replaced": False, "time_s": {**{k: 0.0 for k in ("base", "contrastive", "segmentation", "registration",
                                                               "finetune", "ours", "baseline")}, "total": seconds},
            "variant": variant_label(cfg) or "defaults"}


def _diff(a: Optional[float], b: Optional[float]) -> Optional[float]:
    return None if a is None or b is None else a - b


def summarise(rows: List[Dict]) -> Dict:
    """Mean gain, worst scene's gain, share of scenes where ours is worse (masked PSNR), and the same for full
    images; instances that lost more than 1 dB; wrong or failed registrations; the mean gain on own, shared and
    unseen pixels, by visibility and by being seen well."""
    from splatreplace_ns.eval.coverage_scores import mean_coverage_gains

    masked = [r["gain_masked"] for r in rows if r["gain_masked"] is not None]
    full = [r["gain_full"] for r in rows if r["gain_full"] is not None]
    losses = [{"seed": r["seed"], "instance": int(k), "gain": v["gain"]}
              for r in rows for k, v in r["per_instance"].items() if v["gain"] < -1.0]
    return {
        "scenes": len(rows),
        **({"not_posed": [r["seed"] for r in rows if "error" in r]} if any("error" in r for r in rows) else {}),
        "gain_masked_mean": statistics.fmean(masked) if masked else None,
        "gain_masked_worst": min(masked) if masked else None,
        "share_worse_masked": sum(g < 0 for g in masked) / len(masked) if masked else None,
        "gain_full_mean": statistics.fmean(full) if full else None,
        "gain_full_worst": min(full) if full else None,
        "share_worse_full": sum(g < 0 for g in full) / len(full) if full else None,
        "instances_losing_over_1db": losses,
        "wrong_registrations": sum(len(r["registration"]["wrong"]) for r in rows),
        "failed_registrations": sum(len(r["registration"]["failures"]) for r in rows),
        "refused_right": sum(len(r["registration"].get("refused_right", [])) for r in rows),
        "refused_wrong": sum(len(r["registration"].get("refused_wrong", [])) for r in rows),
        "reverted": sum(len(r["registration"].get("reverted", [])) for r in rows),
        "coverage_gain_mean": mean_coverage_gains([r.get("coverage") for r in rows]),
        "coverage_sharp_gain_mean": mean_coverage_gains([(r.get("coverage") or {}).get("sharp") for r in rows]),
        "segmentation_miou_mean": statistics.fmean(m) if (m := [r["segmentation_miou"] for r in rows
                                                                if r["segmentation_miou"] is not None]) else None,
    }


def run_suite(cfg: BenchSuiteConfig) -> Dict:
    from splatreplace_ns.eval.report import versions

    seeds = split_seeds(cfg)
    regime(cfg)  # a regime that does not exist stops here
    res = QUICK["res"] if cfg.quick else cfg.res
    cores = os.cpu_count() or 1
    torch.set_num_threads(max(1, cores if cfg.sequential else cores // 2))
    t0 = time.perf_counter()
    configuration = {"res": res, "n_train": cfg.n_train, "n_test": cfg.n_test, "base_iterations": cfg.base_iterations,
                     "contrastive_iterations": cfg.contrastive_iterations,
                     "finetune_iterations": cfg.finetune_iterations, "registration": cfg.registration,
                     "overrides": list(cfg.overrides), "from_segmentation": cfg.from_segmentation,
                     **({"reuse_baseline": True} if cfg.reuse_baseline else {}),
                     **({"inputs": cfg.inputs} if cfg.inputs != "exact" else {}),
                     **({"poses": cfg.poses} if cfg.poses != "exact" else {}),
                     **({"training_seed": cfg.training_seed} if cfg.training_seed is not None else {})}
    if cfg.oracle is not None:
        configuration["oracle"] = cfg.oracle
        if not cfg.from_segmentation:
            raise ValueError("--oracle replaces the stages after segmentation's checkpoint: it needs "
                             "--from-segmentation (run the defaults first)")
    if cfg.training_seed is not None and (cfg.reuse_baseline or cfg.from_segmentation):
        raise ValueError("--training-seed trains ours and the baseline again; it does not combine with "
                         "--reuse-baseline or --from-segmentation (they reuse the runs of the default seed)")
    rows = []
    for k, seed in enumerate(seeds):
        saved = run_folder(cfg, scene_name(seed, res, cfg.n_train, cfg.n_test)) / "result.json"
        if cfg.resume and saved.exists():
            previous = json.loads(saved.read_text())
            if previous.get("configuration") == configuration:
                print(f"[suite] scene {k + 1}/{len(seeds)} (seed {seed}): reusing {saved}", flush=True)
                rows.append(previous["row"])
                continue
        print(f"[suite] scene {k + 1}/{len(seeds)} (seed {seed}) ...", flush=True)
        row = run_scene(seed, cfg, res)
        write_result_json({"configuration": configuration, "row": row}, saved)
        rows.append(row)
        g = row["gain_masked"]
        print(f"[suite] seed {seed}: masked gain {'n/a' if g is None else f'{g:+.2f} dB'} "
              f"({row['time_s']['total']:.0f} s)", flush=True)
    return {
        "benchmark": "suite",
        "split": cfg.split,
        "seeds": seeds,
        "quick": cfg.quick,
        "variant": variant_label(cfg) or "defaults",
        "parameters": {**configuration, "baseline_iterations": cfg.base_iterations + cfg.contrastive_iterations
                       + cfg.finetune_iterations, "sequential": cfg.sequential},
        "scenes": rows,
        "summary": summarise(rows),
        "time_s": sum(row["time_s"]["total"] for row in rows),  # every scene's, those reused by --resume too
        "wall_s_this_run": time.perf_counter() - t0,
        "machine": {"platform": platform.platform(), "cpu_count": cores, "cuda": torch.cuda.is_available()},
        "versions": versions(),
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()},
    }
