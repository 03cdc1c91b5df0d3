"""Instance labels of Gaussians from 2D instance masks (ground truth, for evaluating later stages alone).

Each Gaussian's centre is projected into every view where it is visible; the mask id under it is a vote,
and the most voted id wins. Background (0) votes count like the others, so a Gaussian that mostly lands
on background pixels stays background. Used by ``splatreplace bench register`` to measure registration
without the segmentation stage in the way.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch


def labels_from_masks(
    means: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    masks: torch.Tensor,
    depths: Optional[torch.Tensor] = None,
    depth_tolerance: float = 0.02,
    near: float = 0.01,
) -> torch.Tensor:
    """Majority vote of the mask id at each Gaussian's projected centre over the views that see it.

    A view votes for a Gaussian when its centre is in front of the camera (``z > near``), projects inside
    the image, and is not hidden: with ``depths`` given, ``z <= depth · (1 + depth_tolerance)`` at that
    pixel (pixels with depth 0 have no surface and hide nothing). Pixel ``(col, row)`` covers
    ``[col, col+1) × [row, row+1)`` in continuous coordinates (the renderer's convention).

    Args:
        means: [N, 3] centres (world).
        viewmats: [V, 4, 4] world→camera (OpenCV: x right, y down, z forward).
        Ks: [V, 3, 3] intrinsics at ``width × height``.
        width, height: image size of the masks.
        masks: [V, H, W] integer instance ids (0 = background, k > 0 = instance k).
        depths: [V, H, W] rendered z-depth of the scene (0 where empty), or None to skip the visibility test.
        depth_tolerance: relative depth margin of the visibility test.
        near: centres closer than this to the camera plane do not vote.

    Returns:
        [N] int64 labels: the id with the most votes (ties go to the smaller id, so background wins a tie);
        0 for Gaussians no view votes for.
    """
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"labels_from_masks: means must be [N, 3], got {tuple(means.shape)}")
    V = viewmats.shape[0]
    if viewmats.shape != (V, 4, 4) or Ks.shape != (V, 3, 3):
        raise ValueError(
            f"labels_from_masks: need viewmats [V, 4, 4] and Ks [V, 3, 3] for the same V, got "
            f"{tuple(viewmats.shape)} and {tuple(Ks.shape)}"
        )
    if masks.shape != (V, height, width):
        raise ValueError(f"labels_from_masks: masks must be [{V}, {height}, {width}], got {tuple(masks.shape)}")
    if depths is not None and depths.shape != masks.shape:
        raise ValueError(f"labels_from_masks: depths {tuple(depths.shape)} must match masks {tuple(masks.shape)}")
    if masks.is_floating_point():
        raise ValueError("labels_from_masks: masks must hold integer instance ids")
    N = means.shape[0]
    device = means.device
    if N == 0 or V == 0:
        return torch.zeros(N, dtype=torch.long, device=device)
    masks = masks.to(device=device, dtype=torch.long)
    if int(masks.min()) < 0:
        raise ValueError("labels_from_masks: masks hold negative ids; 0 is background, instances are > 0")
    num_ids = int(masks.max()) + 1
    votes = torch.zeros(N, num_ids, dtype=torch.int32, device=device)
    points = means.detach().to(torch.float64)
    homogeneous = torch.cat([points, torch.ones_like(points[:, :1])], dim=-1)  # [N, 4]
    ones = torch.ones(N, dtype=torch.int32, device=device)
    for view in range(V):  # views are few; Gaussians are vectorised
        cam = homogeneous @ viewmats[view].to(device=device, dtype=torch.float64).T  # [N, 4]
        z = cam[:, 2]
        pix = cam[:, :3] @ Ks[view].to(device=device, dtype=torch.float64).T
        u = pix[:, 0] / z.clamp_min(near)
        v = pix[:, 1] / z.clamp_min(near)
        seen = (z > near) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        col = u.clamp(0, width - 1).long()
        row = v.clamp(0, height - 1).long()
        if depths is not None:
            surface = depths[view].to(device=device, dtype=torch.float64)[row, col]
            seen &= (surface <= 0) | (z <= surface * (1.0 + depth_tolerance))
        ids = masks[view][row, col]
        votes.index_put_((torch.nonzero(seen).squeeze(-1), ids[seen]), ones[seen], accumulate=True)
    # argmax returns the first maximum: the smaller id wins ties; rows without votes give 0
    return votes.argmax(dim=-1).to(torch.long)


def training_views(pipeline) -> Tuple[torch.Tensor, torch.Tensor, int, int]:
    """World→camera (OpenCV) matrices [V, 4, 4], intrinsics [V, 3, 3] and (W, H) of the training cameras."""
    from splatreplace_ns.render.cameras import world_to_camera

    cameras = pipeline.datamanager.train_dataset.cameras
    viewmats = world_to_camera(cameras.camera_to_worlds.float()).detach().cpu()
    Ks = cameras.get_intrinsics_matrices().float().cpu()
    return viewmats, Ks, int(cameras.width[0]), int(cameras.height[0])


@torch.no_grad()
def label_gaussians_from_ground_truth(pipeline, depth_tolerance: float) -> torch.Tensor:
    """[N] instance of each Gaussian from the training views' ground-truth masks (visibility: rendered depth)."""
    model = pipeline.model
    dataset = pipeline.datamanager.train_dataset
    viewmats, Ks, width, height = training_views(pipeline)
    ones = torch.ones(model.num_points, 1, device=model.means.device)
    masks, depths = [], []
    for idx in range(len(dataset)):
        try:
            masks.append(pipeline.datamanager.train_instance_mask(idx).long())
        except ValueError as err:
            raise ValueError(f"{err}; the bench needs ground-truth masks") from None
        _, alpha, depth = model.render_features(dataset.cameras[idx : idx + 1], features=ones)
        depths.append(torch.where(alpha[..., 0] > 0, depth[..., 0], torch.zeros_like(depth[..., 0])).cpu())
    return labels_from_masks(
        model.means.detach().cpu(), viewmats, Ks, width, height, torch.stack(masks), torch.stack(depths),
        depth_tolerance,
    )
