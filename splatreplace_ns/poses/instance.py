"""What registration takes and gives: an instance's Gaussians, its rendered virtual views, and the registration result
of one instance onto its class template."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from splatreplace_ns.poses.virtual_cameras import fit_sphere


def float64_array(x) -> np.ndarray:
    """A tensor or array-like as a float64 numpy array (on the CPU)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


@dataclass
class InstanceGaussians:
    """The Gaussians of one instance (a subset of the scene's), in world coordinates.

    Attributes:
        means: (N, 3) centres.
        quats: (N, 4) rotations, wxyz (any norm).
        scales: (N, 3) linear scales (not log).
        opacities: (N,) in [0, 1] (not logits).
        colors: (N, 3) RGB in [0, 1], or (N, K, 3) SH coefficients (then ``sh_degree`` gives the degree;
            if None it is inferred from K = (d + 1)²).
        sh_degree: SH degree of ``colors`` or None for plain RGB.
        id: instance id (used in results and messages).
    Arrays may be numpy or torch (any device; CUDA tensors render with gsplat).
    """

    means: Any
    quats: Any
    scales: Any
    opacities: Any
    colors: Any
    sh_degree: Optional[int] = None
    id: Optional[int] = None

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def centres(self) -> np.ndarray:
        """(N, 3) float64 numpy copy of the centres."""
        return float64_array(self.means).reshape(-1, 3)

    def solid(self, min_opacity: float, min_points: int) -> np.ndarray:
        """(N,) bool: the Gaussians at least ``min_opacity`` opaque, or all of them when fewer than
        ``min_points`` are."""
        keep = float64_array(self.opacities).reshape(-1) >= min_opacity
        return keep if int(keep.sum()) >= min_points else np.ones_like(keep)


@dataclass
class InstanceViews:
    """Rendered views of one instance (output of :func:`render_instance_views`).

    Attributes:
        images: (V, H, W, 3) float32 RGB in [0, 1]; depths: (V, H, W) float32 z-depth (0 = empty);
        alphas: (V, H, W) float32; viewmats: (V, 4, 4) float64 world→camera; Ks: (V, 3, 3) float64.
    """

    images: np.ndarray
    depths: np.ndarray
    alphas: np.ndarray
    viewmats: np.ndarray
    Ks: np.ndarray

    def __iter__(self):  # unpack as (images, depths, alphas, viewmats, K)
        K = self.Ks[0] if len(self.Ks) and np.allclose(self.Ks, self.Ks[:1]) else self.Ks
        return iter((self.images, self.depths, self.alphas, self.viewmats, K))

    @property
    def size(self) -> tuple[int, int]:
        """(W, H)."""
        return int(self.images.shape[2]), int(self.images.shape[1])


@dataclass
class RegistrationResult:
    """Source→template registration of one instance.

    Attributes:
        instance_id, template_id: ids of the source and of its class template.
        transform: (4, 4) float64 rigid, template ≈ transform · source (world frame); identity on failure.
        success: whether a pose was found.
        num_inliers: PnP inliers of the chosen view pair (0 for the template / fpfh).
        fitness: fraction of source centres with a template centre within the ICP distance after
            registration (FPFH inlier fraction when ICP is off; 1 for the template itself).
        message: what happened (names the instance on failure).
        time_s: wall time of this registration.
        pair: (source view, template view) of the chosen pair, or None.
        coarse_transform: (4, 4) transform before ICP.
        proposed_transform: (4, 4) the pose chosen before the acceptance test (equal to ``transform`` when
            accepted; None when no candidate was posed): what a refusal refused.
        candidates: one dict per refined candidate pose: ``transform`` (4, 4), ``fitness``, ``colour`` (the
            colour score; None with ``select="inliers"``), ``inliers`` (0 for a multi-start turn), ``pair``
            (source view, template view), or (-1, k) for turn k.
    """

    instance_id: int
    template_id: int
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    success: bool = False
    num_inliers: int = 0
    fitness: float = 0.0
    message: str = ""
    time_s: float = 0.0
    pair: Optional[tuple[int, int]] = None
    coarse_transform: Optional[np.ndarray] = None
    proposed_transform: Optional[np.ndarray] = None
    candidates: list = field(default_factory=list)


def instance_sphere(inst: InstanceGaussians) -> tuple[np.ndarray, float]:
    """Robust bounding sphere of the instance's centres → center (3,), radius."""
    return fit_sphere(inst.centres())
