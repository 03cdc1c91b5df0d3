"""Instances from clicks: query features, Gaussian selection by threshold, rendered 2D masks."""

from __future__ import annotations

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
