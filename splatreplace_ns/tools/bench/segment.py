"""``splatreplace bench segment``: 3D instance segmentation on the synthetic presets (paper §4.1, Fig. 6).

Two runs of ``ns-train splat-replace`` (in process, nerfstudio's Trainer) on one preset:

* ``reg`` — the default 3DGS* base (opacity/scale L1 on), then the contrastive stage. Test-view masks
  are scored after 1k contrastive iterations and at the end (5k by default); leftover background
  Gaussians near the instances are counted before and after space carving.
* ``none`` — the same without the L1 regularisation and without carving, for the leftover count.

Test-view masks come from rendering the features in the test cameras and thresholding against the
click queries (τ = 0.1); they are scored against the ground-truth masks (mIoU, mAcc; see
``splatreplace_ns.eval.segmentation``). The training views are scored the same way at the end
(``miou_train``): a preset whose test views look at sides no training view saw (temple) has no surface
there to segment, and the training views show the segmentation apart from that. Leftovers =
background-labelled Gaussians whose centres lie inside an instance's ground-truth mesh or within 1 % of
its bounding-box diagonal from it (inside: :func:`splatreplace_ns.tools.sim.geometry.class_signed_distance`), also
given per instance after carving. ``miou_gt_labels`` (test views) and ``miou_gt_labels_train`` are the
ceiling of the reconstruction: its Gaussians labelled by a vote of the ground-truth training masks and
rendered the same way.

``--compare-lifts`` compares the two ways of lifting the 2D instance masks to the Gaussians instead, on the same base
model of each scene (random dev scenes of ``--seeds``, presets of ``--lift-presets``): the voting lift
(``instances.lift``: each Gaussian takes the mask label with most of its blending weight over the training views)
scored right after the base stage, and the contrastive stage scored after each of ``--lift-contrastive-steps``.
Both are scored as above (test-view masks rendered from the selection of the scene's clicks, τ and min_alpha of
the segmentation config) and timed: the vote, or the contrastive training steps. One JSON for all the scenes.
"""

from __future__ import annotations

import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

from splatreplace_ns.eval.segmentation import score_gaussian_labels_in_views, score_views_from_clicks
from splatreplace_ns.tools.bench.output import spread, write_result_json


@dataclass
class BenchSegmentConfig:
    """Segmentation mIoU/mAcc, leftover background Gaussians and time per stage on a sim preset."""

    preset: str = "office"
    """Synthetic preset (office, temple, chess, ...)."""
    json: Optional[Path] = None
    """Where to write the results as JSON."""
    res: str = "160x120"
    """Scene resolution WxH."""
    n_train: int = 60
    """Training views."""
    n_test: int = 12
    """Test views."""
    base_iterations: int = 3000
    """Base 3DGS* iterations."""
    contrastive_iterations: int = 5000
    """Contrastive iterations of the main run (scores are also taken at 1k)."""
    early_contrastive_iterations: int = 1000
    """Where the early score (miou_1k) is taken."""
    data_root: Path = Path("benchmarks/data")
    """Generated scenes are kept here and reused."""
    out_dir: Path = Path("benchmarks/runs")
    """Training outputs."""
    skip_noreg: bool = False
    """Skip the run without regularisation (then leftover.none is null)."""
    threads: int = 2
    """torch threads (1 lets two benchmarks share a two-core machine)."""
    gt_depth_tolerance: float = 0.05
    """Visibility margin of the ground-truth vote that labels the Gaussians for the ceiling (as in bench register)."""
    compare_lifts: bool = False
    """Compare the voting lift with the contrastive stage (mIoU on the test views, seconds of each) on the scenes of
    --seeds and --lift-presets, instead of the preset's segmentation run (uses --res, --n-train, --n-test,
    --base-iterations)."""
    seeds: Tuple[int, ...] = (0, 1, 2, 3)
    """--compare-lifts: random dev scenes (``splatreplace sim random --seed K``; cached under DATA_ROOT/suite)."""
    lift_presets: Tuple[str, ...] = ()
    """--compare-lifts: named presets too."""
    lift_contrastive_steps: Tuple[int, ...] = (500, 1000)
    """--compare-lifts: contrastive iterations after which the contrastive lift is scored (the last is the stage's
    length)."""
    vote_min_shares: Tuple[float, ...] = (0.0, 0.5)
    """--compare-lifts: the voting lift's --pipeline.segmentation.vote-min-share values scored (one vote)."""

    def main(self) -> Dict:
        if self.compare_lifts:
            result = run_lift_bench(self)
            print_lift_table(result)
        else:
            result = run_segment_bench(self)
            print_table(result)
        write_result_json(result, self.json)
        return result


def _scene(cfg: BenchSegmentConfig) -> Path:
    from splatreplace_ns.tools.bench.scenes import cached_scene

    return cached_scene(cfg.preset, cfg.res, cfg.n_train, cfg.n_test, cfg.data_root)


def leftovers_by_instance(
    means: torch.Tensor, labels: torch.Tensor, instances: List[Dict], near: float = 0.01
) -> Dict[int, torch.Tensor]:
    """Which background Gaussians lie inside each instance's mesh or within ``near`` × its bounding-box
    diagonal of it.

    Args:
        means: [N, 3] centres in the normalised world frame.
        labels: [N] instance labels (0 = background).
        instances: dataparser instances with ``id``, ``transform_matrix`` (object→normalised world) and ``class``.
    Returns:
        {instance id: [B] bool over the B background Gaussians (``labels == 0``, in order)}.
    """
    from splatreplace_ns.tools.sim import class_mesh
    from splatreplace_ns.tools.sim.geometry import class_signed_distance

    is_background = labels == 0
    background = means[is_background].double()
    diagonals = {}
    near_each: Dict[int, torch.Tensor] = {}
    for inst in instances:
        if "transform_matrix" not in inst:
            continue
        if background.shape[0] == 0:
            near_each[int(inst["id"])] = torch.zeros(0, dtype=torch.bool)
            continue
        if inst["class"] not in diagonals:
            mesh = class_mesh(inst["class"])
            diagonals[inst["class"]] = float(np.linalg.norm(mesh.get_max_bound() - mesh.get_min_bound()))
        diag = diagonals[inst["class"]]
        to_object = torch.linalg.inv(inst["transform_matrix"].double())
        local = (background @ to_object[:3, :3].T + to_object[:3, 3]).numpy()
        signed = class_signed_distance(inst["class"], local)
        near_each[int(inst["id"])] = torch.from_numpy(signed <= near * diag)
    return near_each


def count_leftovers(means: torch.Tensor, labels: torch.Tensor, instances: List[Dict], near: float = 0.01) -> int:
    """Background Gaussians inside an instance or within ``near`` × its bounding-box diagonal of it (each
    counted once; arguments as :func:`leftovers_by_instance`)."""
    return leftover_total(leftovers_by_instance(means, labels, instances, near), int((labels == 0).sum()))


def leftover_total(near_each: Dict[int, torch.Tensor], n_background: int) -> int:
    """How many of the ``n_background`` Gaussians sit in at least one instance (``near_each`` as returned by
    :func:`leftovers_by_instance`)."""
    hit = torch.zeros(n_background, dtype=torch.bool)
    for near_one in near_each.values():
        hit |= near_one
    return int(hit.sum())


def _train(cfg: BenchSegmentConfig, data: Path, name: str, regularise: bool, carve: bool, contrastive: int, probes: Dict[int, str]):
    from splatreplace_ns.tools.bench.gt_labels import label_gaussians_from_ground_truth
    from splatreplace_ns.method.train import make_trainer_config, setup_trainer

    config = make_trainer_config(data, cfg.out_dir / cfg.preset, cfg.base_iterations, contrastive, experiment_name=name)
    config.pipeline.model.num_downscales = 0
    if not regularise:
        config.pipeline.model.opacity_l1_lambda = 0.0
        config.pipeline.model.scale_l1_lambda = 0.0
    config.pipeline.segmentation.carve = carve
    config.pipeline.segmentation.carve_only_replaced = False  # carving scored as when every instance is replaced
    trainer = setup_trainer(config)
    pipeline = trainer.pipeline
    record: Dict = {"time_s": {}}
    marks = {"start": time.perf_counter()}
    instances = pipeline.datamanager.train_dataparser_outputs.metadata["instances"]

    def probe(step: int) -> None:
        if step == cfg.base_iterations - 1:
            marks["base_done"] = time.perf_counter()
        if step in probes:
            t0 = time.perf_counter()
            scores = score_views_from_clicks(pipeline, data / "clicks.json")
            record[probes[step]] = {
                "miou": scores["miou"],
                "macc": scores["macc"],
                "iou": scores["iou"],
                "failures": scores["failures"],
                "leftover": count_leftovers(pipeline.model.means.detach().cpu(), scores["labels"], instances),
            }
            if probes[step] == "final":  # the training views too: segmentation where the capture has the surface
                train_views = pipeline.datamanager.train_dataset
                train = score_views_from_clicks(pipeline, data / "clicks.json", dataset=train_views)
                record["final"].update(miou_train=train["miou"], macc_train=train["macc"])
                # the ceiling of this reconstruction: Gaussians labelled by the ground-truth training masks
                truth = label_gaussians_from_ground_truth(pipeline, cfg.gt_depth_tolerance)
                test_gt = score_gaussian_labels_in_views(pipeline.model, truth, pipeline.datamanager.eval_dataset,
                                                         pipeline.datamanager)
                train_gt = score_gaussian_labels_in_views(pipeline.model, truth, train_views, pipeline.datamanager)
                record["final"].update(miou_gt_labels=test_gt["miou"], miou_gt_labels_train=train_gt["miou"])
            marks[f"probe_{step}"] = time.perf_counter() - t0
            if step == cfg.base_iterations + contrastive - 1:
                marks["contrastive_done"] = time.perf_counter()

    # before the pipeline's own segmentation callback at the last step
    trainer.callbacks.insert(0, TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], probe))
    trainer.train()
    end = time.perf_counter()
    probe_s = sum(v for k, v in marks.items() if k.startswith("probe_"))
    record["time_s"] = {
        "base": marks["base_done"] - marks["start"],
        "contrastive": marks["contrastive_done"] - marks["base_done"] - probe_s,
        "segmentation": pipeline.segmentation_report.get("time_s", float("nan")),
        "total": end - marks["start"],
    }
    record["carved"] = pipeline.segmentation_report.get("carved", 0)
    means, labels = pipeline.model.means.detach().cpu(), pipeline.model.instance_labels.cpu()
    near_each = leftovers_by_instance(means, labels, instances)
    record["leftover_final"] = leftover_total(near_each, int((labels == 0).sum()))
    # which ground-truth instance the leftovers sit in
    record["leftover_final_by_instance"] = {str(k): int(v.sum()) for k, v in near_each.items()}
    record["gaussians"] = pipeline.model.num_points
    return record


def run_segment_bench(cfg: BenchSegmentConfig) -> Dict:
    torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
    t0 = time.perf_counter()
    data = _scene(cfg)
    sim_s = time.perf_counter() - t0
    last = cfg.base_iterations + cfg.contrastive_iterations - 1
    early = cfg.base_iterations + cfg.early_contrastive_iterations - 1
    reg = _train(cfg, data, "reg", True, True, cfg.contrastive_iterations, {early: "early", last: "final"})
    noreg = None
    if not cfg.skip_noreg:
        noreg = _train(
            cfg, data, "noreg", False, False, cfg.early_contrastive_iterations,
            {cfg.base_iterations + cfg.early_contrastive_iterations - 1: "final"},
        )
    import nerfstudio

    return {
        "benchmark": "segment",
        "preset": cfg.preset,
        "miou": reg["final"]["miou"],
        "macc": reg["final"]["macc"],
        "miou_1k": reg["early"]["miou"],
        "miou_5k": reg["final"]["miou"],
        "macc_1k": reg["early"]["macc"],
        "miou_train": reg["final"]["miou_train"],
        "macc_train": reg["final"]["macc_train"],
        "miou_gt_labels": reg["final"]["miou_gt_labels"],
        "miou_gt_labels_train": reg["final"]["miou_gt_labels_train"],
        "iou_per_instance": reg["final"]["iou"],
        "click_failures": {"1k": reg["early"]["failures"], "final": reg["final"]["failures"]},
        "leftover": {
            "none": None if noreg is None else noreg["final"]["leftover"],
            "reg": reg["final"]["leftover"],
            "reg_carve": reg["leftover_final"],
            "reg_carve_by_instance": reg["leftover_final_by_instance"],
        },
        "carved": reg["carved"],
        "time_s": {"sim": sim_s, **reg["time_s"], **({"noreg_total": noreg["time_s"]["total"]} if noreg else {})},
        "parameters": {
            "res": cfg.res, "n_train": cfg.n_train, "n_test": cfg.n_test, "base_iterations": cfg.base_iterations,
            "contrastive_iterations": cfg.contrastive_iterations,
            "early_contrastive_iterations": cfg.early_contrastive_iterations, "threads": torch.get_num_threads(),
        },
        "machine": {
            "platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
            "nerfstudio": nerfstudio.__version__ if hasattr(nerfstudio, "__version__") else "1.1.5",
        },
    }


def print_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"segmentation on '{result['preset']}' (test views)")
    for col in ("mIoU", "mAcc", "mIoU@1k", "mIoU@end", "mIoU train views", "ceiling test / train",
                "leftover none", "leftover reg", "leftover reg+carve"):
        table.add_column(col)
    lo = result["leftover"]
    table.add_row(
        f"{result['miou']:.4f}", f"{result['macc']:.4f}", f"{result['miou_1k']:.4f}", f"{result['miou_5k']:.4f}",
        f"{result['miou_train']:.4f}", f"{result['miou_gt_labels']:.4f} / {result['miou_gt_labels_train']:.4f}",
        str(lo["none"]), str(lo["reg"]), str(lo["reg_carve"]),
    )
    Console().print(table)
    Console().print("time per stage (s): " + ", ".join(f"{k} {v:.1f}" for k, v in result["time_s"].items()))


# ---------------------------------------------------------------------------------------------- --compare-lifts
def _lift_scene(cfg: BenchSegmentConfig, scene: str) -> Path:
    from splatreplace_ns.tools.bench.scenes import cached_scene
    from splatreplace_ns.tools.bench.suite import cached_random_scene

    if scene.startswith("random_"):
        return cached_random_scene(int(scene.split("_", 1)[1]), cfg.res, cfg.n_train, cfg.n_test, cfg.data_root / "suite")
    return cached_scene(scene, cfg.res, cfg.n_train, cfg.n_test, cfg.data_root)


def _scores(scores: Dict) -> Dict:
    return {"miou": scores["miou"], "macc": scores["macc"], "iou": scores["iou"], "failures": scores["failures"]}


def score_voting_lift(pipeline, clicks: Path, min_shares: Tuple[float, ...]) -> Dict:
    """Votes the training masks onto the pipeline's current Gaussians and scores the test views for each minimum
    share; the pipeline is left on the contrastive lift, without votes. Returns {"time_s", "share_<s>": scores}."""
    from splatreplace_ns.instances.lift import Votes, labels_from_votes

    seg = pipeline.config.segmentation
    lift, min_share = seg.lift, seg.vote_min_share
    seg.lift, seg.vote_min_share, pipeline._lift_votes = "voting", 0.0, None
    try:
        votes = pipeline.lift_votes()
        out: Dict = {"time_s": pipeline.votes_time_s, "views": votes.views,
                     "unlabelled_share": float((votes.weights.sum(-1) <= 0).float().mean())}
        for share in min_shares:
            pipeline._lift_votes = Votes(labels_from_votes(votes.weights, share), votes.weights, votes.views)
            out[f"share_{share:g}"] = _scores(score_views_from_clicks(pipeline, clicks))
        return out
    finally:
        seg.lift, seg.vote_min_share, pipeline._lift_votes = lift, min_share, None


def _lift_run(cfg: BenchSegmentConfig, scene: str) -> Dict:
    import json

    from splatreplace_ns.method.train import make_trainer_config, setup_trainer

    t0 = time.perf_counter()
    data = _lift_scene(cfg, scene)
    sim_s = time.perf_counter() - t0
    B, steps = cfg.base_iterations, sorted(set(cfg.lift_contrastive_steps))
    config = make_trainer_config(data, cfg.out_dir / "lifts", B, steps[-1], experiment_name=data.name)
    config.pipeline.model.num_downscales = 0
    trainer = setup_trainer(config)
    pipeline = trainer.pipeline
    clicks = data / "clicks.json"
    row: Dict = {"scene": scene, "data": data.name, "instances": len(json.loads(clicks.read_text())),
                 "contrastive": {}, "time_s": {"sim": sim_s}}
    marks: Dict[str, float] = {}

    def probe(step: int) -> None:  # before the pipeline's own callback (segmentation at the stage's last step)
        if step == B - 1:
            row["time_s"]["base"] = time.perf_counter() - marks["start"]
            row["voting"] = score_voting_lift(pipeline, clicks, cfg.vote_min_shares)
            marks["contrastive_start"] = time.perf_counter()
        elif step - B + 1 in steps:
            trained = time.perf_counter() - marks["contrastive_start"]
            t = time.perf_counter()
            row["contrastive"][str(step - B + 1)] = {**_scores(score_views_from_clicks(pipeline, clicks)),
                                                     "time_s": trained}
            marks["contrastive_start"] += time.perf_counter() - t  # scoring is not training time

    trainer.callbacks.insert(0, TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], probe))
    marks["start"] = time.perf_counter()
    trainer.train()
    row["time_s"]["total"] = time.perf_counter() - t0
    row["gaussians"] = pipeline.model.num_points
    return row


def run_lift_bench(cfg: BenchSegmentConfig) -> Dict:
    """The voting lift against the contrastive stage on every scene; per-scene rows and mean ± std over them."""
    import nerfstudio

    torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
    scenes = [f"random_{seed}" for seed in cfg.seeds] + list(cfg.lift_presets)
    rows = []
    for scene in scenes:
        rows.append(_lift_run(cfg, scene))
        print(f"{scene}: voting mIoU {rows[-1]['voting'][f'share_{cfg.vote_min_shares[0]:g}']['miou']:.4f}, "
              + ", ".join(f"contrastive@{k} {v['miou']:.4f}" for k, v in rows[-1]["contrastive"].items()))
    summary: Dict = {}
    for share in cfg.vote_min_shares:
        key = f"share_{share:g}"
        summary[f"voting_{key}"] = {"miou": spread([r["voting"][key]["miou"] for r in rows]),
                                    "time_s": spread([r["voting"]["time_s"] for r in rows])}
    for steps in rows[0]["contrastive"]:
        summary[f"contrastive_{steps}"] = {"miou": spread([r["contrastive"][steps]["miou"] for r in rows]),
                                           "time_s": spread([r["contrastive"][steps]["time_s"] for r in rows])}
    return {
        "benchmark": "segment_lift",
        "definition": ("mIoU over the instances of the test views' masks rendered from the clicks' selection "
                       "(eval.segmentation.score_views_from_clicks); time_s: the vote over the training views "
                       "(voting) or the contrastive training steps (contrastive), on the same base model"),
        "scenes": rows,
        "summary": summary,
        "parameters": {
            "res": cfg.res, "n_train": cfg.n_train, "n_test": cfg.n_test, "base_iterations": cfg.base_iterations,
            "contrastive_steps": sorted(set(cfg.lift_contrastive_steps)), "vote_min_shares": list(cfg.vote_min_shares),
            "seeds": list(cfg.seeds), "presets": list(cfg.lift_presets), "threads": torch.get_num_threads(),
        },
        "machine": {
            "platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
            "nerfstudio": nerfstudio.__version__ if hasattr(nerfstudio, "__version__") else "1.1.5",
            "device": "cuda" if torch.cuda.is_available() else "cpu",
        },
    }


def print_lift_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    p = result["parameters"]
    table = Table(title=f"voting lift vs contrastive stage: test-view mIoU and seconds ({p['res']}, {p['n_train']} "
                        f"train / {p['n_test']} test views, base {p['base_iterations']} it., {p['threads']} threads)")
    table.add_column("scene")
    table.add_column("inst.")
    columns = [(f"voting_share_{s:g}", "voting" + (f" (share > {s:g})" if s else ""),
                lambda r, s=s: (r["voting"][f"share_{s:g}"]["miou"], r["voting"]["time_s"])) for s in p["vote_min_shares"]]
    columns += [(f"contrastive_{k}", f"contrastive {k} it.",
                 lambda r, k=str(k): (r["contrastive"][k]["miou"], r["contrastive"][k]["time_s"]))
                for k in p["contrastive_steps"]]
    for _, title, _ in columns:
        table.add_column(f"{title} mIoU")
        table.add_column("s")
    for row in result["scenes"]:
        cells = [row["scene"], str(row["instances"])]
        for _, _, get in columns:
            miou, seconds = get(row)
            cells += [f"{miou:.3f}", f"{seconds:.1f}"]
        table.add_row(*cells)
    cells = ["mean ± std", ""]
    for key, _, _ in columns:
        s = result["summary"][key]
        cells += [f"{s['miou']['mean']:.3f} ± {s['miou']['std']:.3f}", f"{s['time_s']['mean']:.1f} ± {s['time_s']['std']:.1f}"]
    table.add_row(*cells)
    Console().print(table)
