"""Contrastive loss on rendered per-pixel features (paper §4.1)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import torch
import torch.nn.functional as F


@dataclass
class ContrastiveLossConfig:
    margin: float = 0.3
    """Different-mask pairs are pushed until their cosine similarity is below this (distance > 1 − margin)."""
    hard_threshold: float = 0.5
    """Same-mask pairs farther apart than this get an extra pull term."""
    unit_norm_lambda: float = 0.1
    """Weight of the regulariser pulling rendered feature norms to 1."""
    max_pairs: int = 65536
    """Random pairs drawn from the sampled pixels per step."""


def cosine_distance(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """``1 − cos(a, b)`` along the last axis: [..., D] × [..., D] → [...], in [0, 2]."""
    return 1.0 - F.cosine_similarity(a, b, dim=-1, eps=eps)


def contrastive_loss(
    features: torch.Tensor,
    labels: torch.Tensor,
    config: ContrastiveLossConfig = ContrastiveLossConfig(),
    generator: torch.Generator | None = None,
) -> Dict[str, torch.Tensor]:
    """Pull same-label pixel features together, push different labels apart.

    The pull term is weighted by the negative/positive pair ratio (negatives dominate), positives
    with distance > ``hard_threshold`` get an extra pull, negatives with cosine similarity above
    ``margin`` are pushed,
    and rendered feature norms are regularised toward 1.

    Args:
        features: [P, D] rendered features at the sampled pixels.
        labels: [P] mask label of each pixel (0 = background).

    Returns:
        dict of scalar losses: ``pull``, ``push``, ``hard_pull``, ``unit_norm``.
    """
    P = features.shape[0]
    n_pairs = min(config.max_pairs, P * (P - 1) // 2) if P > 1 else 0
    zero = features.sum() * 0.0
    if n_pairs == 0:
        return {"pull": zero, "push": zero, "hard_pull": zero, "unit_norm": zero}
    i = torch.randint(0, P, (n_pairs,), generator=generator, device="cpu").to(features.device)
    j = torch.randint(0, P - 1, (n_pairs,), generator=generator, device="cpu").to(features.device)
    j = j + (j >= i).long()  # never pair a pixel with itself
    # index_select, not features[i]: the backward of advanced indexing accumulates with atomic adds on more than
    # one CPU thread (a different sum on every run); index_select's backward (index_add_) adds in a fixed order
    distance = cosine_distance(features.index_select(0, i), features.index_select(0, j))
    positive = labels[i] == labels[j]
    n_pos = positive.sum().clamp_min(1)
    n_neg = (~positive).sum().clamp_min(1)
    ratio = n_neg.float() / n_pos.float()

    pull = ratio * (distance * positive).sum() / n_pairs
    hard = positive & (distance > config.hard_threshold)
    hard_pull = ratio * (distance * hard).sum() / n_pairs
    push = (F.relu((1.0 - distance) - config.margin) * ~positive).sum() / n_pairs
    unit_norm = config.unit_norm_lambda * ((features.norm(dim=-1) - 1.0) ** 2).mean()
    return {"pull": pull, "push": push, "hard_pull": hard_pull, "unit_norm": unit_norm}
