"""Pure-PyTorch, vectorised rasteriser for projected 2D Gaussians (CPU or GPU).

Semantics are gsplat's ("classic" mode): pixel centres at ``(x + 0.5,
y + 0.5)``; ``alpha = min(0.999, o * exp(-sigma))`` with
``sigma = 1/2 d^T conic d``; pairs with ``alpha < 1/255`` are skipped; front to
back, a pair contributes only if the transmittance after it stays above 1e-4
(the first pair that would bring it lower finishes the pixel);
``out = sum_i alpha_i T_i f_i``.

Layout
------
The image (padded on the right to a multiple of ``SEG``) is cut into
*segments* of ``SEG`` consecutive pixels of one row.  For every image row its
``alpha >= 1/255`` ellipse touches (computed analytically per Gaussian and
row), a Gaussian covers a run of segments; each (Gaussian, segment) pair is an
*entry*.  Entries are generated front to back (the visible Gaussians are
depth sorted first) and stably sorted by segment id, so the entries of a
segment are contiguous and depth ordered.  Per-pair quantities are dense
``[SEG, E]`` tensors (column major), in which the list of Gaussians of every
pixel is a contiguous, depth-ordered run:

* ``sigma`` is evaluated as a sum of squares,
  ``a/2 (dx - Sxy/Syy dy)^2 + dy^2 / (2 Syy)``, so it is never negative;
* the transmittance is a segmented cumulative sum of ``log(1 - alpha)`` in
  float64 (two global cumsums; the first one's offsets at the starts of the
  runs are cancelled before the second);
* the output ``sum_i w_i f_i`` is one CSR (pixels x Gaussians) x dense
  product.

Early termination also saves work: the depth-sorted Gaussians are processed
in *depth slices* front to back, carrying every pixel's log-transmittance
(``_DONE`` once finished) from slice to slice.  Entries on segments whose
pixels are all finished are dropped before any per-pixel work, and once all
pixels are finished the remaining Gaussians are never expanded.  Only entries
with a contributing pair are kept for the backward pass.

The backward pass is hand written (``torch.autograd.Function``) and mirrors
gsplat's: per-pixel suffix sums of ``w_j (f_j . dL/dC)`` (a segmented cumsum
plus a per-pixel tail carried from the slices behind) give ``dL/dalpha``; the
gradients w.r.t. the 2D means and conics are reduced to per-entry moments of
``dL/dsigma`` and scattered to the Gaussians.

On CPU, the large per-pair temporaries live in a reusable per-thread
workspace (page faults on freshly allocated memory otherwise cost about a
third of the run time; ``render.workspace``); :func:`~splatreplace_ns.render.workspace.release_workspace` frees it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import torch
from torch import Tensor

from splatreplace_ns.render.footprints import (
    Footprints,
    SEG,
    csr_matmul,
    entry_segments,
    footprint_rows,
    footprints,
    segmented_cumsum_,
)
from splatreplace_ns.render.workspace import workspace_for

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "T_MIN",
    "SEG",
    "RasterStats",
    "rasterize_projected",
]

# gsplat's constants (see its rasterize_to_pixels kernels)
ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
LOG_T_MIN = math.log(T_MIN)

# a depth slice aims at about this many entries per still-active segment
_SLICE_ENTRIES_PER_SEGMENT = 32
_MIN_SLICE_ENTRIES = 4096
# bytes of temporaries per slice (bounds peak memory of the forward pass)
_SLICE_BYTES = 256 * 1024 * 1024


@dataclass
class RasterStats:
    """Counters of one rasterisation (for benchmarks and diagnostics)."""

    n_entries: int = 0  # (Gaussian, segment) entries touched by an ellipse
    n_evaluated: int = 0  # (Gaussian, pixel) pairs evaluated in the forward pass
    n_backward: int = 0  # pairs kept for the backward pass
    n_slices: int = 0


# log-transmittance marker of a finished pixel (finite so that it can travel
# through cumulative sums; anything <= LOG_T_MIN works)
_DONE = -200.0
# exponents are clamped to this before exp(): exp(-80) ~ 1.8e-35 is still a
# normal float32 (denormals are extremely slow on CPUs) and far below any
# threshold used here
_LOG_FLOOR = -80.0


def _next_up(x: float, dtype: torch.dtype) -> float:
    return float(torch.nextafter(torch.tensor(x, dtype=dtype), torch.tensor(math.inf, dtype=dtype)))


def _next_down(x: float, dtype: torch.dtype) -> float:
    return float(torch.nextafter(torch.tensor(x, dtype=dtype), torch.tensor(-math.inf, dtype=dtype)))


@dataclass
class _Slice:
    ent_g: Tensor  # [E] int64
    ent_s: Tensor  # [E] int64
    a: Tensor  # [SEG, E] o exp(-sigma) where alpha >= 1/255, else 0 (unclamped)
    T: Tensor  # [SEG, E] transmittance before the pair; 0 where not contributing
    d0: Tensor  # [E] x offset of column 0's pixel centre from the mean
    dy: Tensor  # [E] y offset of the row's pixel centres from the mean


def _entry_geometry(ent_s: Tensor, n_seg_x: int, dtype: torch.dtype) -> Tuple[Tensor, Tensor]:
    """Pixel-centre coordinates (x of column 0, y) of every entry's segment."""
    ent_y = torch.div(ent_s, n_seg_x, rounding_mode="floor")
    x0 = (ent_s - ent_y * n_seg_x) * SEG
    return x0.to(dtype).add_(0.5), ent_y.to(dtype).add_(0.5)


def _composite_forward(
    fp: Footprints,
    gparams: Tensor,
    feats1: Tensor,
    n_seg_x: int,
    width: int,
    height: int,
    stats: RasterStats,
    save: bool = True,
) -> Tuple[Tensor, List["_Slice"]]:
    """Front-to-back compositing.  Returns the accumulated features
    [SEG * n_seg, C + 1] (pixel rows ordered (column, segment)) and, with
    ``save``, the per-slice state needed by the backward pass."""
    dtype = feats1.dtype
    dev = feats1.device
    Nv, C1 = feats1.shape
    n_seg = height * n_seg_x
    n_pix = SEG * n_seg
    a_min = _next_down(ALPHA_MIN, dtype)  # threshold keeps a > a_min, i.e. a >= 1/255
    col = torch.arange(SEG, device=dev, dtype=dtype).unsqueeze(1)  # [SEG, 1]
    seg_arange = torch.arange(SEG, device=dev, dtype=torch.int32).unsqueeze(1)

    acc = torch.zeros(n_pix, C1, dtype=dtype, device=dev)
    # log-transmittance of every pixel (_DONE once finished), [SEG, n_seg]:
    # pixel (column c of segment s) is at [c, s]
    carry = torch.zeros(SEG, n_seg, dtype=torch.float64, device=dev)
    pad = n_seg_x * SEG - width
    if pad:
        carry.view(SEG, height, n_seg_x)[SEG - pad :, :, -1] = _DONE
    any_done = pad > 0
    n_active = n_seg

    ws = workspace_for(dev)
    bytes_per_entry = SEG * (4 * C1 + 96)
    max_entries = max(_MIN_SLICE_ENTRIES, _SLICE_BYTES // bytes_per_entry)
    slices: List[_Slice] = []
    g0 = 0
    done_est = 0
    while g0 < Nv and n_active > 0:
        ws.reset()
        # ---- next depth slice: Gaussians [g0, g1) -> rows -> entries --------
        target = _SLICE_ENTRIES_PER_SEGMENT * n_seg * n_seg // max(n_active, 1)
        target = int(min(max(target, _MIN_SLICE_ENTRIES), max_entries))
        g1 = int(torch.searchsorted(fp.cum_est, done_est + target, right=False).item()) + 1
        g1 = min(max(g1, g0 + 1), Nv)
        done_est = int(fp.cum_est[g1 - 1].item())
        row_g, row_y, k0, nseg = footprint_rows(fp, g0, g1, width)
        g0 = g1
        if row_g.shape[0] == 0:
            continue
        cum = torch.cumsum(nseg, 0)
        E_nom = int(cum[-1].item())
        stats.n_entries += E_nom
        # (Gaussian, segment) entries: segment id = first segment of the row +
        # offset of the entry within the row
        ent_row = torch.repeat_interleave(
            torch.arange(row_g.shape[0], device=dev), nseg, output_size=E_nom
        )
        key = row_y * n_seg_x + k0 - (cum - nseg)
        ent_s = torch.arange(E_nom, device=dev) + key.index_select(0, ent_row)
        ent_g = row_g.index_select(0, ent_row)
        del ent_row, key, row_g, row_y, k0, nseg, cum
        if any_done:
            # drop entries on segments whose pixels are all finished
            seg_live = carry.amax(0) > _DONE
            keep = seg_live.index_select(0, ent_s).nonzero().squeeze(1)
            ent_s = ent_s.index_select(0, keep)
            ent_g = ent_g.index_select(0, keep)
        E = ent_s.shape[0]
        if E == 0:
            continue
        key, perm = torch.sort(ent_s.to(torch.int32), stable=True)
        ent_g = ent_g.index_select(0, perm)
        ent_s = key.long()
        del key, perm
        segs, firsts, lasts = entry_segments(ent_s)
        stats.n_evaluated += E * SEG
        stats.n_slices += 1

        # ---- per-pair alpha -------------------------------------------------
        mx, my, kb, na, nd, logo = gparams.index_select(1, ent_g).unbind(0)
        px0, py = _entry_geometry(ent_s, n_seg_x, dtype)
        dy = py.sub_(my)
        d0 = px0.sub_(mx)
        u0 = torch.addcmul(d0, kb, dy)  # dx - Sxy/Syy dy at column 0
        qb = torch.addcmul(logo, nd, dy * dy)  # log o - dy^2 / (2 Syy)
        # a = o exp(-sigma), zeroed where below 1/255 (the exponent is clamped:
        # denormal results are extremely slow on CPUs)
        a = torch.add(u0, col, out=ws.empty((SEG, E), dtype)).square_()
        torch.addcmul(qb, a, na, out=a).clamp_(min=_LOG_FLOOR).exp_()
        torch.nn.functional.threshold_(a, a_min, 0.0)
        alpha = torch.clamp(a, max=ALPHA_MAX, out=ws.empty((SEG, E), dtype))

        # ---- transmittance: segmented cumsum of log(1 - alpha) --------------
        one_m = torch.mul(alpha, -1.0, out=ws.empty((SEG, E), dtype)).add_(1.0)
        l64 = ws.empty((SEG, E), torch.float64)
        l64.copy_(torch.log(one_m, out=ws.empty((SEG, E), dtype)))
        incl, _ = segmented_cumsum_(l64, firsts, lasts, carry.index_select(1, segs), ws)
        # new carry: log T after this slice, _DONE for finished pixels
        new = incl.index_select(1, lasts)
        carry[:, segs] = torch.nn.functional.threshold(new, LOG_T_MIN, _DONE)
        if not any_done:
            any_done = bool((new <= LOG_T_MIN).any())
        if any_done:
            n_active = int((carry.amax(0) > _DONE).sum().item())
        # a pair contributes iff log T after it stays > log(1e-4);
        # T before it = exp(log T after) / (1 - alpha) >= 1e-4.  Others get
        # T = 0 (via a floor whose exp is tiny but not denormal).
        torch.nn.functional.threshold_(incl, LOG_T_MIN, _LOG_FLOOR)
        T = ws.empty((SEG, E), dtype)
        T.copy_(incl).exp_().div_(one_m)
        torch.nn.functional.threshold_(T, 1e-20, 0.0)
        del incl, l64, one_m
        w = alpha.mul_(T)

        # ---- accumulate sum_i w_i f_i with one CSR x dense product ----------
        counts = torch.zeros(n_seg, dtype=torch.int32, device=dev)
        counts[segs] = (lasts - firsts + 1).to(torch.int32)
        seg_start = torch.cumsum(counts, 0, dtype=torch.int32) - counts
        crow = torch.empty(n_pix + 1, dtype=torch.int32, device=dev)
        crow[:-1] = (seg_arange * E + seg_start).view(-1)
        crow[-1] = SEG * E
        cols = ws.empty((SEG, E), torch.int32)
        cols.copy_(ent_g.view(1, E))
        acc += csr_matmul(crow, cols.view(-1), w.view(-1), n_pix, Nv, feats1)
        del cols, crow

        # ---- keep the entries that contribute somewhere ---------------------
        if not save:
            continue
        keep = (w.sum(0) > 0).nonzero().squeeze(1)
        del w
        n_keep = keep.shape[0]
        stats.n_backward += n_keep * SEG
        if n_keep == 0:
            continue
        if n_keep < E:
            ent_g, ent_s, d0, dy = (t.index_select(0, keep) for t in (ent_g, ent_s, d0, dy))
            a, T = a.index_select(1, keep), T.index_select(1, keep)
        else:  # a and T live in the workspace: copy them out
            a, T = a.clone(), T.clone()
        slices.append(_Slice(ent_g=ent_g, ent_s=ent_s, a=a, T=T, d0=d0, dy=dy))
    return acc, slices


def _composite_backward(slices: List["_Slice"], G: Tensor, featsT: Tensor, n_seg: int) -> Tuple[Tensor, Tensor]:
    """Backward of :func:`_composite_forward`.

    G: dL/d(accumulated features), [(C + 1) * SEG, n_seg] (channel, column,
    segment).  Returns the per-Gaussian moments of dL/dsigma [6, Nv] and
    dL/dfeats^T [C, Nv].
    """
    dtype = featsT.dtype
    dev = featsT.device
    C, Nv = featsT.shape
    # gate of the clamp: gradient flows through alpha only if a <= 0.999
    a_max = -_next_up(ALPHA_MAX, dtype)
    col = torch.arange(SEG, device=dev, dtype=dtype).unsqueeze(1)
    mom = torch.zeros(6, Nv, dtype=dtype, device=dev)
    d_featsT = torch.zeros(C, Nv, dtype=dtype, device=dev)
    # per pixel: sum of w_j v_j over the slices behind
    tail = torch.zeros(SEG, n_seg, dtype=torch.float64, device=dev)
    ws = workspace_for(dev)

    for sl in reversed(slices):
        ws.reset()
        ent_g, ent_s, a, T = sl.ent_g, sl.ent_s, sl.a, sl.T
        E = ent_s.shape[0]
        shape = (SEG, E)
        segs, firsts, lasts = entry_segments(ent_s)
        alpha = torch.clamp(a, max=ALPHA_MAX, out=ws.empty(shape, dtype))
        w = torch.mul(alpha, T, out=ws.empty(shape, dtype))
        # dL/dC of every pair's pixel, channel-major [C + 1, SEG, E]
        Gg = torch.index_select(G, 1, ent_s, out=ws.empty(((C + 1) * SEG, E), dtype))
        Gg = Gg.view(C + 1, SEG, E)
        Fe = featsT.index_select(1, ent_g)  # [C, E]
        # v_i = f_i . dL/dC(pixel)  (alpha channel: feature 1);
        # dL/df_i = sum over its pixels of w_i dL/dC
        v = ws.empty(shape, dtype).copy_(Gg[C])
        for c in range(C):
            v.addcmul_(Gg[c], Fe[c])
        d_featsT.index_add_(1, ent_g, Gg[:C].mul_(w).sum(1))
        del Gg, Fe
        # -(sum_{j behind i} w_j v_j), behind = later in this slice or in the
        # slices behind it (tail)
        u = ws.empty(shape, torch.float64).copy_(w.mul_(v))
        neg_suffix, total = segmented_cumsum_(
            u, firsts, lasts, tail.index_select(1, segs).neg_(), ws, minus_total=True
        )
        tail[:, segs] += total
        # dL/dalpha = T v - suffix / (1 - alpha)
        d_alpha = ws.empty(shape, dtype).copy_(neg_suffix)
        d_alpha.div_(alpha.mul_(-1.0).add_(1.0)).addcmul_(T, v)
        del neg_suffix, u, v, w, alpha
        # dL/dsigma = -alpha dL/dalpha where alpha = o exp(-sigma) (unclamped)
        gate = torch.neg(a, out=ws.empty(shape, dtype))
        d_sigma = d_alpha.mul_(torch.nn.functional.threshold_(gate, a_max, 0.0))

        # moments of dL/dsigma over the pair offsets (dx, dy) per entry
        dy = sl.dy
        dx = torch.add(sl.d0, col, out=ws.empty(shape, dtype))
        t = torch.mul(d_sigma, dx, out=ws.empty(shape, dtype))
        e0 = d_sigma.sum(0)
        ex = t.sum(0)
        exx = t.mul_(dx).sum(0)
        mom.index_add_(1, ent_g, torch.stack([e0, ex, exx, dy * e0, dy * ex, dy * dy * e0]))
    return mom, d_featsT


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, cov2d, fp, width, height, stats, save):
        dtype = feats.dtype
        dev = feats.device
        Nv, C = feats.shape
        n_seg_x = (width + SEG - 1) // SEG

        # sigma = a/2 dx^2 + b dx dy + c/2 dy^2   (a, b, c: conic)
        #       = a/2 (dx - Sxy/Syy dy)^2 + dy^2 / (2 Syy)   (S: 2D covariance)
        # a sum of squares: never negative, no cancellation
        syy = cov2d[:, 2].to(dtype)
        gparams = torch.stack(
            [
                means2d[:, 0].to(dtype),
                means2d[:, 1].to(dtype),
                -cov2d[:, 1].to(dtype) / syy,
                -0.5 * conics[:, 0].to(dtype),
                -0.5 / syy,
                torch.log(opacities.to(dtype)),
            ]
        )  # [6, Nv]
        # accumulated alpha = sum_i w_i is one more channel with feature 1
        feats1 = torch.cat([feats, torch.ones(Nv, 1, dtype=dtype, device=dev)], 1).contiguous()

        acc, slices = _composite_forward(
            fp, gparams, feats1, n_seg_x, width, height, stats, save=save
        )
        ctx.slices = slices
        ctx.geom = (width, height, n_seg_x)
        ctx.save_for_backward(means2d, conics, opacities, feats)
        # pixel rows are ordered (column, segment) -> image [H, W, C + 1]
        img = acc.view(SEG, height, n_seg_x, C + 1).permute(1, 2, 0, 3)
        return img.reshape(height, n_seg_x * SEG, C + 1)[:, :width].contiguous()

    @staticmethod
    def backward(ctx, grad_img):
        means2d, conics, opacities, feats = ctx.saved_tensors
        width, height, n_seg_x = ctx.geom
        dtype = feats.dtype
        Nv, C = feats.shape
        pad = n_seg_x * SEG - width
        g = grad_img.to(dtype)
        if pad:
            g = torch.nn.functional.pad(g, (0, 0, 0, pad))
        featsT = feats.t().contiguous()  # [C, Nv]

        # [H, Wp, C + 1] -> [channel, column, segment]
        n_seg = height * n_seg_x
        G = g.reshape(n_seg, SEG, C + 1).permute(2, 1, 0).reshape((C + 1) * SEG, n_seg)
        mom, d_featsT = _composite_backward(ctx.slices, G, featsT, n_seg)
        ctx.slices = None

        S0, SX, SXX, SY, SXY, SYY = mom.unbind(0)
        ca, cb, cc = conics.to(dtype).unbind(1)
        op = opacities.to(dtype)
        # sigma = a/2 dx^2 + b dx dy + c/2 dy^2 with dx = px - mx, dy = py - my
        g_means2d = torch.stack([-(ca * SX + cb * SY), -(cb * SX + cc * SY)], dim=1)
        g_conics = torch.stack([0.5 * SXX, SXY, 0.5 * SYY], dim=1)
        # alpha = o exp(-sigma):  dL/do = sum dL/dalpha alpha / o = -S0 / o
        g_op = torch.where(op > 0, -S0 / op.clamp_min(1e-30), torch.zeros_like(S0))
        return g_means2d, g_conics, g_op, d_featsT.t(), None, None, None, None, None, None


def rasterize_projected(
    means2d: Tensor,
    conics: Tensor,
    cov2d: Tensor,
    opacities: Tensor,
    feats: Tensor,
    width: int,
    height: int,
    det2d: Optional[Tensor] = None,
    stats: Optional[RasterStats] = None,
) -> Tensor:
    """Composite visible 2D Gaussians front to back.

    Args:
        means2d [Nv, 2], conics [Nv, 3] (inverse 2D covariance xx, xy, yy),
        cov2d [Nv, 3] (2D covariance xx, xy, yy), opacities [Nv],
        feats [Nv, C]: the visible Gaussians in front-to-back order.
        det2d [Nv]: determinant of cov2d; pass an accurately computed one
            for very elongated Gaussians (default: from cov2d).
        cov2d and det2d only bound the footprints and evaluate the Gaussians
        stably; gradients flow through means2d, conics, opacities and feats.

    Returns:
        [height, width, C + 1]: ``sum_i w_i feat_i`` per pixel (no
        background), followed by the accumulated alpha ``sum_i w_i``.
    """
    dev = feats.device
    dtype = feats.dtype
    C = feats.shape[1]
    stats = stats if stats is not None else RasterStats()
    with torch.no_grad():
        cov2d = cov2d.detach()
        if det2d is None:
            det2d = cov2d[:, 0] * cov2d[:, 2] - cov2d[:, 1] * cov2d[:, 1]
        fp = footprints(means2d.detach(), cov2d, det2d.detach(), opacities.detach(), width, height)
    if means2d.shape[0] == 0 or int(fp.nrows.sum().item()) == 0:
        # nothing covers any pixel; an empty sum keeps the outputs attached to
        # the graph (exactly 0, zero gradients)
        zero = feats[:0].sum() + means2d[:0].sum() + conics[:0].sum() + opacities[:0].sum()
        return torch.zeros(height, width, C + 1, dtype=dtype, device=dev) + zero.to(dtype)
    # keep per-pair state for the backward pass only when there will be one
    save = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, opacities, feats)
    )
    return _Composite.apply(
        means2d, conics, opacities, feats, cov2d, fp, width, height, stats, save
    )
