"""One click per instance → a set of Gaussians, with the checks that keep bad clicks harmless.

Used by both the non-interactive path (``clicks.json``) and the viewer. Every rejected click raises
:class:`SelectionError` with a message naming the click, and leaves the selection unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import torch

from splatreplace_ns.datamanager.clicks import pixel_index
from splatreplace_ns.instances.select import feature_distance_to_queries, select_gaussians


class SelectionError(ValueError):
    """A click that cannot become an instance (outside the image, on background, duplicate, empty)."""


@dataclass
class SelectedInstance:
    id: int
    """Instance id (1-based, the label used in masks)."""
    cls: str
    """Class name; instances of one class share a template later."""
    query: torch.Tensor
    """[D] query feature (rendered feature at the clicked pixel)."""
    num_gaussians: int
    source: str
    """Where the click came from (file and pixel, or the viewer)."""


@dataclass
class InstanceSelection:
    """The instances picked so far.

    Args:
        gaussian_features: callable returning the current [N, D] per-Gaussian features.
        background_query: [D] mean rendered feature of background pixels, or None when unknown.
        tau: cosine-distance threshold (paper: 0.1).
        duplicate_overlap: a new click whose Gaussians overlap an existing instance's by more than
            this fraction (of the smaller set) is the same instance clicked twice.
    """

    gaussian_features: Callable[[], torch.Tensor]
    background_query: Optional[torch.Tensor] = None
    tau: float = 0.1
    duplicate_overlap: float = 0.5
    instances: List[SelectedInstance] = field(default_factory=list)

    def add(self, query: torch.Tensor, cls: str, source: str) -> SelectedInstance:
        """Validates and adds one instance; raises SelectionError and changes nothing on a bad click."""
        if not bool(torch.isfinite(query).all()) or float(query.norm()) < 1e-6:
            raise SelectionError(f"{source}: no feature was rendered at this pixel (empty space); click on an object")
        if self.background_query is not None:
            distance = float(feature_distance_to_queries(query[None], self.background_query[None])[0, 0])
            if distance <= self.tau:
                raise SelectionError(f"{source}: this click is on the background, not on an instance")
        features = self.gaussian_features()
        chosen = select_gaussians(features, query[None], self.tau) == 1
        count = int(chosen.sum())
        if count == 0:
            raise SelectionError(f"{source}: no Gaussian has a feature within tau={self.tau} of this click")
        for other in self.instances:
            other_set = select_gaussians(features, other.query[None], self.tau) == 1
            overlap = int((chosen & other_set).sum()) / max(1, min(count, int(other_set.sum())))
            if overlap > self.duplicate_overlap:
                raise SelectionError(
                    f"{source}: selects the same Gaussians as instance {other.id} ({other.source}); "
                    "one click per instance"
                )
        instance = SelectedInstance(
            id=len(self.instances) + 1, cls=cls, query=query.detach().clone(), num_gaussians=count, source=source
        )
        self.instances.append(instance)
        return instance

    def undo(self) -> Optional[SelectedInstance]:
        """Removes the last instance (None when empty)."""
        return self.instances.pop() if self.instances else None

    @property
    def queries(self) -> torch.Tensor:
        """[M, D] the instances' query features."""
        if not self.instances:
            return torch.zeros(0, self.gaussian_features().shape[-1], device=self.gaussian_features().device)
        return torch.stack([inst.query for inst in self.instances])

    def labels(self) -> torch.Tensor:
        """[N] long: instance id of each Gaussian, 0 = background."""
        return select_gaussians(self.gaussian_features(), self.queries.to(self.gaussian_features().device), self.tau)

    def summary(self) -> List[Dict]:
        """JSON-friendly list of the instances."""
        return [
            {"id": i.id, "class": i.cls, "num_gaussians": i.num_gaussians, "source": i.source} for i in self.instances
        ]


def query_at_pixel(
    features: torch.Tensor, alpha: torch.Tensor, u: float, v: float, source: str, min_alpha: float = 0.5
) -> torch.Tensor:
    """The rendered feature at pixel (u, v) = (column, row) of one view.

    Args:
        features: [H, W, D] rendered features.
        alpha: [H, W, 1] accumulated opacity.

    Raises:
        SelectionError when the pixel is outside the image or nothing was rendered there.
    """
    H, W = features.shape[:2]
    pixel = pixel_index(u, v, W, H)
    if pixel is None:
        raise SelectionError(f"{source}: pixel ({u}, {v}) is outside the {W}x{H} image")
    row, col = pixel
    if float(alpha[row, col, 0]) < min_alpha:
        raise SelectionError(f"{source}: nothing is rendered at pixel ({u}, {v}) (alpha {float(alpha[row, col, 0]):.2f})")
    return features[row, col]
