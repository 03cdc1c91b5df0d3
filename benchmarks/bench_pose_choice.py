"""How the choice of a pose against the training images decides, scored against the truth, per way of scoring.

For each dev scene it loads the defaults' suite run at the end of segmentation (the checkpoint `splatreplace bench
suite` keeps) and the candidate poses registration proposed there (from the run's last checkpoint), then re-runs
only the choice among those candidates (`SplatReplacePipeline.choose_poses_by_images`) once per variant of its
settings, and counts against the scene's ground-truth poses: poses accepted within 5° of the truth (modulo the
class's symmetry), accepted further off, refused although the chosen candidate was right, and the other refusals.
No training: a variant costs the choice's renders only (seconds per instance), so the counts say which settings
are worth a full `bench suite --from-segmentation` run, whose masked gains decide.

    splatreplace bench suite --split dev --seeds 0 1 2 3 4 5 6 7 8 --res 96x72    # the defaults' runs, once
    python benchmarks/bench_pose_choice.py --seeds 0 1 2 3 4 5 6 7 8
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import tyro

from splatreplace_ns.tools.bench.output import write_result_json

WRONG_POSE_DEG = 5.0
"""As the suite counts a wrong pose (``splatreplace_ns.tools.bench.suite.WRONG_POSE_DEG``)."""

VARIANTS: Dict[str, Dict[str, str]] = {
    "defaults": {},
    "per_view": {"image_score": "per_view"},
    "pair": {"image_margin_pixels": "pair"},
    "pair+per_view": {"image_margin_pixels": "pair", "image_score": "per_view"},
    "no_upright": {"upright": False},  # the chosen candidate kept as rigid ICP placed it, not polished
    "no_fine_turns": {"image_fine_turns_deg": ()},  # the leading poses not tried again turned by 4 and 8 degrees
    "fine_turns_3deg": {"image_fine_turns_deg": (-9.0, -6.0, -3.0, 3.0, 6.0, 9.0)},
}
"""Settings of ``RegistrationConfig`` each variant changes."""

COUNTS = ("accepted_right", "accepted_wrong", "refused_right", "refused_other")


@dataclass
class BenchPoseChoiceConfig:
    seeds: Tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7, 8)
    """Dev seeds whose defaults' suite runs exist (at --res and the demo's budget)."""
    res: str = "96x72"
    """Image size of those runs."""
    variants: Tuple[str, ...] = tuple(VARIANTS)
    """Which ways of scoring to run (see VARIANTS)."""
    out: Path = Path("benchmarks/results/pose_choice_dev.json")
    """Where to write the JSON."""


def classify(rows: Sequence[Mapping]) -> Dict[str, int]:
    """Counts of :data:`COUNTS` over one scene's registration report rows (templates left out).

    Args:
        rows: per instance ``success``, ``rotation_error_deg`` (of the accepted pose), ``proposed_rotation_error_deg``
            (of the chosen candidate when refused, None when nothing was chosen) and ``template`` (bool).
    """
    counts = dict.fromkeys(COUNTS, 0)
    for row in rows:
        if row["template"]:
            continue
        if row["success"]:
            right = row["rotation_error_deg"] is not None and row["rotation_error_deg"] <= WRONG_POSE_DEG
            counts["accepted_right" if right else "accepted_wrong"] += 1
        else:
            proposed = row.get("proposed_rotation_error_deg")
            counts["refused_right" if proposed is not None and proposed <= WRONG_POSE_DEG else "refused_other"] += 1
    return counts


EVIDENCE = ("margin_db", "over_own_db", "fitness", "colour", "inliers", "views", "pixels", "distinct_poses",
            "class_fitness", "class_colour", "class_colour_margin")
"""What the choice knows about an instance's chosen pose, without the truth: its image margin over the best rival,
how much better than the instance's own Gaussians it explains the pixels, the chosen candidate's ICP fitness,
colour agreement and PnP inliers, the views and pixels compared, how many distinct poses were compared, and how
well it agrees with the class's other copies under their chosen poses
(:func:`splatreplace_ns.poses.class_evidence.class_agreement`)."""


def evidence(entry: Mapping, agreement: Optional[Mapping] = None) -> Optional[Dict[str, Optional[float]]]:
    """The :data:`EVIDENCE` of one registration entry's image choice (None where nothing was chosen);
    ``agreement``: the instance's :func:`~splatreplace_ns.poses.class_evidence.class_agreement`."""
    choice = entry.get("image_choice") or {}
    if choice.get("chosen") is None:
        return None
    candidate = entry["candidates"][choice["chosen"]]
    chosen = choice.get("chosen_score")
    own = choice.get("psnr_own")
    return {"margin_db": choice.get("margin_db"),
            "over_own_db": None if chosen is None or own is None else chosen - own,
            "fitness": candidate.get("fitness"), "colour": candidate.get("colour"), "inliers": candidate.get("inliers"),
            "views": choice.get("views"), "pixels": choice.get("pixels"),
            "distinct_poses": len({round(float(x), 6) for x in choice.get("scores") or [] if x is not None}),
            **{k: (agreement or {}).get(k) for k in EVIDENCE if k.startswith("class_")}}


def separation(rows: Sequence[Mapping]) -> Dict[str, Dict]:
    """How well each piece of evidence separates right chosen poses (within WRONG_POSE_DEG of the truth) from wrong
    ones, over non-template instances with a chosen pose: per feature the area under the ROC curve (the chance that
    a right pose scores higher than a wrong one; 0.5 is no separation, ties count half) and both groups' medians."""
    import statistics

    chosen = [r for r in rows if not r["template"] and r.get("evidence") and r.get("proposed_rotation_error_deg") is not None]
    right = [r for r in chosen if r["proposed_rotation_error_deg"] <= WRONG_POSE_DEG]
    wrong = [r for r in chosen if r["proposed_rotation_error_deg"] > WRONG_POSE_DEG]
    out = {}
    for name in EVIDENCE:
        # no rival at all (margin None with a chosen pose) counts as the largest margin
        def value(r):
            v = r["evidence"].get(name)
            return float("inf") if v is None and name == "margin_db" else v
        a = [value(r) for r in right if value(r) is not None]
        b = [value(r) for r in wrong if value(r) is not None]
        pairs = [(x > y) + 0.5 * (x == y) for x in a for y in b]
        finite = lambda xs: [x for x in xs if x != float("inf")]  # noqa: E731
        out[name] = {"auc": sum(pairs) / len(pairs) if pairs else None, "right": len(a), "wrong": len(b),
                     "median_right": statistics.median(finite(a)) if finite(a) else None,
                     "median_wrong": statistics.median(finite(b)) if finite(b) else None}
    return out


def _scene_runs(seed: int, res: str):
    """(data folder, checkpoint folder) of the defaults' suite run of dev seed ``seed``."""
    from splatreplace_ns.tools.bench.suite import BenchSuiteConfig, run_folder, scene_name

    cfg = BenchSuiteConfig(split="dev", seeds=(seed,), res=res)
    data = cfg.data_root / scene_name(seed, res, cfg.n_train, cfg.n_test)
    run = run_folder(cfg, data.name, default=True)
    step = cfg.base_iterations + cfg.contrastive_iterations - 1
    checkpoints = run / "ours" / "splat-replace" / "run" / "nerfstudio_models"
    if not (checkpoints / f"step-{step:09d}.ckpt").exists():
        raise FileNotFoundError(f"{run}: no defaults' run with its checkpoint at the end of segmentation; run "
                                f"`splatreplace bench suite --split dev --seeds {seed} --res {res}` first")
    return data, checkpoints, step, cfg


def run_scene(seed: int, res: str, variants: Sequence[str], scratch: Path) -> Dict[str, Dict]:
    """Every variant's counts and choice time on one scene → {variant: {counts..., "time_s", "per_instance"}}."""
    import torch

    from splatreplace_ns.eval.report import registration_report
    from splatreplace_ns.poses.class_evidence import class_agreement
    from splatreplace_ns.tools.sim.scene import class_size
    from splatreplace_ns.method.train import make_trainer_config, setup_trainer
    from splatreplace_ns.poses.register import with_floor_up_axis

    data, checkpoints, step, cfg = _scene_runs(seed, res)
    last = sorted(checkpoints.glob("step-*.ckpt"))[-1]
    state = torch.load(last, map_location="cpu", weights_only=False)["pipeline"]
    proposed = next(v for k, v in state.items() if k.endswith("_extra_state"))["registration"]
    config = make_trainer_config(data, scratch, cfg.base_iterations, cfg.contrastive_iterations,
                                 cfg.finetune_iterations, experiment_name=f"pose_choice_{seed}",
                                 resume_from=(checkpoints, step))
    pipeline = setup_trainer(config).pipeline
    model = pipeline.model
    instances = pipeline.instance_gaussians()
    labels = model.instance_labels.to(model.means.device)
    background = (labels == 0) & (pipeline.leftover_owner() == 0)
    registration, _ = with_floor_up_axis(pipeline.config.registration, model.means.detach()[background],
                                         model.means.detach()[labels > 0])
    out = {}
    for name in variants:
        model.registration = copy.deepcopy(proposed)
        start = time.perf_counter()
        pipeline.choose_poses_by_images(instances, dataclasses.replace(registration, **VARIANTS[name]))
        seconds = time.perf_counter() - start
        report, why = registration_report(pipeline, class_size)
        if report is None:
            raise RuntimeError(f"seed {seed}: {why}")
        agreement = class_agreement(instances, model.registration, {int(i["id"]): i["class"] for i in model.instances},
                                    registration)  # choose_poses_by_images alone does not record it
        rows = [{"instance": r["instance"], "success": r["success"], "rotation_error_deg": r["rotation_error_deg"],
                 "proposed_rotation_error_deg": r.get("proposed_rotation_error_deg"),
                 "template": int(model.registration[r["instance"]]["template"]) == int(r["instance"]),
                 "margin_db": (model.registration[r["instance"]].get("image_choice") or {}).get("margin_db"),
                 "evidence": evidence(model.registration[r["instance"]], agreement.get(int(r["instance"])))}
                for r in report["per_instance"]]
        out[name] = {**classify(rows), "time_s": seconds, "per_instance": rows}
    return out


def table(result: Dict) -> None:
    variants = result["parameters"]["variants"]
    print("| variant | " + " | ".join(c.replace("_", " ") for c in COUNTS) + " | choice time (s, per scene) |")
    print("| --- |" + " ---: |" * (len(COUNTS) + 1))
    for name in variants:
        totals = result["totals"][name]
        times = [result["scenes"][str(s)][name]["time_s"] for s in result["parameters"]["seeds"]]
        print(f"| {name} | " + " | ".join(str(totals[c]) for c in COUNTS)
              + f" | {sum(times) / len(times):.0f} ({min(times):.0f}–{max(times):.0f}) |")


def separation_table(result: Dict) -> None:
    variant = "defaults" if "defaults" in result["separation"] else next(iter(result["separation"]))
    print(f"\nEvidence against the truth ({variant}; AUC 0.5 = no separation, 1 = right poses always score higher):")
    print("| evidence | AUC | right / wrong | median, right | median, wrong |")
    print("| --- | ---: | --- | ---: | ---: |")
    fmt = lambda v: "–" if v is None else f"{v:.2f}"  # noqa: E731
    for name, row in result["separation"][variant].items():
        print(f"| {name} | {fmt(row['auc'])} | {row['right']} / {row['wrong']} | {fmt(row['median_right'])} | "
              f"{fmt(row['median_wrong'])} |")


def main(cfg: BenchPoseChoiceConfig) -> Dict:
    import tempfile

    unknown = [v for v in cfg.variants if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; known: {list(VARIANTS)}")
    scenes: Dict[str, Dict] = {}
    with tempfile.TemporaryDirectory() as scratch:
        for seed in cfg.seeds:
            scenes[str(seed)] = run_scene(seed, cfg.res, cfg.variants, Path(scratch))
            print(f"seed {seed}: " + "; ".join(
                f"{name} " + " / ".join(str(scenes[str(seed)][name][c]) for c in COUNTS) for name in cfg.variants))
    totals = {name: {c: sum(scenes[str(s)][name][c] for s in cfg.seeds) for c in COUNTS} for name in cfg.variants}
    result = {"parameters": {"seeds": list(cfg.seeds), "res": cfg.res, "variants": list(cfg.variants),
                             "settings": {v: VARIANTS[v] for v in cfg.variants}, "wrong_pose_deg": WRONG_POSE_DEG},
              "totals": totals, "scenes": scenes}
    result["separation"] = {name: separation([row for s in cfg.seeds for row in scenes[str(s)][name]["per_instance"]])
                            for name in cfg.variants}
    table(result)
    separation_table(result)
    write_result_json(result, cfg.out)
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchPoseChoiceConfig))
