"""Space carving of leftover background Gaussians (paper §4.1, post-processing)."""

from __future__ import annotations

import torch


def carve_mask(
    means: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    instance_masks: torch.Tensor,
    rendered_depths: torch.Tensor,
    depth_tolerance: float = 0.02,
    near: float = 0.01,
    mask_tolerance: int = 0,
) -> torch.Tensor:
    """Which background Gaussians to remove.

    A Gaussian is removed when, in *every* training view, its centre projects inside an instance
    mask, or outside the image, or is not visible (behind the camera, or behind the rendered surface
    by more than ``depth_tolerance`` relative depth) — the paper's three conditions — *and* it projects
    inside an instance mask in at least one view. The last condition is ours: the paper removes residual
    Gaussians of the instances, and visibility judged against the rendered (expected) depth counts the
    contributing Gaussians of any fuzzy surface as hidden: it lowers the share carved from 59 % to 33 % on a
    short-trained tiny scene and from 39 % to 32 % on the office demo.

    Args:
        means: [N, 3] centres of the background Gaussians.
        viewmats: [V, 4, 4] world→camera (OpenCV).
        Ks: [V, 3, 3] intrinsics.
        instance_masks: [V, H, W] bool, union of the instance masks of each view.
        rendered_depths: [V, H, W] expected depth of the full scene in each view (0 where empty).
        mask_tolerance: a centre within this many pixels of a mask counts as inside it (the masks are
            thresholded renders: a chair leg one or two pixels wide is often missing from them, and a
            leftover inside it then looks like visible background in that view).

    Returns:
        [N] bool, True = remove.
    """
    if mask_tolerance > 0:
        size = 2 * int(mask_tolerance) + 1
        instance_masks = torch.nn.functional.max_pool2d(
            instance_masks[:, None].float(), size, stride=1, padding=int(mask_tolerance)
        )[:, 0] > 0
    N = means.shape[0]
    remove = torch.ones(N, dtype=torch.bool, device=means.device)
    touches_an_instance = torch.zeros(N, dtype=torch.bool, device=means.device)
    homogeneous = torch.cat([means, torch.ones_like(means[:, :1])], dim=-1)  # [N, 4]
    for view in range(viewmats.shape[0]):  # views are few; Gaussians are vectorised
        cam = homogeneous @ viewmats[view].T  # [N, 4]
        z = cam[:, 2]
        in_front = z > near
        pix = cam[:, :3] @ Ks[view].T
        u = pix[:, 0] / z.clamp_min(near)
        v = pix[:, 1] / z.clamp_min(near)
        inside = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        col = u.clamp(0, width - 1).long()
        row = v.clamp(0, height - 1).long()
        in_mask = inside & instance_masks[view][row, col]
        surface = rendered_depths[view][row, col]
        occluded = inside & (surface > 0) & (z > surface * (1.0 + depth_tolerance))
        remove &= (~inside) | in_mask | occluded
        touches_an_instance |= in_mask
    return remove & touches_an_instance


def carved_instance(
    means: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    label_masks: torch.Tensor,
    near: float = 0.01,
    mask_tolerance: int = 0,
) -> torch.Tensor:
    """Which instance each Gaussian is a leftover of: the instance whose mask its centre projects into in the
    most views (ties: the lower id). A Gaussian carved for an instance that is then not replaced is part of
    what that instance looks like, and stays.

    Args:
        means: [N, 3] centres; viewmats: [V, 4, 4] world→camera (OpenCV); Ks: [V, 3, 3] intrinsics.
        label_masks: [V, H, W] integer instance ids per view (0 = background).
        mask_tolerance: a centre within this many pixels of a mask counts as inside it (the highest id nearby).

    Returns:
        [N] long, the instance id (0: inside no instance's mask in any view).
    """
    labels = label_masks.long()
    if mask_tolerance > 0:
        size = 2 * int(mask_tolerance) + 1
        labels = torch.nn.functional.max_pool2d(labels[:, None].float(), size, stride=1,
                                                padding=int(mask_tolerance))[:, 0].round().long()
    N, M = means.shape[0], int(labels.max()) if labels.numel() else 0
    votes = torch.zeros(N, M + 1, dtype=torch.long, device=means.device)
    homogeneous = torch.cat([means, torch.ones_like(means[:, :1])], dim=-1)  # [N, 4]
    rows = torch.arange(N, device=means.device)
    for view in range(viewmats.shape[0]):
        cam = homogeneous @ viewmats[view].T
        z = cam[:, 2]
        pix = cam[:, :3] @ Ks[view].T
        u = pix[:, 0] / z.clamp_min(near)
        v = pix[:, 1] / z.clamp_min(near)
        inside = (z > near) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        label = labels[view][v.clamp(0, height - 1).long(), u.clamp(0, width - 1).long()]
        label = torch.where(inside, label, torch.zeros_like(label))
        votes[rows, label] += 1
    votes[:, 0] = 0  # background views do not vote
    best = votes.argmax(dim=1)  # the first (lowest id) of equal counts
    return torch.where(votes.max(dim=1).values > 0, best, torch.zeros_like(best))
