"""Instances from clicks: query features, Gaussian selection by threshold, rendered 2D masks."""

from __future__ import annotations

from typing import Dict, List

import torch
import torch.nn.functional as F


def feature_distance_to_queries(features: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """Cosine distance of every feature to every query.

    Args:
        features: [..., D]
        queries: [M, D]

    Returns:
        [..., M] in [0, 2].
    """
    return 1.0 - F.normalize(features, dim=-1, eps=1e-8) @ F.normalize(queries, dim=-1, eps=1e-8).T


def select_gaussians(gaussian_features: torch.Tensor, queries: torch.Tensor, tau: float = 0.1) -> torch.Tensor:
    """Instance label of each Gaussian: the closest query within ``tau``, else 0 (background).

    Args:
        gaussian_features: [N, D] per-Gaussian contrastive features.
        queries: [M, D] one query feature per clicked instance.

    Returns:
        [N] long labels, k in 1..M for instance k (query k−1), 0 for background.
    """
    if queries.shape[0] == 0:
        return torch.zeros(gaussian_features.shape[0], dtype=torch.long, device=gaussian_features.device)
    distance = feature_distance_to_queries(gaussian_features, queries)
    best, idx = distance.min(dim=-1)
    return torch.where(best <= tau, idx + 1, torch.zeros_like(idx))


def masks_from_rendered_features(
    rendered: torch.Tensor, alpha: torch.Tensor, queries: torch.Tensor, tau: float = 0.1, min_alpha: float = 0.5
) -> torch.Tensor:
    """2D instance masks of one view by comparing rendered features with the queries.

    Args:
        rendered: [H, W, D] rendered features.
        alpha: [H, W, 1] accumulated opacity (pixels with little coverage stay background).
        queries: [M, D].

    Returns:
        [H, W] long labels (0 = background, k = instance k).
    """
    labels = select_gaussians(rendered.reshape(-1, rendered.shape[-1]), queries, tau).reshape(rendered.shape[:2])
    return torch.where(alpha[..., 0] >= min_alpha, labels, torch.zeros_like(labels))


def mask_coverage_counts(masks: torch.Tensor, instance_alpha: torch.Tensor, min_alpha: float = 0.5) -> torch.Tensor:
    """Per instance, how many of its mask's pixels its selected Gaussians cover, in one view.

    Carving removes the unselected Gaussians whose centres lie inside the masks in every view, so an instance
    whose selected Gaussians cover little of its mask (contrastive features not yet converged: the rendered
    feature blends to the query where most single Gaussians stay beyond ``tau``) loses the rest of itself.

    Args:
        masks: [H, W] long labels (0 = background, k = instance k), as from :func:`masks_from_rendered_features`.
        instance_alpha: [H, W, M] accumulated opacity of each instance's selected Gaussians alone.

    Returns:
        [M, 2] long: (pixels of mask k covered with opacity ≥ ``min_alpha``, pixels of mask k).
    """
    M = instance_alpha.shape[-1]
    ids = torch.arange(1, M + 1, device=masks.device)
    in_mask = masks[..., None] == ids  # [H, W, M]
    covered = in_mask & (instance_alpha >= min_alpha)
    return torch.stack([covered.sum(dim=(0, 1)), in_mask.sum(dim=(0, 1))], dim=-1)


def undercovered_instances(instances: List[Dict], coverage: List[float], min_coverage: float) -> List[str]:
    """One warning per instance whose selected Gaussians cover less than ``min_coverage`` of its rendered masks.

    Args:
        instances: ``[{"id", "class", "num_gaussians"}, ...]`` (the selection's summary).
        coverage: per instance, the covered share of its mask pixels over the training views
            (from :func:`mask_coverage_counts`).
    """
    return [
        f"instance {instance['id']} ({instance['class']}, {instance['num_gaussians']} Gaussians) covers {share:.0%} of "
        "its rendered masks, and if it is replaced carving removes the rest of it as leftovers: the contrastive "
        "features are likely undertrained (more --pipeline.contrastive-iterations, or a larger "
        "--pipeline.segmentation.tau)"
        for instance, share in zip(instances, coverage)
        if share < min_coverage
    ]
