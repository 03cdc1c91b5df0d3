"""``splatreplace bench masks``: instance masks from one click per instance, against the ground truth.

On a sim preset with the masks withheld (images, cameras, points and clicks only — what a capture has):

* per backend: mIoU and boundary F-score of the written masks over every frame, and the wall time of
  the masks after the base stage (the base stage's time is reported apart);
* the ceiling (``oracle``): the same scores for masks rendered from each Gaussian's ground-truth label, what
  the base model and the renderer allow whatever the clustering;
* downstream: ``ns-train splat-replace`` (all stages, fine-tuning included) trained in process on the
  capture with our masks and on the same capture with the ground-truth masks; test-view segmentation mIoU
  and PSNR inside the ground-truth instance masks (the same pixels for both runs).
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import cv2
import numpy as np
import torch

from splatreplace_ns.eval.segmentation import ground_truth_masks_by_name, score_views_from_clicks, segmentation_scores
from splatreplace_ns.method.masks_command import BaseFrames
from splatreplace_ns.datamanager.click_masks import MASKS_DIR, read_dataset_meta
from splatreplace_ns.tools.sim.capture import strip_ground_truth
from splatreplace_ns.instances.geometric_config import ClusteringConfig
from splatreplace_ns.tools.bench.output import write_result_json
from splatreplace_ns.tools.bench.user_inputs import make_regime_folder

NO_MASKED = "a downstream run reported no masked PSNR (no test view shows an instance)"


@dataclass
class BenchMasksConfig:
    """Mask mIoU / boundary F per backend, wall time, and the downstream effect of our masks."""

    preset: str = "office"
    """Synthetic preset (office, temple, chess, ...)."""
    suite_seed: Optional[int] = None
    """A scene of the scene suite (``splatreplace sim random`` with this seed, as ``bench suite`` makes it under
    ``data_root/suite``) instead of the preset."""
    json: Optional[Path] = None
    """Where to write the results as JSON."""
    res: str = "160x120"
    """Scene resolution WxH."""
    n_train: int = 60
    """Training views."""
    n_test: int = 12
    """Test views."""
    base_iterations: int = 2000
    """Base 3DGS* iterations of the masks run."""
    base_frames: BaseFrames = "auto"
    """Frames the masks run's base stage trains on (``splatreplace masks --base-frames``): the scenes list their
    split, so ``auto`` trains on the training views; ``every`` on the test views too."""
    inputs: Literal["exact", "user"] = "exact"
    """What the base model trains from (never depth or masks): ``exact``, the scene's dense point cloud sampled from
    the true depth; ``user``, what a user has (``bench suite --inputs user``: COLMAP's sparse points at the scene's
    poses, or random Gaussians where it finds too few)."""
    load_config: Optional[Path] = None
    """Reuse this base run (config.yml of an earlier masks run on the same capture) instead of training."""
    backends: Tuple[str, ...] = ("geometric",)
    """Backends to score; onnx-sam needs --sam-encoder/--sam-decoder."""
    sam_encoder: Optional[Path] = None
    sam_decoder: Optional[Path] = None
    border: str = "none"
    """Border cleanup of the geometric backend (none, grabcut, guided)."""
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    """Clustering and split of the geometric backend (``splatreplace masks --clustering.*``)."""
    skip_bad_clicks: bool = True
    """Make the masks of the clicks that work and score each skipped click's instance as IoU 0 (the
    command's ``--skip-bad-clicks``); off: a bad scene click stops the benchmark with its error."""
    downstream: bool = True
    """Also train splat-replace on our masks and on the ground-truth masks."""
    downstream_base_iterations: int = 1000
    downstream_contrastive_iterations: int = 500
    downstream_finetune_iterations: int = 500
    """Fine-tuning of the downstream runs: their masked PSNR is that of the replaced scene."""
    oracle: bool = True
    """Also score masks rendered from each Gaussian's ground-truth label (JSON ``oracle``): the ceiling that the
    base model and the mask renderer set, whatever the clustering."""
    boundary_tolerance: int = 2
    """Boundary F-score: a boundary pixel matches within this many pixels."""
    data_root: Path = Path("benchmarks/data")
    out_dir: Path = Path("benchmarks/runs")

    def main(self) -> Dict:
        result = run_masks_bench(self)
        print_table(result)
        write_result_json(result, self.json)
        return result


# ----------------------------------------------------------------------------- scores


def boundaries(mask: np.ndarray) -> np.ndarray:
    """[H, W] bool → its inner boundary pixels (in the mask, with a 4-neighbour outside it)."""
    m = mask.astype(np.uint8)
    return mask & ~cv2.erode(m, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def boundary_f_score(pred: np.ndarray, gt: np.ndarray, pred_to_gt: Dict[int, int], tolerance: int = 2) -> Dict:
    """Boundary F-score per instance (Perazzi et al.'s F measure), accumulated over views.

    Args:
        pred: [V, H, W] predicted labels; gt: [V, H, W] ground-truth labels.
        pred_to_gt: predicted id → ground-truth id.
        tolerance: pixels within which a boundary pixel counts as matched.

    Returns:
        {"boundary_f": mean over instances, "per_instance": {gt_id: F}}.
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tolerance + 1, 2 * tolerance + 1))
    scores = {}
    for p, g in pred_to_gt.items():
        matched_p = total_p = matched_g = total_g = 0
        for v in range(pred.shape[0]):
            bp, bg = boundaries(pred[v] == p), boundaries(gt[v] == g)
            near_g = cv2.dilate(bg.astype(np.uint8), kernel).astype(bool)
            near_p = cv2.dilate(bp.astype(np.uint8), kernel).astype(bool)
            matched_p += int((bp & near_g).sum())
            total_p += int(bp.sum())
            matched_g += int((bg & near_p).sum())
            total_g += int(bg.sum())
        precision = matched_p / total_p if total_p else float(total_g == 0)
        recall = matched_g / total_g if total_g else float(total_p == 0)
        scores[g] = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"boundary_f": float(np.mean(list(scores.values()))) if scores else 0.0, "per_instance": scores}


def read_masks(data: Path, frames: List[Dict]) -> np.ndarray:
    """[V, H, W] masks named by ``frames[].instance_mask_path``."""
    return np.stack([cv2.imread(str(data / f["instance_mask_path"]), cv2.IMREAD_UNCHANGED) for f in frames])


def score_masks(scene: Path, capture: Path, tolerance: int) -> Dict:
    """mIoU and boundary F of a capture's written masks against the scene's ground truth (every frame)."""
    ours_meta = read_dataset_meta(capture)
    return score_arrays(read_masks(capture, ours_meta["frames"]), scene, [f["file_path"] for f in ours_meta["frames"]],
                        tolerance)


def score_arrays(ours: np.ndarray, scene: Path, file_paths: List[str], tolerance: int) -> Dict:
    """mIoU and boundary F of [F, H, W] masks (click k → id k + 1) of the frames ``file_paths`` against the
    scene's ground truth of the same frames (matched by file name)."""
    gt_meta = json.loads((scene / "transforms.json").read_text())
    by_name = {Path(f["file_path"]).name: f for f in gt_meta["frames"]}
    gt = read_masks(scene, [by_name[Path(p).name] for p in file_paths])
    clicks = json.loads((scene / "clicks.json").read_text())
    pred_to_gt = {k + 1: int(c["id"]) for k, c in enumerate(clicks)}
    seg = segmentation_scores(torch.from_numpy(ours.astype(np.int64)), torch.from_numpy(gt.astype(np.int64)), pred_to_gt)
    bf = boundary_f_score(ours, gt, pred_to_gt, tolerance)
    return {"miou": seg["miou"], "iou": seg["iou"], "boundary_f": bf["boundary_f"], "boundary_f_per_instance": bf["per_instance"]}


@torch.no_grad()
def oracle_masks(base_config: Path, capture: Path, scene: Path, depth_tolerance: float = 0.05) -> Tuple[np.ndarray, List[str]]:
    """Masks rendered from each Gaussian's ground-truth label: the best the base model and the mask renderer
    allow, whatever the clustering and the split.

    A Gaussian's label is the majority of the scene's ground-truth masks at its centre over the frames that
    see it (:func:`~splatreplace_ns.tools.bench.gt_labels.labels_from_masks`, visibility by the rendered depth);
    the instance of click k (id k + 1, as in the written masks) is the Gaussians labelled with that click's
    ground-truth id, rendered exactly as the geometric backend renders its instances (no border cleanup).

    Returns:
        [F, H, W] uint16 masks and the frames' file paths, in the capture's frame order.
    """
    from splatreplace_ns.instances.frames import frame_cameras
    from splatreplace_ns.method.masks_command import load_base
    from splatreplace_ns.instances.masks2d import BorderConfig, render_instance_masks
    from splatreplace_ns.instances.frames import render_frames
    from splatreplace_ns.tools.bench.gt_labels import labels_from_masks

    transforms = capture / "transforms.json"
    base = load_base(base_config, transforms)
    model = base.model
    model.eval()
    frames = frame_cameras(transforms, base.dataparser_transform, base.dataparser_scale, base.downscale)
    gt_meta = json.loads((scene / "transforms.json").read_text())
    by_name = {Path(f["file_path"]).name: f for f in gt_meta["frames"]}
    gt = torch.from_numpy(read_masks(scene, [by_name[Path(p).name] for p in frames.file_paths]).astype(np.int64))
    renders = render_frames(model, frames)
    depths = torch.stack([torch.where(a[..., 0] > 0, d[..., 0], torch.zeros_like(d[..., 0]))
                          for a, d in zip(renders.alphas, renders.depths)])
    height, width = depths.shape[1:]
    full_size = tuple(gt.shape[1:])
    if full_size != (height, width):  # a downscaled capture: vote on masks of the rendered size
        gt = torch.nn.functional.interpolate(gt[:, None].float(), size=(height, width), mode="nearest")[:, 0].long()
    labels = labels_from_masks(model.means.detach().cpu(), torch.stack(renders.viewmats).float(),
                               torch.stack(renders.Ks).float(), width, height, gt, depths, depth_tolerance)
    clicks = json.loads((scene / "clicks.json").read_text())
    instance = torch.zeros_like(labels)
    for k, click in enumerate(clicks):
        instance[labels == int(click["id"])] = k + 1
    masks = [render_instance_masks(model, frames.cameras[i : i + 1].to(model.device), instance, len(clicks), None,
                                   BorderConfig(method="none")) for i in range(len(frames.file_paths))]
    # scored against the full-size ground truth, as the written masks are
    masks = [cv2.resize(m, full_size[::-1], interpolation=cv2.INTER_NEAREST) if m.shape != full_size else m
             for m in masks]
    return np.stack(masks), list(frames.file_paths)


# ----------------------------------------------------------------------------- runs


def scene_of(cfg: BenchMasksConfig) -> Path:
    from splatreplace_ns.tools.bench.scenes import cached_scene

    if cfg.suite_seed is not None:
        from splatreplace_ns.tools.bench.suite import cached_random_scene

        return cached_random_scene(cfg.suite_seed, cfg.res, cfg.n_train, cfg.n_test, cfg.data_root / "suite")
    return cached_scene(cfg.preset, cfg.res, cfg.n_train, cfg.n_test, cfg.data_root)


def regime_source(scene: Path, inputs: str) -> Path:
    """The folder a masks run's capture is stripped from (:func:`strip_ground_truth`: images, cameras, the point
    cloud and the clicks are kept): the scene itself, or its ``bench suite --inputs user`` folder, whose cloud is
    COLMAP's sparse points (none: random Gaussians)."""
    return scene if inputs == "exact" else make_regime_folder(scene, inputs)


def with_ground_truth_masks(scene: Path, capture: Path, out: Path) -> Path:
    """A copy of the capture whose masks and instances are the scene's ground truth (the reference run)."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(capture, out, ignore=shutil.ignore_patterns("masks", MASKS_DIR, "transforms.json*"))
    shutil.copytree(scene / "masks", out / "masks")
    gt_meta = json.loads((scene / "transforms.json").read_text())
    meta = json.loads((capture / "transforms.json").read_text())  # as the user gave it: masks are beside it
    for frame, gt_frame in zip(meta["frames"], gt_meta["frames"]):
        frame["instance_mask_path"] = gt_frame["instance_mask_path"]
    clicks = json.loads((scene / "clicks.json").read_text())
    meta["instances"] = [{"id": int(i["id"]), "class": i["class"]} for i in gt_meta["instances"]]
    (out / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")
    # the reference run's clicks carry the ground-truth ids' order as they are
    (out / "clicks.json").write_text(json.dumps(clicks, indent=2) + "\n")
    return out


@torch.no_grad()
def test_view_psnr_in_gt_masks(pipeline, scene: Path) -> Optional[float]:
    """Mean test-view PSNR inside the union of the scene's *ground-truth* instance masks, so that runs trained
    on different masks are scored on the same pixels (``ns-eval``'s psnr_masked uses the dataset's own masks)."""
    from splatreplace_ns.eval.metrics import psnr

    model = pipeline.model
    model.eval()
    dataset = pipeline.datamanager.eval_dataset
    gt_by_name = ground_truth_masks_by_name(scene)
    values = []
    for idx in range(len(dataset)):
        camera = dataset.cameras[idx : idx + 1].to(pipeline.device)
        outputs = model.get_outputs_for_camera(camera)
        image = dataset.get_data(idx, image_type="float32")["image"].to(pipeline.device)
        gt_rgb = model.composite_with_background(model.get_gt_img(image), outputs["background"])
        mask = cv2.imread(str(gt_by_name[Path(dataset.image_filenames[idx]).name]), cv2.IMREAD_UNCHANGED) > 0
        value = psnr(outputs["rgb"], gt_rgb, torch.from_numpy(mask).to(pipeline.device))
        if value is not None:
            values.append(value)
    return float(np.mean(values)) if values else None


def downstream_run(cfg: BenchMasksConfig, data: Path, scene: Path, name: str) -> Dict:
    """Trains splat-replace on one dataset; returns psnr (all / masked when reported) and test-view mIoU."""
    from splatreplace_ns.method.train import evaluate_test_views, make_trainer_config, run_training

    config = make_trainer_config(
        data, cfg.out_dir / data.parent.name, cfg.downstream_base_iterations,  # the capture's masks_<scene>[_user]
        cfg.downstream_contrastive_iterations, cfg.downstream_finetune_iterations, experiment_name=name,
    )
    config.pipeline.model.num_downscales = 0
    seg: Dict = {}
    segmented_at = cfg.downstream_base_iterations + cfg.downstream_contrastive_iterations - 1

    def score_segmentation(trainer, step: int) -> None:
        # right after the segmentation stage: once the shared templates are built the instances share
        # their Gaussians, and a click no longer selects one instance
        if step == segmented_at:
            seg.update(score_views_from_clicks(trainer.pipeline, data / "clicks.json", reference_scene=scene))
            seg["skipped"] = list(trainer.pipeline.segmentation_report.get("skipped_clicks", []))

    start = time.perf_counter()
    trainer = run_training(config, after_step=score_segmentation)
    train_s = time.perf_counter() - start
    metrics = evaluate_test_views(trainer)
    return {
        "psnr": float(metrics["psnr"]),
        "psnr_masked": test_view_psnr_in_gt_masks(trainer.pipeline, scene),
        "segmentation_miou": seg["miou"],
        "click_failures": seg["failures"],
        "clicks_skipped_in_training": seg["skipped"],
        "time_s": train_s,
    }


def run_masks_bench(cfg: BenchMasksConfig) -> Dict:
    from splatreplace_ns.method.masks_command import MasksCommand, make_masks
    from splatreplace_ns.instances.masks2d import BorderConfig

    torch.set_num_threads(1)  # measured faster than 2 on the shared two-core machines
    scene = scene_of(cfg)
    source = regime_source(scene, cfg.inputs)
    # one capture folder per scene (preset, resolution, views) and inputs: runs at two resolutions must not share one
    name = f"masks_{source.name}"
    rows, base_config, base_s = [], cfg.load_config, None
    first_capture = None
    for backend in cfg.backends:
        capture = cfg.data_root / name / backend
        strip_ground_truth(source, capture)
        command = MasksCommand(
            capture, backend=backend, load_config=base_config, base_iterations=cfg.base_iterations,
            base_frames=cfg.base_frames,
            output_dir=cfg.out_dir / name, sam_encoder=cfg.sam_encoder, sam_decoder=cfg.sam_decoder,
            border=BorderConfig(method=cfg.border), clustering=cfg.clustering, skip_bad_clicks=cfg.skip_bad_clicks,
        )
        report = make_masks(command)
        if base_config is None:
            base_config, base_s = Path(report["config"]), report["time_s"]["base"]
        scores = score_masks(scene, capture, cfg.boundary_tolerance)
        rows.append({"backend": backend, "miou": scores["miou"], "boundary_f": scores["boundary_f"],
                     "time_s": report["time_s"]["masks"], "iou_per_instance": scores["iou"],
                     "boundary_f_per_instance": scores["boundary_f_per_instance"],
                     "skipped_clicks": report["skipped_clicks"], "sparse_instances": report["sparse_instances"]})
        first_capture = first_capture or capture

    oracle = None
    if cfg.oracle and first_capture is not None:
        start = time.perf_counter()
        masks, file_paths = oracle_masks(base_config, first_capture, scene)
        scores = score_arrays(masks, scene, file_paths, cfg.boundary_tolerance)
        oracle = {"miou": scores["miou"], "boundary_f": scores["boundary_f"], "iou_per_instance": scores["iou"],
                  "time_s": time.perf_counter() - start}

    downstream: Dict = {"psnr_masked_gt_masks": None, "psnr_masked_our_masks": None}
    if cfg.downstream and first_capture is not None:
        reference = with_ground_truth_masks(scene, first_capture, first_capture.parent / "gt_masks")
        ours = downstream_run(cfg, first_capture, scene, "downstream_our_masks")
        gt = downstream_run(cfg, reference, scene, "downstream_gt_masks")
        downstream = {
            "psnr_masked_gt_masks": gt["psnr_masked"],
            "psnr_masked_our_masks": ours["psnr_masked"],
            "segmentation_miou_gt_masks": gt["segmentation_miou"],
            "segmentation_miou_our_masks": ours["segmentation_miou"],
            "psnr_gt_masks": gt["psnr"],
            "psnr_our_masks": ours["psnr"],
            "click_failures": {"gt_masks": gt["click_failures"], "our_masks": ours["click_failures"]},
            "clicks_skipped_in_training": {
                "gt_masks": gt["clicks_skipped_in_training"], "our_masks": ours["clicks_skipped_in_training"],
            },
            "time_s": {"gt_masks": gt["time_s"], "our_masks": ours["time_s"]},
        }
        if gt["psnr_masked"] is None or ours["psnr_masked"] is None:
            downstream["note"] = NO_MASKED
    import nerfstudio

    return {
        "benchmark": "masks",
        "preset": cfg.preset if cfg.suite_seed is None else scene.name,
        "rows": rows,
        "oracle": oracle,
        "downstream": downstream,
        "base": {"config": str(base_config), "time_s": base_s, "reused": cfg.load_config is not None},
        "parameters": {
            "res": cfg.res, "n_train": cfg.n_train, "n_test": cfg.n_test, "base_iterations": cfg.base_iterations,
            "inputs": cfg.inputs,
            "base_frames": cfg.base_frames,
            "border": cfg.border, "boundary_tolerance": cfg.boundary_tolerance,
            "clustering": dataclasses.asdict(cfg.clustering),
            "downstream_base_iterations": cfg.downstream_base_iterations,
            "downstream_contrastive_iterations": cfg.downstream_contrastive_iterations,
            "downstream_finetune_iterations": cfg.downstream_finetune_iterations,
        },
        "machine": {
            "platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
            "nerfstudio": getattr(nerfstudio, "__version__", "1.1.5"),
        },
    }


def print_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"instance masks on '{result['preset']}' (every frame, masks withheld)")
    for col in ("backend", "mIoU", "boundary F", "time (s)"):
        table.add_column(col)
    for row in result["rows"]:
        table.add_row(row["backend"], f"{row['miou']:.4f}", f"{row['boundary_f']:.4f}", f"{row['time_s']:.1f}")
    oracle = result.get("oracle")
    if oracle:
        table.add_row("ceiling (ground-truth label of every Gaussian)", f"{oracle['miou']:.4f}",
                      f"{oracle['boundary_f']:.4f}", f"{oracle['time_s']:.1f}")
    Console().print(table)
    for row in result["rows"]:
        for message in row.get("skipped_clicks", []):
            Console().print(f"{row['backend']}: skipped (scored as IoU 0): {message}")
        for message in row.get("sparse_instances", []):
            Console().print(f"{row['backend']}: warning: {message}")
    d = result["downstream"]
    fmt = lambda v: "null" if v is None else f"{v:.3f}"  # noqa: E731
    Console().print(
        f"downstream: psnr_masked gt {fmt(d.get('psnr_masked_gt_masks'))} / ours {fmt(d.get('psnr_masked_our_masks'))}"
        + (f" ({d['note']})" if "note" in d else "")
        + (f"; segmentation mIoU gt {fmt(d['segmentation_miou_gt_masks'])} / ours {fmt(d['segmentation_miou_our_masks'])}"
           if "segmentation_miou_gt_masks" in d else "")
    )
