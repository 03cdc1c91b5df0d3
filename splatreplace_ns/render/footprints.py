"""The CPU rasteriser's sparse bookkeeping: each projected Gaussian's ``alpha >= 1/255`` ellipse and the image rows
and segments it touches, segmented cumulative sums over (Gaussian, segment) entries, and a CSR product."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Tuple

import torch
from torch import Tensor


# width of a pixel segment
SEG = 8
# margin (pixels) added to the analytic ellipse extents; pixels inside the
# margin but outside the ellipse are rejected by the exact alpha test
EXTENT_MARGIN = 1e-2


@dataclass
class Footprints:
    """Per visible Gaussian (front to back): the ``alpha >= 1/255`` ellipse
    ``{d : d^T Sigma^-1 d <= 2 tau}``, ``tau = log(255 o)``, and the image rows
    it touches (float64, detached)."""

    params: Tensor  # [6, Nv]: mx, my, 2 tau (0: reaches no pixel), 1/Syy,
    #                 Sxy/Syy, det/Syy (variance of x given y)
    y_lo: Tensor  # [Nv] int64 first row
    nrows: Tensor  # [Nv] int64 number of rows (0: no pixel)
    cum_est: Tensor  # [Nv] int64 inclusive cumsum of an estimate of the entries


def footprints(
    means2d: Tensor, cov2d: Tensor, det2d: Tensor, opacities: Tensor, width: int, height: int
) -> Footprints:
    f64 = torch.float64
    mx = means2d[:, 0].to(f64)
    my = means2d[:, 1].to(f64)
    sxx = cov2d[:, 0].to(f64)
    sxy = cov2d[:, 1].to(f64)
    syy = cov2d[:, 2].to(f64)
    # o exp(-sigma) >= 1/255  <=>  sigma <= tau = log(255 o)
    tau = torch.log(opacities.to(f64).clamp_min(1e-30) * 255.0)
    has = (tau > 0) & torch.isfinite(mx) & torch.isfinite(my) & torch.isfinite(syy)
    tau2 = torch.where(has, 2.0 * tau, torch.zeros_like(tau))
    # the y extent of the ellipse is sqrt(2 tau Syy)
    ry = torch.sqrt(tau2 * syy)
    marg = EXTENT_MARGIN + 1e-6 * ry
    y_lo = torch.ceil((my - ry - 0.5 - marg).clamp(-1.0, height + 1.0)).clamp_min(0.0).long()
    y_hi = torch.floor((my + ry - 0.5 + marg).clamp(-2.0, float(height))).clamp_max(height - 1.0).long()
    nrows = torch.where(has, (y_hi - y_lo + 1).clamp_min(0), torch.zeros_like(y_lo))
    # segments per row: about (mean span / SEG + 1), the mean span of an
    # ellipse row being pi/4 of its x extent 2 rx
    rx = torch.sqrt(tau2 * sxx).clamp_max(float(width))
    per_row = (rx * (0.5 * math.pi / SEG) + 1.0).long()
    inv_syy = 1.0 / syy
    return Footprints(
        params=torch.stack(
            [mx, my, tau2, inv_syy, sxy * inv_syy, det2d.to(f64).clamp_min(0.0) * inv_syy]
        ),
        y_lo=y_lo,
        nrows=nrows,
        cum_est=torch.cumsum(nrows * per_row, 0),
    )


def footprint_rows(fp: Footprints, g0: int, g1: int, width: int) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """The (Gaussian, image row) spans of Gaussians [g0, g1), Gaussian-major.

    Returns (row_g, row_y, k0, nseg): Gaussian index, image row, first
    segment and number of segments of every row with at least one segment.
    """
    dev = fp.params.device
    nrows = fp.nrows[g0:g1]
    R = int(nrows.sum().item())
    if R == 0:
        z = torch.zeros(0, dtype=torch.long, device=dev)
        return z, z, z, z
    row_g = torch.repeat_interleave(torch.arange(g0, g1, device=dev), nrows, output_size=R)
    row_start = torch.cumsum(nrows, 0) - nrows
    row_y = torch.arange(R, device=dev) - (row_start - fp.y_lo[g0:g1]).index_select(0, row_g - g0)
    # x span of the ellipse in row y: x given dy is Gaussian with mean
    # mx + Sxy/Syy dy and variance det/Syy, so the half width is
    # sqrt((2 tau - dy^2/Syy) det/Syy)
    mx, my, tau2, inv_syy, slope, cond_var = fp.params.index_select(1, row_g).unbind(0)
    dy = (row_y.to(torch.float64) + 0.5) - my
    hx = torch.sqrt((tau2 - dy * dy * inv_syy).clamp_min_(0.0).mul_(cond_var))
    cx = mx.addcmul_(slope, dy).sub_(0.5)
    marg = hx * 1e-6 + EXTENT_MARGIN
    x_lo = torch.ceil((cx - hx - marg).clamp_(-1.0, width + 1.0)).clamp_min_(0.0).long()
    x_hi = torch.floor((cx + hx + marg).clamp_(-2.0, float(width))).clamp_max_(width - 1.0).long()
    k0 = torch.div(x_lo, SEG, rounding_mode="floor")
    nseg = (torch.div(x_hi, SEG, rounding_mode="floor") - k0 + 1).mul_(x_hi >= x_lo)
    keep = (nseg > 0).nonzero().squeeze(1)
    if keep.shape[0] < R:
        row_g, row_y, k0, nseg = (t.index_select(0, keep) for t in (row_g, row_y, k0, nseg))
    return row_g, row_y, k0, nseg


def entry_segments(ent_s: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Runs of equal segment ids in the sorted ``ent_s``.

    Returns (segs, firsts, lasts): segment id, index of its first and of its
    last entry, one element per run.
    """
    E = ent_s.shape[0]
    is_first = torch.ones(E, dtype=torch.bool, device=ent_s.device)
    if E > 1:
        torch.ne(ent_s[1:], ent_s[:-1], out=is_first[1:])
    firsts = is_first.nonzero().squeeze(1)
    lasts = torch.empty_like(firsts)
    lasts[:-1] = firsts[1:] - 1
    lasts[-1] = E - 1
    return ent_s.index_select(0, firsts), firsts, lasts


def segmented_cumsum_(
    x: Tensor, firsts: Tensor, lasts: Tensor, offset: Tensor, ws, minus_total: bool = False
) -> Tuple[Tensor, Tensor]:
    """In-place inclusive cumulative sum along dim 1, restarted at every run.

    ``x`` [S, E] (float64) is made of the runs ``firsts[r] .. lasts[r]``
    (contiguous, covering dim 1).  Element i of run r becomes
    ``offset[:, r] + sum_{firsts[r] <= j <= i} x_j``; with ``minus_total`` the
    run's own total is subtracted as well, i.e. the result is
    ``offset - sum_{j > i} x_j``.

    Two global cumsums: the first gives every run's starting offset, which is
    cancelled by correcting the first element of the run before the second.

    Returns (x, run totals [S, n_runs]).
    """
    c = torch.cumsum(x, 1, out=ws.empty(x.shape, x.dtype))
    before = c.index_select(1, firsts).sub_(x.index_select(1, firsts))
    total = c.index_select(1, lasts).sub_(before)
    del c
    target = offset - before
    if minus_total:
        target -= total
    corr = target.clone()
    corr[:, 1:] -= target[:, :-1]
    x.index_add_(1, firsts, corr)
    return x.cumsum_(1), total


def csr_matmul(crow: Tensor, cols: Tensor, values: Tensor, n_rows: int, n_cols: int, dense: Tensor) -> Tensor:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        A = torch.sparse_csr_tensor(
            crow, cols, values, size=(n_rows, n_cols), check_invariants=False
        )
        return A @ dense
