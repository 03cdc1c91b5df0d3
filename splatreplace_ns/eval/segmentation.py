"""Segmentation scores of rendered instance masks against ground truth."""

from __future__ import annotations

from typing import Dict, Mapping

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
