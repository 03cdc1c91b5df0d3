"""Instance labels of Gaussians by weighted voting of 2D instance masks (an alternative to the contrastive stage).

Where every training view has an instance mask, each Gaussian can take the label of the mask pixels it is
rendered into, weighted by how much it contributes to them: its blending weight ``w_i(p) = T_i(p) α_i(p)``
(transmittance times opacity, the weight of its feature in pixel ``p``). Summed over the pixels of every
training view, label by label, these are the Gaussian's votes; it takes the label with the most (background,
label 0, votes like the instances). A Gaussian hidden behind an opaque one gets little weight anywhere, so the
surface decides; a Gaussian no view renders gets no vote and stays background.

The weights come from the project's rasteriser without a special kernel: the rendered feature of a pixel is
``Σ_i w_i(p) f_i``, linear in the per-Gaussian features ``f``, so with ``f = 0`` and the loss
``Σ_p f̂(p)[mask(p)]`` (the rendered channel of each pixel's label) the gradient with respect to ``f_i[c]`` is
``Σ_{p: mask(p) = c} w_i(p)``, exactly the votes. One render and one backward pass per view, with as many
channels as the view has labels.

With the voting lift (``--pipeline.segmentation.lift voting``) the Gaussians' features for the click selection
are the one-hot voted labels (:func:`voted_features`), and a click's query is the one-hot label rendered at its
pixel (:func:`snap_query`): the contrastive stage's selection, masks, carving and registration then run on them
unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import torch

from splatreplace_ns.instances.masks2d import labels_from_weights, one_hot_labels


@dataclass
class Votes:
    """Result of :func:`vote_labels`."""

    labels: torch.Tensor
    """[N] int64 label of each Gaussian (0 = background, also where no view gave it weight)."""
    weights: torch.Tensor
    """[N, K+1] float32 blending weight per label summed over the views (column k = label k)."""
    views: int
    """How many views voted."""

    @property
    def share(self) -> torch.Tensor:
        """[N] the winning label's share of the Gaussian's total weight (0 where it has none)."""
        total = self.weights.sum(-1)
        best = self.weights.gather(-1, self.labels[:, None])[:, 0]
        return torch.where(total > 0, best / total.clamp_min(1e-12), torch.zeros_like(total))


def view_label_weights(render: Callable[[torch.Tensor], torch.Tensor], mask: torch.Tensor, num_gaussians: int,
                       device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Blending weight of every Gaussian in the pixels of each label of one view.

    Args:
        render: ``render(features [N, C]) -> [H, W, C]``, the composited features of the view (differentiable in
            ``features``; geometry fixed).
        mask: [H, W] integer labels (0 = background) at the render's size.
        num_gaussians: N.

    Returns:
        ``(labels [C] int64, weights [N, C] float32)``: the labels present in the mask, sorted, and per Gaussian
        the weight summed over the pixels of each (non-finite sums, from a Gaussian with non-finite parameters
        and those it hides, are 0).
    """
    mask = mask.to(device).long()
    present, channel = torch.unique(mask, return_inverse=True)  # [C], [H, W] index into present
    features = torch.zeros(num_gaussians, present.shape[0], device=device, requires_grad=True)
    with torch.enable_grad():
        rendered = render(features)
        if tuple(rendered.shape[:2]) != tuple(mask.shape):
            raise ValueError(f"mask of size {tuple(mask.shape)} (H, W) for a view rendered at {tuple(rendered.shape[:2])}")
        picked = rendered.gather(-1, channel[..., None])  # [H, W, 1]: the channel of each pixel's own label
        (grad,) = torch.autograd.grad(picked.sum(), features, allow_unused=True)
    if grad is None:  # nothing the render depends on (no Gaussian in the view)
        grad = torch.zeros_like(features)
    return present, torch.nan_to_num(grad.detach().float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)


def vote_labels(render_view: Callable[[int, torch.Tensor], torch.Tensor], masks: Iterable[torch.Tensor],
                num_gaussians: int, min_share: float = 0.0, device=None) -> Votes:
    """Each Gaussian's label: the one that gets most of its blending weight summed over the views.

    Args:
        render_view: ``render_view(v, features [N, C]) -> [H, W, C]``, the composited features of view ``v``
            (e.g. ``model.render_features(cameras[v : v + 1], features)[0]``).
        masks: the views' [H, W] integer masks, in view order (a generator is fine: one at a time is held).
        num_gaussians: N.
        min_share: the winner also needs more than this share of the Gaussian's total weight, else it stays
            background (0: plain arg-max; 0.5: a majority).

    Returns:
        :class:`Votes`; ties go to the smaller label (so background wins a tie).
    """
    weights = torch.zeros(num_gaussians, 1, device=device)
    views = 0
    for view, mask in enumerate(masks):
        present, w = view_label_weights(lambda f: render_view(view, f), mask, num_gaussians, device)
        if present.numel() and int(present.min()) < 0:
            raise ValueError(f"view {view}: negative label {int(present.min())} in its mask")
        top = int(present.max()) + 1 if present.numel() else 0
        if top > weights.shape[1]:
            weights = torch.cat([weights, weights.new_zeros(num_gaussians, top - weights.shape[1])], dim=1)
        weights.index_add_(1, present.to(weights.device), w.to(weights.device))
        views += 1
    return Votes(labels=labels_from_votes(weights, min_share), weights=weights, views=views)


def labels_from_votes(weights: torch.Tensor, min_share: float = 0.0) -> torch.Tensor:
    """[N, K+1] summed weights → [N] int64 winning label (0 where there is no weight or the winner's share is
    not above ``min_share``; ties go to the smaller label)."""
    if weights.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=weights.device)
    best, _ = weights.max(dim=-1)
    index = torch.arange(weights.shape[1], device=weights.device).expand_as(weights)
    winner = torch.where(weights == best[:, None], index, torch.full_like(index, weights.shape[1])).min(-1).values
    total = weights.sum(-1)
    keep = (best > 0) & (best > min_share * total)
    return torch.where(keep, winner, torch.zeros_like(winner))


def voted_features(votes: Votes) -> torch.Tensor:
    """[N, K+1] one-hot voted labels (channel 0 = background): the per-Gaussian features the click selection
    compares with a click's query (cosine distance 0 to the same label, 1 to another)."""
    return one_hot_labels(votes.labels, votes.weights.shape[1] - 1).to(votes.weights.device)


def background_query(votes: Votes) -> torch.Tensor:
    """[K+1] the background's query (label 0): a click whose query is this is refused as background."""
    return one_hot_labels(torch.zeros(1, dtype=torch.long), votes.weights.shape[1] - 1)[0].to(votes.weights.device)


def snap_query(rendered: torch.Tensor) -> torch.Tensor:
    """A click's query from the voted labels rendered at its pixel: [K+1] blended one-hot → [K+1] one-hot of the
    label with the most weight there (all zeros where nothing is rendered, which the selection refuses)."""
    label = labels_from_weights(rendered[None, None], 0.0).reshape(1)
    if not bool(torch.isfinite(rendered).all()) or float(rendered.sum()) <= 0:
        return torch.zeros_like(rendered)
    return one_hot_labels(label, rendered.shape[-1] - 1)[0].to(rendered)


def vote_training_views(model, cameras, mask_of: Callable[[int], torch.Tensor], min_share: float = 0.0,
                        device=None) -> Votes:
    """:func:`vote_labels` over every training view, rendered with ``model.render_features`` (geometry detached; the
    model's backend).

    Args:
        cameras: the training views' nerfstudio ``Cameras`` (as trained: undistorted, cropped).
        mask_of: ``mask_of(v) -> [H, W]`` instance mask of view ``v`` in the same geometry (the datamanager's
            ``train_instance_mask``).
    """

    def render_view(view: int, features: torch.Tensor) -> torch.Tensor:
        return model.render_features(cameras[view : view + 1].to(device), features)[0]

    return vote_labels(render_view, (mask_of(v) for v in range(len(cameras))), model.num_points, min_share, device)


def votes_from_labels(labels: torch.Tensor, num_labels: int) -> Votes:
    """Labels already known per Gaussian (the geometric masks step's instance ids, made from the clicks on the same
    Gaussians) as :class:`Votes`, each Gaussian with all of its one unit of weight on its label: no 3D → 2D → 3D
    round trip through rendered masks.

    Args:
        labels: [N] int label of each Gaussian (0 = background).
        num_labels: K, the largest label (the weights get K + 1 columns).
    """
    labels = labels.long().clamp(0, num_labels)
    return Votes(labels=labels, weights=one_hot_labels(labels, num_labels).float(), views=0)
