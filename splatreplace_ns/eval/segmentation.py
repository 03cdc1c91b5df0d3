"""Segmentation scores of rendered instance masks against ground truth, and the click replay that makes them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Mapping, Optional

import cv2
import numpy as np
import torch


def segmentation_scores(pred: torch.Tensor, gt: torch.Tensor, pred_to_gt: Mapping[int, int]) -> Dict:
    """mIoU and mAcc of instance label maps over a set of views.

    IoU of an instance = |pred ∩ gt| / |pred ∪ gt| accumulated over all views; mIoU is their mean
    over the instances. Accuracy of a label = fraction of its ground-truth pixels predicted as it;
    mAcc is the mean over the instances and the background.

    Args:
        pred: [V, H, W] predicted labels (0 = background, k = predicted instance k).
        gt: [V, H, W] ground-truth labels (0 = background).
        pred_to_gt: predicted instance id → ground-truth id.

    Returns:
        {"miou", "macc", "iou": {gt_id: iou}, "acc": {gt_id: acc}} (gt_id 0 = background).
    """
    pred = pred.long()
    gt = gt.long()
    mapped = torch.zeros_like(pred)
    for p, g in pred_to_gt.items():
        mapped[pred == p] = g
    iou, acc = {}, {}
    for g in sorted(set(pred_to_gt.values())):
        a, b = mapped == g, gt == g
        union = int((a | b).sum())
        iou[g] = float((a & b).sum()) / union if union else 1.0
        acc[g] = float((a & b).sum()) / max(1, int(b.sum()))
    bg = gt == 0
    acc[0] = float((mapped[bg] == 0).sum()) / max(1, int(bg.sum()))
    return {
        "miou": sum(iou.values()) / max(1, len(iou)),
        "macc": sum(acc.values()) / len(acc),
        "iou": iou,
        "acc": acc,
    }


def ground_truth_masks_by_name(scene: Path) -> Dict[str, Path]:
    """Image file name → ground-truth instance mask path, from a scene's transforms.json."""
    frames = json.loads((Path(scene) / "transforms.json").read_text())["frames"]
    return {Path(f["file_path"]).name: Path(scene) / f["instance_mask_path"] for f in frames}


def click_gt_ids(pipeline, clicks_path: Path) -> Dict[int, int]:
    """Ground-truth instance id of every click in ``clicks.json``, by click index.

    The entry's ``"id"`` when given (the simulator writes it), else the ground-truth mask value under the
    clicked pixel of its training view (0 when the click is on ground-truth background).
    """
    from splatreplace_ns.datamanager.clicks import load_clicks, pixel_index

    raw = json.loads(Path(clicks_path).read_text())
    train = pipeline.datamanager.train_dataset
    ids = {}
    for click in load_clicks(clicks_path):
        if "id" in raw[click.index]:
            ids[click.index] = int(raw[click.index]["id"])
            continue
        mask = train.get_data(pipeline.train_index_of(click.file_path), image_type="uint8")["instance_mask"]
        H, W = mask.shape[:2]
        # the pixel the segmentation stage reads for this click (nearest centre), kept inside the image
        u, v = min(max(click.xy[0], 0.0), W - 1.0), min(max(click.xy[1], 0.0), H - 1.0)
        row, col = pixel_index(u, v, W, H)
        ids[click.index] = int(mask[row, col, 0])
    return ids


@torch.no_grad()
def score_views_from_clicks(pipeline, clicks_path: Path, dataset=None, reference_scene: Optional[Path] = None) -> Dict:
    """Selects the instances from the clicks (no carving) and scores the masks they give in a set of views.

    The masks of a view are its rendered features thresholded against the click queries
    (``instances.select.masks_from_rendered_features``, τ and min_alpha from the pipeline's segmentation
    config), scored against the ground-truth masks with :func:`segmentation_scores`. A click that cannot
    become an instance counts as a missed instance (IoU 0), not a crash. The pipeline's selection and the
    model's train/eval mode are left as they were.

    Args:
        pipeline: a ``SplatReplacePipeline`` (its ``begin_selection``/``add_click`` replay the clicks).
        clicks_path: ``clicks.json``.
        dataset: views to score (default: the eval dataset); must carry ``instance_mask`` unless
            ``reference_scene`` is given.
        reference_scene: a scene directory with the ground truth (masks in its transforms.json, the
            clicks' ``"id"`` in its clicks.json), used instead of the dataset's own masks: a run trained on
            masks of its own making is then scored against the truth.

    Returns:
        :func:`segmentation_scores` plus ``labels`` ([N] per-Gaussian labels of the replayed selection),
        ``failures`` (messages of the rejected clicks) and ``pred_to_gt``.
    """
    from splatreplace_ns.datamanager.clicks import load_clicks, pixel_index
    from splatreplace_ns.instances.from_clicks import SelectionError
    from splatreplace_ns.instances.select import masks_from_rendered_features

    model = pipeline.model
    was_training, previous_selection = model.training, pipeline.selection
    model.eval()
    try:
        selection = pipeline.begin_selection()
        if reference_scene is None:
            gt_ids = click_gt_ids(pipeline, clicks_path)
        else:
            gt_ids = {k: int(c["id"]) for k, c in enumerate(json.loads((Path(reference_scene) / "clicks.json").read_text()))}
            gt_paths = ground_truth_masks_by_name(reference_scene)
        pred_to_gt, failures = {}, []
        for click in load_clicks(clicks_path):
            gt_id = gt_ids[click.index]
            if gt_id == 0:  # nothing to score it against
                failures.append(f"click {click.index} ({click.file_path} at {click.xy}): on ground-truth background")
                continue
            try:
                pipeline.add_click(click)
            except SelectionError as err:
                failures.append(str(err))
                pred_to_gt[-(click.index + 1)] = gt_id
                continue
            pred_to_gt[selection.instances[-1].id] = gt_id
        queries = selection.queries.to(pipeline.device)
        cfg = pipeline.config.segmentation
        dataset = pipeline.datamanager.eval_dataset if dataset is None else dataset
        preds, gts = [], []
        features_of_gaussians = selection.gaussian_features()  # contrastive features, or voted labels (lift voting)
        for idx in range(len(dataset)):
            camera = dataset.cameras[idx : idx + 1].to(pipeline.device)
            features, alpha, _ = model.render_features(camera, features_of_gaussians)
            preds.append(masks_from_rendered_features(features, alpha, queries, cfg.tau, cfg.min_alpha).cpu())
            if reference_scene is None:
                gts.append(pipeline.datamanager.instance_mask_as_rendered(dataset, idx))
            else:
                gt = cv2.imread(str(gt_paths[Path(dataset.image_filenames[idx]).name]), cv2.IMREAD_UNCHANGED)
                gts.append(pipeline.datamanager.mask_as_rendered(dataset, idx, gt))
        scores = segmentation_scores(torch.stack(preds), torch.stack(gts), pred_to_gt)
        scores["labels"] = selection.labels().cpu()
        scores["failures"] = failures
        scores["pred_to_gt"] = pred_to_gt
        return scores
    finally:
        pipeline.selection = previous_selection
        model.train(was_training)


@torch.no_grad()
def score_gaussian_labels_in_views(model, labels: torch.Tensor, dataset, datamanager) -> Dict:
    """Renders fixed per-Gaussian instance labels into a dataset's views and scores them against its masks.

    With labels voted from the training views' ground-truth masks this is the best a hard per-Gaussian
    selection can render on this reconstruction: where the Gaussians render a far view badly, no
    segmentation of them does better there.

    Args:
        model: a SplatReplaceModel (``render_features``).
        labels: [N] ground-truth instance id per Gaussian (0 = background).
        dataset: views carrying ``instance_mask``.
        datamanager: the run's datamanager (reads each mask in the geometry its camera renders).

    Returns:
        :func:`segmentation_scores` over the instances that the labels hold.
    """
    from splatreplace_ns.instances.masks2d import BorderConfig, render_instance_masks

    ids = sorted(int(i) for i in torch.unique(labels) if int(i) > 0)
    preds, gts = [], []
    for idx in range(len(dataset)):
        camera = dataset.cameras[idx : idx + 1].to(model.device)
        # the masks command's own render of labelled Gaussians, borders as rendered
        mask = render_instance_masks(model, camera, labels.long(), max(ids, default=0), None, BorderConfig(method="none"))
        preds.append(torch.from_numpy(mask.astype("int64")))
        gts.append(datamanager.instance_mask_as_rendered(dataset, idx).long())
    return segmentation_scores(torch.stack(preds), torch.stack(gts), {i: i for i in ids})
