"""Per-view instance masks from labelled Gaussians, and their border cleanup with OpenCV.

One render per view splats a one-hot label per Gaussian (channel 0 = everything that is not an
instance), so occlusion is handled by the alpha compositing itself: where two instances overlap, or
the table hides the chair, the front one carries the weight. The rendered mask follows the
Gaussians' footprints, which bleed a pixel or two over the true silhouette; GrabCut (or a guided
filter) seeded by the rendered mask pulls the border onto the image edges.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional

import cv2
import numpy as np
import torch


@dataclass
class BorderConfig:
    method: Literal["grabcut", "guided", "none"] = "none"
    """Border cleanup: none (the rendered labels as they are), GrabCut seeded by the rendered mask, or a guided
    filter of the label weights (both follow low-contrast texture edges on small images; sharp, high-resolution
    captures may gain from GrabCut)."""
    min_weight: float = 0.5
    """A pixel is an instance's when its rendered weight is at least this (and the largest)."""
    band: int = 2
    """GrabCut: pixels within this distance of a rendered border are left for GrabCut to decide."""
    grabcut_iterations: int = 3
    """GrabCut iterations per instance and view."""
    guided_radius: int = 2
    """Guided filter window radius (pixels)."""
    guided_eps: float = 1e-3
    """Guided filter regulariser (image in [0, 1])."""


def one_hot_labels(instance_of_gaussian: torch.Tensor, num_instances: int) -> torch.Tensor:
    """[N] instance id per Gaussian (0 = background) → [N, K+1] one-hot features to splat."""
    return torch.nn.functional.one_hot(instance_of_gaussian.long(), num_instances + 1).float()


def labels_from_weights(weights: torch.Tensor, min_weight: float) -> torch.Tensor:
    """Per-pixel instance from rendered one-hot weights.

    Args:
        weights: [H, W, K+1] composited one-hot labels (channel 0 = background Gaussians).
        min_weight: the winning instance needs at least this weight.

    Returns:
        [H, W] int64 labels (0 = background).
    """
    best_weight, best = weights.max(dim=-1)
    return torch.where((best > 0) & (best_weight >= min_weight), best, torch.zeros_like(best))


def distort_map(values: np.ndarray, K: np.ndarray, distortion: np.ndarray, nearest: bool = True) -> np.ndarray:
    """Resamples a map rendered with a pinhole camera into the distorted (captured) image.

    Args:
        values: [H, W] or [H, W, C] map in the ideal pinhole image.
        K: [3, 3] intrinsics (pixel centres at ``i + 0.5``).
        distortion: [6] OpenCV (k1, k2, k3, k4, p1, p2); all zero returns ``values`` unchanged.
        nearest: nearest sampling (labels, depth) or bilinear (weights).

    Returns:
        the map aligned with the captured image (0 outside the rendered one), same shape and dtype.
    """
    if not np.any(distortion):
        return values
    k1, k2, k3, k4, p1, p2 = distortion
    H, W = values.shape[:2]
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pixels = np.stack([cols.ravel(), rows.ravel()], -1)[:, None, :].astype(np.float64)
    coeffs = np.array([k1, k2, p1, p2, k3, k4, 0.0, 0.0])
    ideal = cv2.undistortPoints(pixels, K, coeffs, P=K).reshape(H, W, 2)
    map_x = (ideal[..., 0] - 0.5).astype(np.float32)
    map_y = (ideal[..., 1] - 0.5).astype(np.float32)
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    out = cv2.remap(values.astype(np.float32), map_x, map_y, interpolation, borderValue=0)
    return out.reshape(values.shape).astype(values.dtype)


def grabcut_instance(image: np.ndarray, rendered: np.ndarray, band: int, iterations: int) -> np.ndarray:
    """GrabCut of one instance seeded by its rendered mask.

    Pixels deeper than ``band`` inside the rendered mask are sure foreground, farther than ``band``
    outside it sure background, the band between is left for GrabCut. Works on the bounding box only.

    Args:
        image: [H, W, 3] uint8 RGB.
        rendered: [H, W] bool rendered mask of the instance.

    Returns:
        [H, W] bool cleaned mask (the rendered one when GrabCut cannot run: too small, one colour).
    """
    if not rendered.any():
        return rendered
    H, W = rendered.shape
    rows, cols = np.nonzero(rendered)
    pad = 3 * band + 2
    r0, r1 = max(0, rows.min() - pad), min(H, rows.max() + pad + 1)
    c0, c1 = max(0, cols.min() - pad), min(W, cols.max() + pad + 1)
    crop = rendered[r0:r1, c0:c1].astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    sure_fg = cv2.erode(crop, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    maybe = cv2.dilate(crop, kernel).astype(bool)
    seeds = np.full(crop.shape, cv2.GC_BGD, dtype=np.uint8)
    seeds[maybe] = cv2.GC_PR_BGD
    seeds[crop.astype(bool)] = cv2.GC_PR_FGD
    seeds[sure_fg] = cv2.GC_FGD
    if not sure_fg.any() or not (seeds == cv2.GC_BGD).any():
        return rendered
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.setRNGSeed(0)  # GrabCut's GMM initialisation draws from OpenCV's RNG: same input, same mask
    try:
        cv2.grabCut(
            np.ascontiguousarray(image[r0:r1, c0:c1, ::-1]), seeds, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK
        )
    except cv2.error:
        return rendered
    out = np.zeros_like(rendered)
    out[r0:r1, c0:c1] = (seeds == cv2.GC_FGD) | (seeds == cv2.GC_PR_FGD)
    return out


def grabcut_labels(image: np.ndarray, labels: np.ndarray, order: np.ndarray, cfg: BorderConfig) -> np.ndarray:
    """Cleans every instance's border; overlaps go to the instance in front.

    Args:
        image: [H, W, 3] uint8 RGB.
        labels: [H, W] rendered labels.
        order: [K+1] front-to-back rank of each label in this view (smaller = nearer; index 0 unused).

    Returns:
        [H, W] cleaned labels.
    """
    out = np.zeros_like(labels)
    depth_rank = np.full(labels.shape, np.inf)
    for k in np.unique(labels):
        if k == 0:
            continue
        mask = grabcut_instance(image, labels == k, cfg.band, cfg.grabcut_iterations)
        # a pixel the render gave to another instance stays with it (the render knows occlusion)
        mask &= (labels == k) | (labels == 0)
        take = mask & (order[k] < depth_rank)
        out[take] = k
        depth_rank[take] = order[k]
    return out


def guided_labels(image: np.ndarray, weights: np.ndarray, cfg: BorderConfig) -> np.ndarray:
    """Guided filter of the rendered one-hot weights with the image as guide, then the arg-max.

    Args:
        image: [H, W, 3] uint8 RGB.
        weights: [H, W, K+1] rendered one-hot weights.
    """
    guide = image.astype(np.float32) / 255.0
    unassigned = np.clip(1.0 - weights.sum(-1, keepdims=True), 0.0, 1.0)
    stack = np.concatenate([weights[..., :1] + unassigned, weights[..., 1:]], -1).astype(np.float32)
    filtered = np.stack(
        [cv2.ximgproc.guidedFilter(guide, np.ascontiguousarray(stack[..., c]), cfg.guided_radius, cfg.guided_eps) for c in range(stack.shape[-1])],
        -1,
    )
    return np.argmax(filtered, axis=-1)


def front_to_back_order(labels: np.ndarray, depth: np.ndarray, num_instances: int) -> np.ndarray:
    """Rank of each instance by its median rendered depth in the view ([K+1], unseen last)."""
    median = np.full(num_instances + 1, np.inf)
    for k in np.unique(labels):
        if k > 0:
            median[k] = float(np.median(depth[labels == k]))
    return np.argsort(np.argsort(median, kind="stable"), kind="stable")


@torch.no_grad()
def render_instance_masks(
    model, camera, instance_of_gaussian: torch.Tensor, num_instances: int, image: Optional[np.ndarray],
    cfg: BorderConfig, distortion: Optional[np.ndarray] = None,
) -> np.ndarray:
    """The instance mask of one view.

    Args:
        model: the base model (``render_features``).
        camera: one nerfstudio camera.
        instance_of_gaussian: [N] instance id per Gaussian (0 = background).
        image: [H, W, 3] uint8 RGB of the frame (needed unless ``cfg.method == "none"``).
        distortion: [6] OpenCV distortion of the frame, or None.

    Returns:
        [H, W] uint16 mask (0 = background, k = instance k).
    """
    features = one_hot_labels(instance_of_gaussian, num_instances).to(model.device)
    weights, _, depth = model.render_features(camera, features)
    labels = labels_from_weights(weights, cfg.min_weight).cpu().numpy()
    weights, depth = weights.cpu().numpy(), depth[..., 0].cpu().numpy()
    if distortion is not None and np.any(distortion):  # clean up in the captured image's geometry
        K = camera.get_intrinsics_matrices().reshape(3, 3).double().cpu().numpy()  # the camera may be on CUDA
        labels = distort_map(labels, K, distortion)
        depth = distort_map(depth, K, distortion)
        weights = distort_map(weights, K, distortion, nearest=False)
    if cfg.method == "grabcut":
        labels = grabcut_labels(image, labels, front_to_back_order(labels, depth, num_instances), cfg)
    elif cfg.method == "guided":
        labels = guided_labels(image, weights, cfg)
    return labels.astype(np.uint16)
