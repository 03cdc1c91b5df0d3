"""Single-camera Gaussian splatting entry point with a pure-torch (CPU/GPU)
path and an optional gsplat (CUDA) path."""

from __future__ import annotations

import functools
import os
import warnings
from dataclasses import dataclass, field
from typing import Any, Dict, Optional

import torch
from torch import Tensor

from .projection import EPS2D, project_gaussians
from .raster_torch import RasterStats, rasterize_projected
from .sh import sh_to_color

__all__ = ["RenderOutput", "rasterize", "resolve_backend", "BACKEND_ENV_VAR"]

BACKEND_ENV_VAR = "SPLATREPLACE_RENDER_BACKEND"
_BACKENDS = ("auto", "torch", "gsplat")


@dataclass
class RenderOutput:
    """Result of :func:`rasterize` (single camera).

    image [H, W, D], depth [H, W, 1] (expected depth, 0 where alpha == 0),
    alpha [H, W, 1], means2d [1, N, 2] (non-leaf; ``retain_grad()`` works),
    radii [1, N] int32 (0 = culled).
    """

    image: Tensor
    depth: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    depths: Optional[Tensor] = None  # [1, N] camera-space z of each Gaussian
    conics: Optional[Tensor] = None  # [1, N, 3]
    width: int = 0
    height: int = 0
    backend: str = "torch"
    n_pairs: Optional[int] = None  # evaluated Gaussian-pixel pairs (torch path)
    extras: Dict[str, Any] = field(default_factory=dict)

    @property
    def info(self) -> Dict[str, Any]:
        """gsplat-style ``meta`` dict, as read by gsplat's densification
        strategies (``means2d``, ``radii``, ``width``, ``height``,
        ``n_cameras``)."""
        return {
            "means2d": self.means2d,
            "radii": self.radii,
            "depths": self.depths,
            "conics": self.conics,
            "width": self.width,
            "height": self.height,
            "n_cameras": 1,
            "camera_ids": None,
            "gaussian_ids": None,
            **self.extras,
        }


def resolve_backend(backend: str, device: torch.device) -> str:
    """'auto' -> 'gsplat' on CUDA when gsplat's kernels load, 'torch' otherwise.

    The environment variable ``SPLATREPLACE_RENDER_BACKEND`` overrides the
    request: ``torch`` forces the pure-torch path (also over an explicit
    ``"gsplat"``); ``gsplat`` / ``auto`` replace an ``"auto"`` request.

    On CUDA, 'auto' falls back to the torch path with a warning when gsplat's
    CUDA kernels cannot be built or loaded (:func:`gsplat_unavailable_reason`),
    while an explicit 'gsplat' raises: gsplat itself imports without them and
    fails only at its first render.
    """
    if backend not in _BACKENDS:
        raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
    env = os.environ.get(BACKEND_ENV_VAR, "").strip().lower()
    if env:
        if env not in _BACKENDS:
            raise ValueError(f"{BACKEND_ENV_VAR} must be one of {_BACKENDS}, got {env!r}")
        if env == "torch" or backend == "auto":
            backend = env
    if backend == "auto":
        if device.type != "cuda":
            return "torch"
        reason = gsplat_unavailable_reason()
        if reason is None:
            return "gsplat"
        _warn_torch_fallback(reason)
        return "torch"
    if backend == "gsplat":
        if device.type != "cuda":
            raise RuntimeError(
                "backend='gsplat' requires CUDA tensors (gsplat's rasteriser is CUDA-only); "
                f"got tensors on {device}. Use backend='torch' or 'auto'."
            )
        reason = gsplat_unavailable_reason()
        if reason is not None:
            raise RuntimeError(f"backend='gsplat' is not usable here: {reason}. {_GSPLAT_HINT}")
    return backend


_GSPLAT_HINT = (
    "gsplat builds its CUDA kernels on first use (a few minutes, once per machine) and needs a CUDA toolkit (nvcc) "
    "whose version matches torch's; or render with backend='torch' "
    "(--pipeline.model.render-backend torch)"
)


@functools.lru_cache(maxsize=None)
def gsplat_unavailable_reason() -> Optional[str]:
    """None when gsplat's CUDA kernels load (building them first if needed); otherwise why they do not.

    gsplat 1.4 imports without its kernels: with no CUDA toolkit it prints a warning, leaves its extension
    unset and fails with an AttributeError at the first render, in the middle of a training run.
    """
    try:
        from gsplat.cuda._backend import _C
    except Exception as exc:  # not installed, or the kernels failed to build or load
        return f"gsplat's CUDA kernels could not be built or loaded ({type(exc).__name__}: {exc})"
    if _C is None:
        return "gsplat found no CUDA toolkit (nvcc) to build its CUDA kernels"
    return None


@functools.lru_cache(maxsize=None)
def _warn_torch_fallback(reason: str) -> None:
    warnings.warn(
        f"{reason}: rendering with the pure-torch path on the GPU instead (7-23x slower per render than gsplat "
        f"in `splatreplace bench render` on an H100). {_GSPLAT_HINT}",
        RuntimeWarning,
        stacklevel=3,
    )


def _check_inputs(means, quats, scales, opacities, colors, viewmat, K, sh_degree):
    N = means.shape[0]
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    if quats.shape != (N, 4):
        raise ValueError(f"quats must be [N, 4], got {tuple(quats.shape)}")
    if scales.shape != (N, 3):
        raise ValueError(f"scales must be [N, 3], got {tuple(scales.shape)}")
    if opacities.shape != (N,):
        raise ValueError(f"opacities must be [N], got {tuple(opacities.shape)}")
    if viewmat.shape != (4, 4):
        raise ValueError(f"viewmat must be [4, 4], got {tuple(viewmat.shape)}")
    if K.shape != (3, 3):
        raise ValueError(f"K must be [3, 3], got {tuple(K.shape)}")
    if sh_degree is None:
        if colors.dim() != 2 or colors.shape[0] != N or colors.shape[1] < 1:
            raise ValueError(f"colors must be [N, D] (D >= 1), got {tuple(colors.shape)}")
    else:
        if colors.dim() != 3 or colors.shape[0] != N or colors.shape[2] != 3:
            raise ValueError(f"SH coefficients must be [N, K, 3], got {tuple(colors.shape)}")
        if not 0 <= sh_degree <= 4:
            raise ValueError(f"sh_degree must be in 0..4, got {sh_degree}")
        if colors.shape[1] < (sh_degree + 1) ** 2:
            raise ValueError(
                f"sh_degree={sh_degree} needs K >= {(sh_degree + 1) ** 2}, got K={colors.shape[1]}"
            )


def _background(background: Optional[Tensor], D: int, like: Tensor) -> Optional[Tensor]:
    if background is None:
        return None
    bg = torch.as_tensor(background, device=like.device, dtype=like.dtype).reshape(-1)
    if bg.numel() == 1 and D != 1:
        bg = bg.expand(D)
    if bg.numel() != D:
        raise ValueError(f"background must have {D} channels, got {bg.numel()}")
    return bg


def _camera_center(viewmat: Tensor) -> Tensor:
    R = viewmat[:3, :3]
    t = viewmat[:3, 3]
    return -(R.T @ t)


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: Optional[int] = None,
    background: Optional[Tensor] = None,
    near: float = 0.01,
    far: float = 1e10,
    backend: str = "auto",
    absgrad: bool = False,
) -> RenderOutput:
    """Render N 3D Gaussians into one pinhole camera.

    Args:
        means [N, 3], quats [N, 4] (wxyz, any norm), scales [N, 3] (linear),
        opacities [N] (0..1).
        colors: [N, D] features (``sh_degree=None``) or [N, K, 3] SH
            coefficients (``sh_degree`` in 0..3/4); SH colours follow gsplat:
            ``clamp_min(SH(mean - camera_centre) + 0.5, 0)``.
        viewmat [4, 4] world->camera (OpenCV), K [3, 3].
        background: optional [D] colour composited behind.
        near, far: Gaussians with camera z < near or z > far are culled (as in
            gsplat's CUDA kernel, z == near is kept).
        backend: "auto" (gsplat on CUDA, torch otherwise; see
            :func:`resolve_backend`), "torch" or "gsplat".
        absgrad: gsplat only: also accumulate ``means2d.absgrad`` (what
            splatfacto's densification uses); the torch path has plain grads.

    The torch path culls a Gaussian with a NaN or infinite parameter (radius 0,
    zero gradients): the image is that of the finite Gaussians alone.

    Both backends follow gsplat's "classic" rasterisation: EWA projection with
    a 0.3 px^2 low-pass, ``alpha = min(0.999, o exp(-sigma))`` (gsplat's clamp),
    pairs below alpha 1/255 skipped, front-to-back compositing stopped before
    the transmittance drops to 1e-4.  ``depth`` is the expected depth
    ``sum_i w_i z_i / alpha`` (gsplat's "ED"), 0 where alpha is 0.
    """
    width = int(width)
    height = int(height)
    _check_inputs(means, quats, scales, opacities, colors, viewmat, K, sh_degree)
    D = 3 if sh_degree is not None else colors.shape[1]
    bg = _background(background, D, means)
    backend = resolve_backend(backend, means.device)
    if means.shape[0] == 0:
        return _render_empty(means, quats, scales, opacities, colors, D, bg, width, height, backend)
    if backend == "gsplat":
        return _rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmat, K, width, height,
            sh_degree, bg, near, far, absgrad,
        )
    if absgrad:
        raise ValueError("absgrad=True needs the gsplat backend; the torch path computes plain gradients")
    return _rasterize_torch(
        means, quats, scales, opacities, colors, viewmat, K, width, height,
        sh_degree, bg, near, far,
    )


def _render_empty(means, quats, scales, opacities, colors, D, bg, width, height, backend):
    dev, dtype = means.device, means.dtype
    # empty sums keep the outputs attached to the (empty) inputs' graph
    zero = means.sum() + quats.sum() + scales.sum() + opacities.sum() + colors.sum()
    image = torch.zeros(height, width, D, device=dev, dtype=dtype) + zero
    if bg is not None:
        image = image + bg
    alpha = torch.zeros(height, width, 1, device=dev, dtype=dtype) + zero
    depth = torch.zeros(height, width, 1, device=dev, dtype=dtype) + zero
    means2d = means.new_zeros(1, 0, 2) + zero
    return RenderOutput(
        image=image,
        depth=depth,
        alpha=alpha,
        means2d=means2d,
        radii=torch.zeros(1, 0, dtype=torch.int32, device=dev),
        depths=means.new_zeros(1, 0),
        conics=means.new_zeros(1, 0, 3),
        width=width,
        height=height,
        backend=backend,
        n_pairs=0,
    )


def non_finite_gaussians(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, sh_degree: Optional[int]
) -> Optional[Tensor]:
    """The Gaussians with a NaN or an infinite parameter, or None when there is none (the common case: one
    sum per parameter and one check).

    Args:
        means [N, 3], quats [N, 4], scales [N, 3], opacities [N]; colors [N, D], or [N, K, 3] SH coefficients of
        which the first ``(sh_degree + 1)^2`` are read.
    Returns:
        [N] bool (True: some parameter is not finite), or None.
    """
    if sh_degree is not None:
        colors = colors[:, : (sh_degree + 1) ** 2]
    params = (means, quats, scales, opacities, colors)
    with torch.no_grad():
        # a NaN or an infinity makes the total non-finite; finite values whose sum overflows only cost the
        # exact test below
        total = sum(t.sum() for t in params)
        if bool(torch.isfinite(total)):
            return None
        ok = torch.isfinite(opacities)
        for t in (means, quats, scales, colors):
            ok &= torch.isfinite(t).flatten(1).all(1)
    return ~ok


def _rasterize_torch(
    means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, bg, near, far, absgrad=False
) -> RenderOutput:
    dtype = means.dtype
    viewmat = viewmat.to(device=means.device, dtype=dtype)
    K = K.to(device=means.device, dtype=dtype)
    bad = non_finite_gaussians(means, quats, scales, opacities, colors, sh_degree)
    if bad is not None:  # culled like Gaussians outside the view, with zero gradients
        means, quats, scales, opacities, colors = (
            torch.where(bad.view((-1,) + (1,) * (t.dim() - 1)), torch.zeros((), dtype=t.dtype, device=t.device), t)
            for t in (means, quats, scales, opacities, colors)
        )
    proj = project_gaussians(means, quats, scales, viewmat, K, width, height, near, far, EPS2D, cull=bad)

    # The returned means2d is used downstream, so its .grad gets populated.
    means2d = proj.means2d.unsqueeze(0)  # [1, N, 2]

    with torch.no_grad():
        vis_idx = proj.visible.nonzero().squeeze(1)
        order = torch.argsort(proj.depths.detach().index_select(0, vis_idx), stable=True)
        idx = vis_idx.index_select(0, order)

    m2d = means2d[0].index_select(0, idx)
    conics = proj.conics.index_select(0, idx)
    cov2d = proj.cov2d.index_select(0, idx)
    det2d = proj.det2d.index_select(0, idx)
    opac = opacities.to(dtype).index_select(0, idx)
    z = proj.depths.index_select(0, idx)
    if sh_degree is None:
        cols = colors.to(dtype).index_select(0, idx)
    else:
        campos = _camera_center(viewmat)
        dirs = means.index_select(0, idx) - campos
        cols = sh_to_color(sh_degree, dirs, colors.to(dtype).index_select(0, idx))
    D = cols.shape[1]
    feats = torch.cat([cols, z.unsqueeze(1)], dim=1)

    stats = RasterStats()
    acc = rasterize_projected(
        m2d, conics, cov2d, opac, feats, width, height, det2d=det2d, stats=stats
    )
    image = acc[..., :D]
    depth_sum = acc[..., D : D + 1]
    alpha = acc[..., D + 1 : D + 2]
    if bg is not None:
        image = image + (1.0 - alpha) * bg
    depth = depth_sum / alpha.clamp_min(1e-10)

    return RenderOutput(
        image=image,
        depth=depth,
        alpha=alpha,
        means2d=means2d,
        radii=proj.radii.unsqueeze(0),
        depths=proj.depths.unsqueeze(0),
        conics=proj.conics.unsqueeze(0),
        width=width,
        height=height,
        backend="torch",
        n_pairs=stats.n_evaluated,
        extras={
            "n_entries": stats.n_entries,
            "n_pairs_backward": stats.n_backward,
            "n_slices": stats.n_slices,
        },
    )


def _rasterize_gsplat(
    means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, bg, near, far, absgrad=False
) -> RenderOutput:
    from gsplat import rasterization  # resolve_backend has checked that gsplat and its kernels load

    # gsplat normalises quaternions without an epsilon: replace (near-)zero
    # quaternions by the identity so they do not turn into NaNs.
    qn = quats.norm(dim=-1, keepdim=True)
    ident = torch.zeros_like(quats)
    ident[:, 0] = 1.0
    quats = torch.where(qn > 1e-12, quats, ident)

    D = 3 if sh_degree is not None else colors.shape[1]
    render, alpha, meta = rasterization(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmat[None].to(means),
        Ks=K[None].to(means),
        width=width,
        height=height,
        near_plane=near,
        far_plane=far,
        sh_degree=sh_degree,
        packed=False,
        backgrounds=None if bg is None else bg[None],
        render_mode="RGB+ED",
        rasterize_mode="classic",
        absgrad=absgrad,
    )
    extras = {
        k: meta[k]
        for k in ("tile_width", "tile_height", "tiles_per_gauss", "isect_ids", "flatten_ids",
                  "isect_offsets", "tile_size", "opacities")
        if k in meta
    }
    return RenderOutput(
        image=render[0, ..., :D],
        depth=render[0, ..., D:],
        alpha=alpha[0],
        means2d=meta["means2d"],
        radii=meta["radii"],
        depths=meta.get("depths"),
        conics=meta.get("conics"),
        width=width,
        height=height,
        backend="gsplat",
        n_pairs=None,
        extras=extras,
    )
