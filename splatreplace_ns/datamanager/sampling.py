"""Pixel sampling for contrastive learning: ``M_u`` uniform pixels plus ``M_s`` per mask."""

from __future__ import annotations

from typing import Optional, Tuple

import torch


def sample_contrastive_pixels(
    instance_mask: torch.Tensor,
    n_uniform: int = 4096,
    n_per_mask: int = 4096,
    generator: Optional[torch.Generator] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Samples pixels so that large masks get more samples and small masks still get enough.

    Background (label 0, the complement of the union of the masks) counts as one more mask.

    Args:
        instance_mask: [H, W] or [H, W, 1] integer labels, 0 = background.
        n_uniform: ``M_u``, pixels drawn uniformly over the image.
        n_per_mask: ``M_s``, pixels drawn uniformly inside each label present.

    Returns:
        pixel_index [P] (flat ``y * W + x``, long) and labels [P] (long), P = M_u + M_s · #labels.
    """
    labels_flat = instance_mask.reshape(-1).long()
    device = labels_flat.device
    num_pixels = labels_flat.numel()
    picks = [torch.randint(0, num_pixels, (n_uniform,), generator=generator, device="cpu").to(device)]
    if n_per_mask > 0:
        order = torch.argsort(labels_flat, stable=True)
        present, counts = torch.unique_consecutive(labels_flat[order], return_counts=True)
        starts = torch.cumsum(counts, 0) - counts
        # one uniform draw per (label, sample): offset inside that label's run of sorted pixels
        u = torch.rand((len(present), n_per_mask), generator=generator, device="cpu").to(device)
        offsets = (u * counts[:, None]).long().clamp_max(counts[:, None] - 1)
        picks.append(order[(starts[:, None] + offsets).reshape(-1)])
    pixel_index = torch.cat(picks)
    return pixel_index, labels_flat[pixel_index]
