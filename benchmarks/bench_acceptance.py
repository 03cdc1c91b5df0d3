"""Which registrations does the acceptance test refuse, and could another threshold tell right from wrong?

Reads finished `splatreplace bench suite` runs of the dev split with the defaults: for every scene, the pipeline at
the end of segmentation is loaded and registration runs again with the acceptance thresholds off, recording every
candidate pose (ICP fitness, colour score, PnP inliers) and its rotation error against the ground truth (modulo the
class's symmetry). Then each pair of thresholds (min ICP fitness, min colour score) is applied to the recorded
candidates exactly as registration applies them (``choose_candidate``), and the table counts the poses it would
accept and refuse, right (within 5° of the truth after the upright polish, or, for a candidate the run did not
choose, within 10° before it) and wrong. "oracle" takes the right candidate whenever one was posed: what a
perfect choice among the same candidates could reach. A second table applies the method's choice against the
training images (``image_choice``: the template rendered under each candidate into the instance's training views,
the best-explaining one accepted when it beats every rival turned more than 20° by a margin) at several margins;
with ``--views``, once more for each number of training views compared per instance. Writes one JSON.

    python benchmarks/bench_acceptance.py --runs benchmarks/runs/suite --out benchmarks/results/acceptance_dev.json
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
import tyro

from splatreplace_ns.tools.bench.output import write_result_json
from splatreplace_ns.tools.bench.register_scene import load_pipeline
from splatreplace_ns.tools.bench.suite import DEV_SEEDS
from splatreplace_ns.tools.bench.suite_output import WRONG_POSE_DEG
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.decision import choose_candidate

SEGMENTATION_STEP = 1999  # end of the contrastive stage with the demo's budget (1500 + 500)
CANDIDATE_RIGHT_DEG = 10.0  # a candidate before the upright polish, which brings a few degrees
DEFAULTS = (RegistrationConfig.min_fitness, RegistrationConfig.min_photometric_fitness)


@dataclass
class BenchAcceptanceConfig:
    runs: Path = Path("benchmarks/runs/suite")
    """Folder of the suite's runs (one folder per scene and variant, each with result.json)."""
    res: str = "96x72"
    """Image size of the runs to read (their folder names carry it)."""
    out: Path = Path("benchmarks/results/acceptance_dev.json")
    thresholds: Tuple[Tuple[float, float], ...] = (DEFAULTS, (0.0, 0.0), (0.1, 0.05), (0.15, 0.1), (0.2, 0.05), (0.3, 0.15))
    """(min ICP fitness, min colour score) pairs to tabulate; the first is the defaults."""
    margins: Tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0)
    """dB: margins of the choice against the training images to tabulate."""
    views: Tuple[int, ...] = ()
    """Other numbers of training views per instance to score the candidates with, one more table each (the
    method's ``image_views`` is always scored; each count renders every distinct candidate that many times)."""


def defaults_runs(cfg: BenchAcceptanceConfig) -> List[Tuple[int, Path]]:
    """(seed, folder) of every dev-split run with the defaults at the demo's budget."""
    pattern = re.compile(rf"random_(\d+)_{cfg.res}_\d+v\d+_1500-500-1000$")
    runs = [(int(m.group(1)), p) for p in sorted(cfg.runs.iterdir()) if (m := pattern.match(p.name))]
    return [(seed, p) for seed, p in runs if seed in DEV_SEEDS and (p / "result.json").exists()]


def record_candidates(run: Path, views: Tuple[int, ...] = ()) -> Dict:
    """Registration of the run's segmented scene with the thresholds off; the report of every instance with its
    candidates scored against the truth. → {"per_instance": [...], "time_s"}."""
    from splatreplace_ns.eval.report import registration_report
    from splatreplace_ns.tools.sim.scene import class_size

    pipeline = load_pipeline(run / "ours/splat-replace/run/config.yml", SEGMENTATION_STEP)
    pipeline.config.registration = replace(pipeline.config.registration, min_fitness=0.0, min_photometric_fitness=0.0,
                                           image_choice=False)
    start = time.perf_counter()
    with torch.no_grad():
        pipeline.run_registration()
    seconds = time.perf_counter() - start
    report, why = registration_report(pipeline, class_size)
    if report is None:
        raise RuntimeError(f"{run}: no registration report ({why})")
    start = time.perf_counter()
    with torch.no_grad():
        scored = explain_candidates(pipeline, (pipeline.config.registration.image_views, *views))
    explained, by_views = scored[0], dict(zip(views, scored[1:]))
    for row in report["per_instance"]:
        if row["instance"] in explained and row.get("candidates"):
            own, scores = explained[row["instance"]]
            row["own_psnr"] = own
            for i, (c, score, entry) in enumerate(zip(row["candidates"], scores,
                                                      pipeline.model.registration[row["instance"]]["candidates"])):
                c["image_psnr"] = score
                c["image_psnr_by_views"] = {k: by_views[k][row["instance"]][1][i] for k in views}
                c["transform"] = entry["transform"]
    return {"per_instance": report["per_instance"], "time_s": seconds, "image_scores_s": time.perf_counter() - start}


def explain_candidates(pipeline, view_counts: Tuple[int, ...]) -> List[Dict[int, Tuple[float, List[float]]]]:
    """Every registered instance's candidate poses scored against its training images, as the method's pose
    choice scores them (``splatreplace_ns.poses.decision.choose_pose``), once per number of views in
    ``view_counts`` → per count {instance: (PSNR by its own Gaussians, [PSNR with the template placed under each
    candidate])}; instances seen in no training view are left out. The scene is rendered once for all counts."""
    from splatreplace_ns.poses.decision import choose_pose
    from splatreplace_ns.poses.evidence import instance_id_maps

    cfg = pipeline.config.registration
    pipeline.model.eval()
    scene, labels, images, render = pipeline.image_evidence_inputs()
    labels = labels.to(scene["means"].device)
    rgb_before, id_maps = instance_id_maps(scene, labels, range(len(images)), render)
    out: List[Dict[int, Tuple[float, List[float]]]] = [{} for _ in view_counts]
    for iid, entry in pipeline.model.registration.items():
        if not entry.get("candidates") or int(entry["template"]) == int(iid):
            continue
        for scores, views in zip(out, view_counts):
            choice = choose_pose(scene, labels, int(iid), int(entry["template"]),
                                 [c["transform"] for c in entry["candidates"]], images, render, id_maps, rgb_before,
                                 cfg.image_margin_db, cfg.image_rival_deg, views)
            if choice.chosen is not None:
                scores[int(iid)] = (choice.psnr_own, choice.scores)
    return out


def decide(candidates: List[Dict], proposed_error: float, min_fitness: float,
           min_colour: float) -> Tuple[bool, float, float]:
    """What registration with these thresholds does with these candidates → (accepted, the pose's rotation error,
    the error under which it counts as right).

    The candidate chosen with the thresholds off is the proposed pose: it carries the polished pose's error and is
    right within WRONG_POSE_DEG; another one carries its own error before the polish, right within
    CANDIDATE_RIGHT_DEG."""
    cfg = replace(RegistrationConfig(), min_fitness=min_fitness, min_photometric_fitness=min_colour)
    fitness = [c["fitness"] for c in candidates]
    colour = [c["colour"] for c in candidates]
    tiebreak = [(c["inliers"], -c["pair"][0], -c["pair"][1]) for c in candidates]
    at = choose_candidate(fitness, colour, tiebreak, cfg)
    proposed = choose_candidate(fitness, colour, tiebreak, replace(cfg, min_fitness=0.0, min_photometric_fitness=0.0))
    accepted = fitness[at] >= min_fitness and colour[at] >= min_colour
    if at == proposed:
        return accepted, proposed_error, WRONG_POSE_DEG
    return accepted, candidates[at]["rotation_error_deg"], CANDIDATE_RIGHT_DEG


def tabulate(instances: List[Dict], thresholds) -> List[Dict]:
    rows = []
    for min_fitness, min_colour in thresholds:
        row = {"min_fitness": min_fitness, "min_colour": min_colour, "accepted_right": 0, "accepted_wrong": 0,
               "refused_right": 0, "refused_wrong": 0}
        for inst in instances:
            ok, error, limit = decide(inst["candidates"], inst["proposed_rotation_error_deg"], min_fitness, min_colour)
            row[("accepted_" if ok else "refused_") + ("right" if error <= limit else "wrong")] += 1
        rows.append(row)
    oracle = sum(any(c["rotation_error_deg"] <= CANDIDATE_RIGHT_DEG for c in i["candidates"])
                 or i["proposed_rotation_error_deg"] <= WRONG_POSE_DEG for i in instances)
    rows.append({"min_fitness": "oracle", "min_colour": "oracle", "accepted_right": oracle, "accepted_wrong": 0,
                 "refused_right": 0, "refused_wrong": len(instances) - oracle})
    return rows


def tabulate_image_choice(instances: List[Dict], margins, rival_deg: float, views: Optional[int] = None) -> List[Dict]:
    """The choice against the training images (``choose_pose``'s rule) at each margin: the best-explaining
    candidate, accepted when no rival turned more than ``rival_deg`` comes within the margin; right when that
    candidate is within CANDIDATE_RIGHT_DEG of the truth. An instance seen in no training view keeps the
    thresholds' decision (the defaults), as in the method. ``views``: use the scores of that many views
    (``image_psnr_by_views``) instead of the method's."""
    from splatreplace_ns.poses.decision import pick_with_margin

    rows = []
    for margin in margins:
        row = {"margin_db": margin, "accepted_right": 0, "accepted_wrong": 0, "refused_right": 0, "refused_wrong": 0}
        if views is not None:
            row = {"views": views, **row}
        for inst in instances:
            cands = inst["candidates"]
            scores = [c.get("image_psnr") if views is None else (c.get("image_psnr_by_views") or {}).get(views)
                      for c in cands]
            if any(score is None for score in scores):
                ok, error, limit = decide(cands, inst["proposed_rotation_error_deg"], *DEFAULTS)
            else:
                at, _, ok = pick_with_margin(scores,
                                             [torch.tensor(c["transform"]) for c in cands], margin, rival_deg)
                error, limit = cands[at]["rotation_error_deg"], CANDIDATE_RIGHT_DEG
            row[("accepted_" if ok else "refused_") + ("right" if error <= limit else "wrong")] += 1
        rows.append(row)
    return rows


def main(cfg: BenchAcceptanceConfig) -> Dict:
    scenes, instances = {}, []
    for seed, run in defaults_runs(cfg):
        record = record_candidates(run, cfg.views)
        gains = json.loads((run / "result.json").read_text())["row"]["per_instance"]
        for r in record["per_instance"]:
            if not r.get("candidates"):
                continue
            cands = r["candidates"]
            best = cands[choose_candidate([c["fitness"] for c in cands], [c["colour"] for c in cands],
                                          [(c["inliers"], -c["pair"][0], -c["pair"][1]) for c in cands],
                                          replace(RegistrationConfig(), min_fitness=0.0, min_photometric_fitness=0.0))]
            right = [c for c in r["candidates"] if c["rotation_error_deg"] <= CANDIDATE_RIGHT_DEG]
            best_right = max(right, key=lambda c: c["colour"], default=None)
            instances.append({
                "seed": seed, "instance": r["instance"], "proposed_rotation_error_deg": r["proposed_rotation_error_deg"],
                "fitness": best["fitness"], "colour": best["colour"],
                "best_right_candidate": None if best_right is None else {k: best_right[k] for k in ("fitness", "colour")},
                "gain_with_the_defaults": gains.get(str(r["instance"]), {}).get("gain"),
                "own_psnr": r.get("own_psnr"),
                "candidates": [{k: c.get(k) for k in ("rotation_error_deg", "fitness", "colour", "inliers", "pair",
                                                      "image_psnr", "image_psnr_by_views", "transform")}
                               for c in r["candidates"]],
            })
        scenes[seed] = {"registration_s": record["time_s"], "image_scores_s": record["image_scores_s"],
                        "instances": sum(i["seed"] == seed for i in instances)}
        print(f"seed {seed}: {scenes[seed]['instances']} registered instances, registration {record['time_s']:.1f} s, "
              f"image scores {record['image_scores_s']:.1f} s", flush=True)
    rows = tabulate(instances, cfg.thresholds)
    print(f"\n{'min fitness':>11} {'min colour':>10} | accepted right / wrong | refused right / wrong")
    for r in rows:
        print(f"{r['min_fitness']!s:>11} {r['min_colour']!s:>10} | {r['accepted_right']:>14} / {r['accepted_wrong']:<5} |"
              f" {r['refused_right']:>13} / {r['refused_wrong']}")
    image_rows = tabulate_image_choice(instances, cfg.margins, RegistrationConfig.image_rival_deg)
    print(f"\nchoice against the training images\n{'margin dB':>9} | accepted right / wrong | refused right / wrong")
    for r in image_rows:
        print(f"{r['margin_db']:>9} | {r['accepted_right']:>14} / {r['accepted_wrong']:<5} |"
              f" {r['refused_right']:>13} / {r['refused_wrong']}")
    views_rows = [row for k in cfg.views for row in
                  tabulate_image_choice(instances, cfg.margins, RegistrationConfig.image_rival_deg, k)]
    if views_rows:
        print(f"\nthe same choice with other numbers of views\n{'views':>5} {'margin dB':>9} | accepted right / wrong |"
              " refused right / wrong")
        for r in views_rows:
            print(f"{r['views']:>5} {r['margin_db']:>9} | {r['accepted_right']:>14} / {r['accepted_wrong']:<5} |"
                  f" {r['refused_right']:>13} / {r['refused_wrong']}")
    print("\nper instance (seed, instance, pose error after the polish, its fitness / colour, best right candidate's):")
    for i in instances:
        right = i["best_right_candidate"]
        print(f"  {i['seed']:>2} {i['instance']:>3} {i['proposed_rotation_error_deg']:7.1f}°  {i['fitness']:.3f} / "
              f"{i['colour']:.3f}  " + ("none posed" if right is None else f"{right['fitness']:.3f} / {right['colour']:.3f}"))
    result = {"benchmark": "acceptance", "split": "dev", "res": cfg.res, "seeds": sorted(scenes), "scenes": scenes,
              "right_deg": {"chosen_after_polish": WRONG_POSE_DEG, "other_candidate": CANDIDATE_RIGHT_DEG},
              "table": rows, "image_choice_table": image_rows, "image_views": RegistrationConfig.image_views,
              "image_choice_by_views": views_rows,
              "instances": [{**i, "candidates": [{k: v for k, v in c.items() if k != "transform"} for c in i["candidates"]]}
                            for i in instances]}  # the poses themselves are not kept
    write_result_json(result, cfg.out)
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchAcceptanceConfig))
