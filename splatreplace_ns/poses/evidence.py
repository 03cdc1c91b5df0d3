"""The evidence a candidate pose is judged by: how it lays the instance's Gaussians on the template's (shape and
colour), and how well the template placed under it explains the instance's pixels in the training images.

Gaussians' evidence (:func:`fitness`, :func:`colour_agreement`) needs nothing but the two instances; the images'
evidence (:class:`PlacedRenders`) renders the scene with the template placed in the instance's place into the
training views that show the instance most. :mod:`splatreplace_ns.poses.decision` turns either into a decision.
"""

from __future__ import annotations

import math
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from splatreplace_ns.instances.masks2d import labels_from_weights, one_hot_labels
from splatreplace_ns.poses.instance import InstanceGaussians, float64_array
from splatreplace_ns.render.sh import SH_C0
from splatreplace_ns.render.transform import transform_gaussians

GAUSSIAN_KEYS = ("means", "quats", "log_scales", "logit_opacities", "sh")

RenderFn = Callable[[int, Dict[str, Tensor], Tensor], Tuple[Tensor, Tensor]]
"""(training view index, Gaussians with GAUSSIAN_KEYS, extra features [N, D]) → rgb [H, W, 3] in [0, 1] with
the scene's background, extra features rendered [H, W, D]."""


# ----------------------------------------------------------------------------- on the Gaussians


def fitness(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, dist: float) -> float:
    """Fraction of T·src points with a tgt point within ``dist``."""
    from scipy.spatial import cKDTree

    if len(src) == 0 or len(tgt) == 0:
        return 0.0
    moved = src @ T[:3, :3].T + T[:3, 3]
    d, _ = cKDTree(tgt).query(moved, k=1, distance_upper_bound=dist)
    return float(np.isfinite(d).mean())


def base_rgb(inst: InstanceGaussians) -> np.ndarray:
    """(N, 3) view-independent colour: the RGB itself, or the SH DC term mapped like gsplat (c0·C + 0.5)."""
    c = float64_array(inst.colors)
    if c.ndim == 3:
        return np.clip(SH_C0 * c[:, 0, :] + 0.5, 0.0, 1.0)
    return c[:, :3]


def colour_agreement(src, src_rgb, tgt, tgt_rgb, T, dist: float, tol: float) -> float:
    """Fraction of T·src centres that have a tgt centre within ``dist`` whose colour is within ``tol``
    (mean absolute RGB difference). Rejects alignments that fit the shape but not the appearance (e.g. a
    box turned by 180°)."""
    from scipy.spatial import cKDTree

    if len(src) == 0 or len(tgt) == 0:
        return 0.0
    moved = src @ T[:3, :3].T + T[:3, 3]
    d, idx = cKDTree(tgt).query(moved, k=1, distance_upper_bound=dist)
    hit = np.isfinite(d)
    ok = np.zeros(len(src), dtype=bool)
    ok[hit] = np.abs(src_rgb[hit] - tgt_rgb[idx[hit]]).mean(axis=1) < tol
    return float(ok.mean())


# ----------------------------------------------------------------------------- in the training images


def colour_fitted(pred: Tensor, target: Tensor, max_gain: float = 2.0) -> Tensor:
    """Per-channel gain fitted from ``pred`` to ``target`` (least squares, clamped to [1/max_gain, max_gain]).

    A gain models a copy lit brighter or dimmer, or by a coloured light; no bias and a bounded gain, so that the
    fit cannot turn a prediction into the pixels' mean colour (which would explain a small, flat footprint
    whatever the pose).

    Args:
        pred, target: [P, 3] colours.
    Returns:
        [P, 3] ``gain * pred`` clamped to [0, 1].
    """
    if pred.shape[0] == 0:
        return pred
    gain = (pred * target).sum(0) / pred.pow(2).sum(0).clamp_min(1e-8)
    return (gain.clamp(1.0 / max_gain, max_gain) * pred).clamp(0.0, 1.0)


PSNR_CAP_DB = 50.0
"""Scores are capped here: beyond it two renders are equal for 8-bit images, and ``inf`` would refuse a perfect pose."""


def psnr(pred: Tensor, target: Tensor) -> float:
    """PSNR (dB, peak 1) over [P, 3] pixels, at most :data:`PSNR_CAP_DB`; NaN pixels count as wrong."""
    mse = float(torch.nan_to_num((pred.float() - target.float()).pow(2), nan=1.0).mean())
    return PSNR_CAP_DB if mse <= 10.0 ** (-PSNR_CAP_DB / 10.0) else -10.0 * math.log10(mse)


def subset(scene: Mapping[str, Tensor], keep: Tensor) -> Dict[str, Tensor]:
    return {k: scene[k][keep] for k in GAUSSIAN_KEYS}


def _placed(scene: Mapping[str, Tensor], T: Tensor) -> Dict[str, Tensor]:
    """Gaussians moved by the rigid [4, 4] ``T`` (world → world)."""
    means, quats, sh = transform_gaussians(T.to(scene["means"]), scene["means"], scene["quats"], scene["sh"])
    return {"means": means, "quats": quats, "log_scales": scene["log_scales"],
            "logit_opacities": scene["logit_opacities"], "sh": sh}


def _cat(a: Mapping[str, Tensor], b: Mapping[str, Tensor]) -> Dict[str, Tensor]:
    return {k: torch.cat((a[k], b[k])) for k in GAUSSIAN_KEYS}


def instance_id_maps(scene: Mapping[str, Tensor], labels: Tensor, views: Sequence[int],
                     render: RenderFn) -> Tuple[Dict[int, Tensor], Dict[int, Tensor]]:
    """One render per training view of the scene as it is: its colours and which instance each pixel shows.

    Returns:
        ({view: rgb [H, W, 3]}, {view: instance id [H, W] long, 0 = background or weight < 0.5}).
    """
    ids = sorted(set(labels.unique().tolist()) - {0})
    table = torch.tensor([0] + ids, dtype=torch.long, device=labels.device)
    one_hot = one_hot_labels(torch.searchsorted(table, labels), len(ids)).to(scene["means"].dtype)
    rgbs, id_maps = {}, {}
    for v in views:
        rgb, weights = render(v, dict(scene), one_hot)
        dense = labels_from_weights(weights, 0.5)
        id_maps[v] = table.to(dense.device)[dense]
        rgbs[v] = rgb
    return rgbs, id_maps


def instance_views(id_maps: Mapping[int, Tensor], instance: int, max_views: int, min_pixels: int) -> List[int]:
    """The (at most ``max_views``) views where ``instance`` covers the most pixels, at least ``min_pixels``."""
    counts = {v: int((m == instance).sum()) for v, m in id_maps.items()}
    return [v for v in sorted(counts, key=counts.get, reverse=True) if counts[v] >= min_pixels][:max_views]


class PlacedRenders:
    """The template instance ``anchor`` placed under poses in instance ``instance``'s place, with the rest of the
    scene around it, rendered into ``views``: each pose is rendered once, and scored with any set of the poses
    rendered so far (:meth:`scores`), so that a choice in passes renders no pose twice.

    Per view only a box is kept: the instance's pixels and every placed copy's, widened by a quarter of its size
    (at least 4 px). A pose whose copy reaches outside the box widens it, and the poses kept before are rendered
    again in that view, so the scores are those of full renders.

    Args:
        scene: Gaussians (N) with GAUSSIAN_KEYS; labels: [N] long instance ids.
        views: the view indices to compare; id_maps: from :func:`instance_id_maps`.
    """

    def __init__(self, scene: Mapping[str, Tensor], labels: Tensor, instance: int, anchor: int, render: RenderFn,
                 views: Sequence[int], id_maps: Mapping[int, Tensor]) -> None:
        self.render, self.views = render, list(views)
        self.rest = subset(scene, labels != instance)
        self.template = subset(scene, labels == anchor)
        marker = torch.cat((torch.zeros(len(self.rest["means"]), 1), torch.ones(len(self.template["means"]), 1)))
        self.marker = marker.to(scene["means"])
        self.own = {v: id_maps[v] == instance for v in self.views}  # [H, W] bool, full size
        self.boxes: Dict[int, Tuple[int, int, int, int]] = {v: _box(self.own[v]) for v in self.views}
        self.poses: List[Tensor] = []
        self.crops: List[Dict[int, Tuple[Tensor, Tensor]]] = []  # per pose, per view: rgb [h, w, 3], covered [h, w]

    def _render(self, pose: Tensor, v: int) -> Tuple[Tensor, Tensor]:
        rgb, weight = self.render(v, _cat(self.rest, _placed(self.template, pose)), self.marker)
        return rgb, weight[..., 0] >= 0.5

    def add(self, poses: Sequence[Tensor]) -> None:
        """Renders each pose (template → instance, [4, 4]) in every view and keeps it."""
        for pose in poses:
            crops: Dict[int, Tuple[Tensor, Tensor]] = {}
            for v in self.views:
                rgb, covered = self._render(pose, v)
                box = self.boxes[v]
                if covered.any() and not _inside(_box(covered, widen=False), box):
                    box = self.boxes[v] = _union_box(box, _box(covered))
                    for k, kept in enumerate(self.poses):  # the kept crops lack the new pixels: render them again
                        self.crops[k][v] = _crop(self._render(kept, v), box)
                crops[v] = _crop((rgb, covered), box)
            self.poses.append(pose)
            self.crops.append(crops)

    def scores(self, images: Sequence[Tensor], rgb_before: Mapping[int, Tensor], per_view: bool = False,
               which: Optional[Sequence[int]] = None) -> Tuple[float, List[float], int]:
        """How well the own Gaussians and each pose in ``which`` (indices into the poses added; all by default)
        explain the instance's training pixels: those the instance covers in the scene as it is, or any of those
        poses' copies covers (weight ≥ 0.5), the same for every pose. PSNR after a per-channel gain
        (:func:`colour_fitted`) over all compared pixels (``per_view=False``), or per view and averaged over the
        views (``per_view=True``: one view rendered badly under every pose does not outweigh the others, see
        :func:`mean_view_psnr`).

        Args:
            images: training images [H, W, 3] (float in [0, 1] or uint8); rgb_before: from
                :func:`instance_id_maps` (the scene's render).

        Returns:
            (PSNR by the own Gaussians, [PSNR under each pose of ``which``], number of compared pixels).
        """
        which = list(range(len(self.poses))) if which is None else list(which)
        own_px: List[Tensor] = []
        target_px: List[Tensor] = []
        cand_px: List[List[Tensor]] = [[] for _ in which]
        for v in self.views:
            y0, y1, x0, x1 = self.boxes[v]
            footprint = self.own[v][y0:y1, x0:x1]
            for k in which:
                footprint = footprint | self.crops[k][v][1]
            target = images[v][y0:y1, x0:x1, :3]  # an RGBA capture's alpha is not compared
            target = (target.float() / 255.0 if target.dtype == torch.uint8 else target.float()).to(footprint.device)
            target_px.append(target[footprint])
            own_px.append(rgb_before[v][y0:y1, x0:x1][footprint].float())
            for slot, k in enumerate(which):
                cand_px[slot].append(self.crops[k][v][0][footprint].float())
        score = mean_view_psnr if per_view else pooled_psnr
        return score(own_px, target_px), [score(px, target_px) for px in cand_px], int(sum(t.shape[0] for t in target_px))


def _box(mask: Tensor, widen: bool = True) -> Tuple[int, int, int, int]:
    """(y0, y1, x0, x1), the smallest box holding the True pixels of ``mask`` [H, W] (an empty mask: an empty box
    at the origin), widened by a quarter of its size (at least 4 px) inside the image when ``widen``."""
    H, W = mask.shape
    rows, cols = torch.nonzero(mask.any(dim=1)), torch.nonzero(mask.any(dim=0))
    if rows.numel() == 0:
        return (0, 0, 0, 0)
    y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    if widen:
        dy, dx = max(4, (y1 - y0) // 4), max(4, (x1 - x0) // 4)
        y0, y1, x0, x1 = max(0, y0 - dy), min(H, y1 + dy), max(0, x0 - dx), min(W, x1 + dx)
    return (y0, y1, x0, x1)


def _inside(inner: Tuple[int, int, int, int], outer: Tuple[int, int, int, int]) -> bool:
    return outer[0] <= inner[0] and inner[1] <= outer[1] and outer[2] <= inner[2] and inner[3] <= outer[3]


def _union_box(a: Tuple[int, int, int, int], b: Tuple[int, int, int, int]) -> Tuple[int, int, int, int]:
    if a[1] <= a[0] or a[3] <= a[2]:  # empty
        return b
    return (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))


def _crop(render: Tuple[Tensor, Tensor], box: Tuple[int, int, int, int]) -> Tuple[Tensor, Tensor]:
    y0, y1, x0, x1 = box
    return render[0][y0:y1, x0:x1], render[1][y0:y1, x0:x1]


def pooled_psnr(pred: Sequence[Tensor], target: Sequence[Tensor]) -> float:
    """PSNR over the pixels of every view together, after one per-channel gain.

    Args:
        pred, target: per view, [P_v, 3] colours.
    """
    pred_all, target_all = torch.cat(list(pred)), torch.cat(list(target))
    return psnr(colour_fitted(pred_all, target_all), target_all)


def mean_view_psnr(pred: Sequence[Tensor], target: Sequence[Tensor]) -> float:
    """Mean over views of each view's PSNR, each after its own per-channel gain (a view that no pose explains
    then weighs as one view, in its error and in its gain).

    Args:
        pred, target: per view, [P_v, 3] colours (views without pixels are skipped).
    """
    scores = [psnr(colour_fitted(p, t), t) for p, t in zip(pred, target) if p.shape[0] > 0]
    if not scores:
        raise ValueError("mean_view_psnr: no view has pixels to compare")
    return sum(scores) / len(scores)
