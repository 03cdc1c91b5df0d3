"""Tests of the Gaussian-splatting renderer (splatreplace_ns.render).

The pure-torch rasteriser is checked against

* gsplat's PyTorch reference implementations (projection, spherical harmonics),
  which run on CPU;
* a brute-force dense compositor written here: every Gaussian is evaluated at
  every pixel, Gaussians are sorted by depth and composited front to back in
  an explicit loop with gsplat's rules (alpha clamp 0.999, 1/255 skip,
  transmittance early termination at 1e-4).  Gradients of the oracle come from
  autograd through that loop.

Comparisons with the oracle run in float64 (the renderer is dtype generic), so
they can use rtol 1e-5.
"""

from __future__ import annotations

import importlib
import math
import sys
import types

import gsplat.cuda._torch_impl as gsplat_ref  # a pinned requirement: failing to import it must fail the tests
import pytest
import torch

import splatreplace_ns.render.raster_torch as raster_torch
from splatreplace_ns.render import (
    RenderOutput,
    project_gaussians,
    rasterize,
    spherical_harmonics,
)
from splatreplace_ns.render.rasterize import BACKEND_ENV_VAR, resolve_backend
from splatreplace_ns.render.workspace import release_workspace

F64 = torch.float64


# --------------------------------------------------------------------------- #
# scenes                                                                      #
# --------------------------------------------------------------------------- #


def intrinsics(width: int, height: int, fov_deg: float = 60.0, dtype=F64) -> torch.Tensor:
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)


def random_viewmat(seed: int, dtype=F64) -> torch.Tensor:
    """A world->camera transform with a random rotation and translation."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(4, generator=g, dtype=F64)
    q = q / q.norm()
    w, x, y, z = q
    R = torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=F64,
    )
    V = torch.eye(4, dtype=F64)
    V[:3, :3] = R
    V[:3, 3] = torch.randn(3, generator=g, dtype=F64)
    return V.to(dtype)


def make_scene(
    n: int,
    width: int,
    height: int,
    seed: int = 0,
    dtype=F64,
    scale_range=(0.02, 0.3),
    depth_range=(2.0, 6.0),
    opacity_range=(0.1, 0.9),
    feat_dim: int = 3,
    viewmat=None,
    margin: float = 1.2,
):
    """Gaussians spread over the view frustum of a camera (uniform depth, log-uniform
    scales, random rotations).  Means are generated in camera space and mapped to
    world space with the inverse of ``viewmat``."""
    g = torch.Generator().manual_seed(seed)
    K = intrinsics(width, height, dtype=dtype)
    fx = float(K[0, 0])
    V = torch.eye(4, dtype=F64) if viewmat is None else viewmat.to(F64)
    z = depth_range[0] + (depth_range[1] - depth_range[0]) * torch.rand(n, generator=g, dtype=F64)
    x = (torch.rand(n, generator=g, dtype=F64) * 2 - 1) * z * (width / 2) / fx * margin
    y = (torch.rand(n, generator=g, dtype=F64) * 2 - 1) * z * (height / 2) / fx * margin
    cam = torch.stack([x, y, z], 1)
    means = (cam - V[:3, 3]) @ V[:3, :3]  # R^T (p - t)
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=F64))
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    op = opacity_range[0] + (opacity_range[1] - opacity_range[0]) * torch.rand(n, generator=g, dtype=F64)
    colors = torch.rand(n, feat_dim, generator=g, dtype=F64)
    return dict(
        means=means.to(dtype),
        quats=quats.to(dtype),
        scales=scales.to(dtype),
        opacities=op.to(dtype),
        colors=colors.to(dtype),
        viewmat=V.to(dtype),
        K=K,
    )


# --------------------------------------------------------------------------- #
# brute-force oracle                                                          #
# --------------------------------------------------------------------------- #


def oracle_render(
    means, quats, scales, opacities, colors, viewmat, K, width, height,
    sh_degree=None, background=None, near=0.01, far=1e10,
):
    """Dense front-to-back compositing of every Gaussian at every pixel."""
    covars, _ = gsplat_ref._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = gsplat_ref._fully_fused_projection(
        means, covars, viewmat[None], K[None], width, height, near_plane=near, far_plane=far
    )
    means2d.retain_grad()
    radii, m2d, depths, conics = radii[0], means2d[0], depths[0], conics[0]
    if sh_degree is not None:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        cols = gsplat_ref._spherical_harmonics(sh_degree, means - campos, colors)
        cols = torch.clamp_min(cols + 0.5, 0.0)
    else:
        cols = colors
    D = cols.shape[1]
    feats = torch.cat([cols, depths[:, None]], 1)
    valid = (radii > 0).nonzero().squeeze(1)
    order = valid[torch.argsort(depths[valid].detach(), stable=True)]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means.dtype), torch.arange(width, dtype=means.dtype), indexing="ij"
    )
    px = xs.reshape(-1) + 0.5
    py = ys.reshape(-1) + 0.5
    T = torch.ones(height * width, dtype=means.dtype)
    done = torch.zeros(height * width, dtype=torch.bool)
    acc = torch.zeros(height * width, D + 1, dtype=means.dtype)
    zero = torch.zeros_like(T)
    for gi in order.tolist():
        dx = m2d[gi, 0] - px
        dy = m2d[gi, 1] - py
        a, b, c = conics[gi]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp_max(opacities[gi] * torch.exp(-sigma), 0.999)
        skip = (sigma < 0) | (alpha < 1.0 / 255.0) | done
        next_T = T * (1 - alpha)
        term = (~skip) & (next_T <= 1e-4)
        done = done | term
        use = (~skip) & (~term)
        acc = acc + torch.where(use, alpha * T, zero)[:, None] * feats[gi][None]
        T = torch.where(use, next_T, T)
    alpha_img = (1 - T).reshape(height, width, 1)
    image = acc[:, :D].reshape(height, width, D)
    if background is not None:
        image = image + T.reshape(height, width, 1) * background
    depth = acc[:, D:].reshape(height, width, 1) / alpha_img.clamp_min(1e-10)
    return dict(image=image, depth=depth, alpha=alpha_img, radii=radii, means2d=means2d)


PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _leaves(scene):
    return {k: scene[k].detach().clone().requires_grad_(True) for k in PARAMS}


def _loss_weights(height, width, D, seed=1, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(height, width, D + 2, generator=g, dtype=dtype)


def compare_with_oracle(scene, width, height, *, sh_degree=None, background=None, near=0.01,
                        rtol=1e-5, atol=1e-9, check_means2d_grad=True):
    """Render with the torch backend and the oracle; compare outputs and gradients."""
    ours = _leaves(scene)
    ref = _leaves(scene)
    out = rasterize(
        *(ours[k] for k in PARAMS), scene["viewmat"], scene["K"], width, height,
        sh_degree=sh_degree, background=background, near=near, backend="torch",
    )
    out.means2d.retain_grad()
    exp = oracle_render(
        *(ref[k] for k in PARAMS), scene["viewmat"], scene["K"], width, height,
        sh_degree=sh_degree, background=background, near=near,
    )
    D = out.image.shape[-1]
    assert out.image.shape == (height, width, D)
    assert out.depth.shape == (height, width, 1)
    assert out.alpha.shape == (height, width, 1)
    torch.testing.assert_close(out.radii[0], exp["radii"].to(torch.int32))
    for key in ("image", "depth", "alpha"):
        torch.testing.assert_close(getattr(out, key), exp[key], rtol=rtol, atol=atol, msg=key)

    w = _loss_weights(height, width, D)
    (torch.cat([out.image, out.depth, out.alpha], -1) * w).sum().backward()
    (torch.cat([exp["image"], exp["depth"], exp["alpha"]], -1) * w).sum().backward()
    for k in PARAMS:
        assert torch.isfinite(ours[k].grad).all(), k
        scale = ref[k].grad.abs().max().item() + 1e-12
        torch.testing.assert_close(ours[k].grad, ref[k].grad, rtol=rtol, atol=atol * scale + 1e-12, msg=k)
    if check_means2d_grad:
        vis = out.radii[0] > 0
        torch.testing.assert_close(
            out.means2d.grad[0][vis], exp["means2d"].grad[0][vis], rtol=rtol, atol=1e-9
        )
    return out


# --------------------------------------------------------------------------- #
# projection and SH against gsplat's reference implementation                 #
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("seed", [0, 1])
def test_projection_matches_gsplat_reference(seed):
    W, H = 64, 48
    s = make_scene(300, W, H, seed=seed, viewmat=random_viewmat(seed), margin=2.0, depth_range=(0.5, 8.0))
    # a few Gaussians behind the camera / beyond the far plane
    V = s["viewmat"]
    behind = (torch.tensor([[0.1, 0.2, -1.0], [0.0, 0.0, 1e-4], [0.3, -0.2, 50.0]], dtype=F64) - V[:3, 3]) @ V[:3, :3]
    means = torch.cat([s["means"], behind])
    quats = torch.cat([s["quats"], torch.randn(3, 4, dtype=F64)])
    scales = torch.cat([s["scales"], torch.full((3, 3), 0.1, dtype=F64)])
    proj = project_gaussians(means, quats, scales, V, s["K"], W, H, near=0.01, far=20.0)

    covars, _ = gsplat_ref._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, m2d, depths, conics, _ = gsplat_ref._fully_fused_projection(
        means, covars, V[None], s["K"][None], W, H, near_plane=0.01, far_plane=20.0
    )
    radii, m2d, depths, conics = radii[0], m2d[0], depths[0], conics[0]
    vis = radii > 0
    assert vis.sum() > 100 and (~vis).sum() > 3
    torch.testing.assert_close(proj.radii, radii.to(torch.int32))
    torch.testing.assert_close(proj.depths, depths, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(proj.means2d[vis], m2d[vis], rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(proj.conics[vis], conics[vis], rtol=1e-8, atol=1e-12)
    # culled Gaussians report zero pixel coordinates (like gsplat's CUDA kernel)
    assert (proj.means2d[~vis] == 0).all()
    # 2D covariance (blur included) is the inverse of the conic
    a, b, c = conics[vis].unbind(1)
    det = a * c - b * b
    cov_ref = torch.stack([c / det, -b / det, a / det], 1)
    torch.testing.assert_close(proj.cov2d[vis], cov_ref, rtol=1e-7, atol=1e-10)


def test_projection_zero_and_denormal_quaternions():
    W, H = 32, 24
    s = make_scene(4, W, H, seed=3)
    quats = torch.tensor([[0.0, 0, 0, 0], [1e-30, 0, 0, 0], [0, 0, 0, 1e-20], [1.0, 0, 0, 0]], dtype=F64)
    quats.requires_grad_(True)
    proj = project_gaussians(s["means"], quats, s["scales"], s["viewmat"], s["K"], W, H)
    # zero quaternion == identity rotation
    torch.testing.assert_close(proj.conics[0], project_gaussians(
        s["means"][:1], quats[3:].detach(), s["scales"][:1], s["viewmat"], s["K"], W, H).conics[0])
    (proj.conics.sum() + proj.means2d.sum()).backward()
    assert torch.isfinite(quats.grad).all()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics_match_gsplat_reference(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(200, 3, generator=g, dtype=F64)
    coeffs = torch.randn(200, 16, 3, generator=g, dtype=F64)
    ours = spherical_harmonics(degree, dirs, coeffs)
    ref = gsplat_ref._spherical_harmonics(degree, dirs, coeffs)
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------- #
# rasteriser against the dense oracle                                         #
# --------------------------------------------------------------------------- #


def test_render_matches_oracle_random_scene():
    # width not a multiple of the segment width, random camera pose, background
    W, H = 45, 31
    s = make_scene(150, W, H, seed=4, viewmat=random_viewmat(7))
    out = compare_with_oracle(s, W, H, background=torch.tensor([0.2, 0.5, 0.9], dtype=F64))
    assert out.alpha.max() > 0.9 and out.alpha.min() < 0.5  # both covered and empty pixels


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_render_sh_colors_match_oracle(degree):
    W, H = 32, 24
    s = make_scene(80, W, H, seed=5 + degree, viewmat=random_viewmat(degree))
    g = torch.Generator().manual_seed(degree)
    s["colors"] = 0.5 * torch.randn(80, 16, 3, generator=g, dtype=F64)  # K=16 >= (d+1)^2
    out = compare_with_oracle(s, W, H, sh_degree=degree)
    assert out.image.shape == (H, W, 3)


@pytest.mark.parametrize("D", [1, 32])
def test_render_feature_dims_match_oracle(D):
    W, H = 24, 16
    s = make_scene(60, W, H, seed=11 + D, feat_dim=D)
    out = compare_with_oracle(s, W, H, background=torch.linspace(0, 1, D, dtype=F64))
    assert out.image.shape == (H, W, D)


def test_dense_scene_with_early_termination_and_depth_slices(monkeypatch):
    """Many layers per pixel: most pixels terminate early.  Tiny depth slices
    force the carry of transmittance / finished pixels across slices and the
    tail of suffix sums in the backward pass."""
    W, H = 29, 21
    s = make_scene(600, W, H, seed=9, scale_range=(0.1, 0.5), opacity_range=(0.3, 1.0))
    monkeypatch.setattr(raster_torch, "_MIN_SLICE_ENTRIES", 32)
    monkeypatch.setattr(raster_torch, "_SLICE_ENTRIES_PER_SEGMENT", 2)
    out = compare_with_oracle(s, W, H)
    assert out.extras["n_slices"] > 5
    assert (out.alpha > 0.9998).float().mean() > 0.5  # terminated pixels (T <= ~1e-4)


def test_slicing_does_not_change_results(monkeypatch):
    W, H = 40, 30
    s = make_scene(500, W, H, seed=12, scale_range=(0.05, 0.3))
    args = [s[k] for k in PARAMS] + [s["viewmat"], s["K"], W, H]
    a = rasterize(*args, backend="torch")
    monkeypatch.setattr(raster_torch, "_MIN_SLICE_ENTRIES", 16)
    monkeypatch.setattr(raster_torch, "_SLICE_ENTRIES_PER_SEGMENT", 1)
    b = rasterize(*args, backend="torch")
    assert b.extras["n_slices"] > a.extras["n_slices"]
    for key in ("image", "depth", "alpha"):
        torch.testing.assert_close(getattr(a, key), getattr(b, key), rtol=1e-12, atol=1e-12)


def test_overlapping_layers_terminate_exactly():
    """150 nearly identical Gaussians stacked on the same pixels (distinct
    depths): the pixel stops exactly where gsplat's loop stops."""
    W, H = 16, 12
    n = 150
    K = intrinsics(W, H)
    z = torch.linspace(2.0, 5.0, n, dtype=F64)
    K_inv = torch.linalg.inv(K)
    pix = torch.tensor([7.3, 5.6, 1.0], dtype=F64)
    means = (K_inv @ pix)[None] * z[:, None]
    g = torch.Generator().manual_seed(0)
    s = dict(
        means=means,
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        scales=(0.03 * z[:, None]) * (1 + 0.5 * torch.rand(n, 3, generator=g, dtype=F64)),
        opacities=0.05 + 0.2 * torch.rand(n, generator=g, dtype=F64),
        colors=torch.rand(n, 3, generator=g, dtype=F64),
        viewmat=torch.eye(4, dtype=F64),
        K=K,
    )
    out = compare_with_oracle(s, W, H)
    a = out.alpha[5, 7, 0]
    assert a > 1 - 1e-4 * 1.5  # terminated: T ended just above 1e-4
    # the centre pixel does not use all layers: gradients of the back ones are 0
    ours = _leaves(s)
    o = rasterize(*(ours[k] for k in PARAMS), s["viewmat"], s["K"], W, H, backend="torch")
    o.image[5, 7].sum().backward()
    assert (ours["colors"].grad[-20:] == 0).all()
    assert (ours["colors"].grad[:20] != 0).all()


def test_saturated_opacity_matches_oracle():
    W, H = 24, 18
    s = make_scene(40, W, H, seed=21, opacity_range=(0.9, 1.0))
    s["opacities"][:20] = 1.0  # alpha clamps at 0.999 near the centres
    compare_with_oracle(s, W, H)


def test_near_plane_and_behind_camera_match_oracle():
    W, H = 32, 24
    s = make_scene(60, W, H, seed=31, depth_range=(0.3, 3.0))
    V = s["viewmat"]
    # camera-space depths around the near plane (strictly off the plane itself,
    # where gsplat's CUDA kernel and its PyTorch reference disagree) and behind
    extra_cam = torch.tensor(
        [[0.0, 0.0, 0.05 + 1e-9], [0.01, 0.0, 0.05 - 1e-9], [0.0, 0.01, -0.5], [0.0, 0.0, -1e-3]],
        dtype=F64,
    )
    s["means"] = torch.cat([s["means"], (extra_cam - V[:3, 3]) @ V[:3, :3]])
    s["quats"] = torch.cat([s["quats"], torch.randn(4, 4, dtype=F64)])
    s["scales"] = torch.cat([s["scales"], torch.full((4, 3), 0.01, dtype=F64)])
    s["opacities"] = torch.cat([s["opacities"], torch.full((4,), 0.5, dtype=F64)])
    s["colors"] = torch.cat([s["colors"], torch.rand(4, 3, dtype=F64)])
    out = compare_with_oracle(s, W, H, near=0.05)
    assert out.radii[0, -3:].eq(0).all() and out.radii[0, -4] > 0


def test_degenerate_and_huge_scales_match_oracle():
    W, H = 32, 24
    s = make_scene(50, W, H, seed=41)
    s["scales"][:5] = 1e-8  # points (only the 0.3 px blur remains)
    s["scales"][5:10, 0] = 1e-8  # flat discs
    s["scales"][10:12, 1:] = 1e-8  # needles
    s["scales"][12] = 1e3  # covers everything
    s["opacities"][12] = 0.05
    s["scales"][13] = torch.tensor([1e3, 1e-8, 1e-8], dtype=F64)  # endless oblique needle
    s["scales"][14] = torch.tensor([1e3, 1e3, 1e-8], dtype=F64)  # huge thin sheet
    s["opacities"][13:15] = 0.3
    out64 = compare_with_oracle(s, W, H)
    # float32 sees the same footprints (extents use the stably computed determinant)
    s32 = {k: (v.float() if torch.is_tensor(v) else v) for k, v in s.items()}
    out32 = rasterize(*(s32[k] for k in PARAMS), s32["viewmat"], s32["K"], W, H)
    torch.testing.assert_close(out32.alpha.double(), out64.alpha.detach(), rtol=0, atol=1e-4)
    torch.testing.assert_close(out32.image.double(), out64.image.detach(), rtol=0, atol=1e-4)


# --------------------------------------------------------------------------- #
# robustness: finite outputs and gradients                                    #
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_hard_cases_are_finite(dtype):
    W, H = 32, 24
    s = make_scene(40, W, H, seed=51, dtype=dtype)
    means, quats, scales, op = s["means"].clone(), s["quats"].clone(), s["scales"].clone(), s["opacities"].clone()
    means[0] = torch.tensor([0.0, 0.0, -1.0], dtype=dtype)  # behind
    means[1] = torch.tensor([0.0, 0.0, 0.0], dtype=dtype)  # at the camera centre
    means[2] = torch.tensor([0.0, 0.0, 0.01], dtype=dtype)  # exactly on the near plane
    means[3] = torch.tensor([0.1, 0.0, 0.0100001], dtype=dtype)  # just in front of it
    means[4] = torch.tensor([0.0, 0.05, 0.0099999], dtype=dtype)  # just behind it
    quats[5:8] = 0.0  # zero quaternions
    scales[8] = 1e-8
    scales[9, :2] = 1e-8
    scales[10] = 1e3
    scales[11, 0] = 1e3
    op[12:15] = 1.0
    op[15] = 0.0
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, op, s["colors"])]
    out = rasterize(*leaves, s["viewmat"], s["K"], W, H, background=torch.ones(3, dtype=dtype), backend="torch")
    out.means2d.retain_grad()
    for t in (out.image, out.depth, out.alpha, out.means2d):
        assert torch.isfinite(t).all()
    (out.image.sum() + out.depth.sum() + out.alpha.sum()).backward()
    for t in leaves:
        assert torch.isfinite(t.grad).all()
    assert torch.isfinite(out.means2d.grad).all()
    assert out.radii[0, 0] == 0 and out.radii[0, 1] == 0 and out.radii[0, 4] == 0
    assert out.radii[0, 2] > 0  # z == near is kept (gsplat's CUDA kernel culls z < near)


def test_empty_selection():
    W, H = 20, 10
    bg = torch.tensor([0.1, 0.2, 0.3])
    leaves = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    leaves = [t.requires_grad_(True) for t in leaves]
    out = rasterize(*leaves, torch.eye(4), intrinsics(W, H, dtype=torch.float32), W, H, background=bg)
    assert out.image.shape == (H, W, 3) and out.depth.shape == (H, W, 1) and out.alpha.shape == (H, W, 1)
    assert out.means2d.shape == (1, 0, 2) and out.radii.shape == (1, 0)
    torch.testing.assert_close(out.image, bg.expand(H, W, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    (out.image.sum() + out.alpha.sum() + out.depth.sum()).backward()
    # SH input and features of other widths
    sh = torch.zeros(0, 16, 3)
    out = rasterize(*leaves[:4], sh, torch.eye(4), intrinsics(W, H, dtype=torch.float32), W, H, sh_degree=3)
    assert out.image.shape == (H, W, 3)


def test_everything_culled_or_transparent():
    W, H = 16, 16
    s = make_scene(10, W, H, seed=61, dtype=torch.float32)
    leaves = [s[k].clone().requires_grad_(True) for k in PARAMS]
    with torch.no_grad():
        leaves[3].zero_()  # fully transparent: no pixel reaches alpha 1/255
    bg = torch.tensor([0.5, 0.5, 0.5])
    out = rasterize(*leaves, s["viewmat"], s["K"], W, H, background=bg)
    torch.testing.assert_close(out.image, bg.expand(H, W, 3))
    (out.image.sum() + out.depth.sum()).backward()
    assert all(torch.isfinite(t.grad).all() for t in leaves)


def test_inference_mode_and_workspace_release():
    W, H = 40, 30
    s = make_scene(200, W, H, seed=72, dtype=torch.float32)
    leaves = [s[k].clone().requires_grad_(True) for k in PARAMS]
    ref = rasterize(*leaves, s["viewmat"], s["K"], W, H)
    with torch.no_grad():
        out = rasterize(*leaves, s["viewmat"], s["K"], W, H)
    assert out.extras["n_pairs_backward"] == 0 and ref.extras["n_pairs_backward"] > 0
    torch.testing.assert_close(out.image, ref.image.detach())
    release_workspace()
    again = rasterize(*(s[k] for k in PARAMS), s["viewmat"], s["K"], W, H)
    torch.testing.assert_close(again.image, ref.image.detach())


def test_float32_close_to_float64():
    W, H = 48, 36
    s64 = make_scene(300, W, H, seed=71)
    s32 = {k: (v.float() if torch.is_tensor(v) else v) for k, v in s64.items()}
    a = rasterize(*(s64[k] for k in PARAMS), s64["viewmat"], s64["K"], W, H)
    b = rasterize(*(s32[k] for k in PARAMS), s32["viewmat"], s32["K"], W, H)
    assert b.image.dtype == torch.float32
    torch.testing.assert_close(b.image.double(), a.image, rtol=0, atol=2e-4)
    torch.testing.assert_close(b.alpha.double(), a.alpha, rtol=0, atol=2e-4)


# --------------------------------------------------------------------------- #
# interface                                                                   #
# --------------------------------------------------------------------------- #


def test_means2d_retain_grad_and_info_dict():
    W, H = 32, 24
    s = make_scene(30, W, H, seed=81, dtype=torch.float32)
    leaves = [s[k].clone().requires_grad_(True) for k in PARAMS]
    out = rasterize(*leaves, s["viewmat"], s["K"], W, H)
    assert isinstance(out, RenderOutput)
    assert out.means2d.shape == (1, 30, 2) and not out.means2d.is_leaf
    assert out.radii.shape == (1, 30) and out.radii.dtype == torch.int32
    info = out.info
    info["means2d"].retain_grad()  # what gsplat's DefaultStrategy does before backward
    out.image.sum().backward()
    grad = info["means2d"].grad
    assert grad is not None and grad.shape == (1, 30, 2)
    vis = out.radii[0] > 0
    assert grad[0][vis].abs().sum() > 0
    assert info["width"] == W and info["height"] == H and info["n_cameras"] == 1


def test_backend_selection(monkeypatch):
    cpu = torch.device("cpu")
    monkeypatch.delenv(BACKEND_ENV_VAR, raising=False)
    rasterize_module = importlib.import_module("splatreplace_ns.render.rasterize")
    monkeypatch.setattr(rasterize_module, "gsplat_unavailable_reason", lambda: None)  # as on a CUDA machine
    assert resolve_backend("auto", cpu) == "torch"
    assert resolve_backend("torch", cpu) == "torch"
    with pytest.raises(RuntimeError, match="CUDA"):
        resolve_backend("gsplat", cpu)
    with pytest.raises(ValueError):
        resolve_backend("opengl", cpu)
    monkeypatch.setenv(BACKEND_ENV_VAR, "torch")
    assert resolve_backend("auto", torch.device("cuda")) == "torch"
    assert resolve_backend("gsplat", torch.device("cuda")) == "torch"
    monkeypatch.setenv(BACKEND_ENV_VAR, "gsplat")
    assert resolve_backend("torch", torch.device("cuda")) == "torch"
    assert resolve_backend("auto", torch.device("cuda")) == "gsplat"
    W, H = 8, 8
    s = make_scene(3, W, H, dtype=torch.float32)
    args = [s[k] for k in PARAMS] + [s["viewmat"], s["K"], W, H]
    monkeypatch.setenv(BACKEND_ENV_VAR, "torch")  # forced: gsplat request renders with torch
    assert rasterize(*args, backend="gsplat").backend == "torch"
    monkeypatch.delenv(BACKEND_ENV_VAR)
    with pytest.raises(RuntimeError, match="CUDA"):
        rasterize(*args, backend="gsplat")


def test_gsplat_without_its_kernels_falls_back_to_torch_or_says_why(monkeypatch):
    """gsplat imports without a CUDA toolkit (its extension left unset) and failed only at the first render,
    mid-run. 'auto' must fall back to the torch path with a warning that says why, 'gsplat' must refuse."""
    rasterize_module = importlib.import_module("splatreplace_ns.render.rasterize")
    cuda = torch.device("cuda")
    monkeypatch.delenv(BACKEND_ENV_VAR, raising=False)
    for backend_module, expected in (
        (types.SimpleNamespace(_C=None), "no CUDA toolkit"),  # what gsplat 1.4 leaves without nvcc
        (None, "could not be built or loaded"),  # the import itself fails (a failed build, no gsplat)
    ):
        rasterize_module.gsplat_unavailable_reason.cache_clear()
        rasterize_module._warn_torch_fallback.cache_clear()
        monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", backend_module)
        assert expected in rasterize_module.gsplat_unavailable_reason()
        with pytest.warns(RuntimeWarning, match=expected):
            assert resolve_backend("auto", cuda) == "torch"
        with pytest.raises(RuntimeError, match=expected):
            resolve_backend("gsplat", cuda)
        assert resolve_backend("auto", torch.device("cpu")) == "torch"
    rasterize_module.gsplat_unavailable_reason.cache_clear()
    rasterize_module._warn_torch_fallback.cache_clear()
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", types.SimpleNamespace(_C=object()))
    assert rasterize_module.gsplat_unavailable_reason() is None
    assert resolve_backend("auto", cuda) == "gsplat"
    rasterize_module.gsplat_unavailable_reason.cache_clear()


def test_render_benchmark_leaves_out_gsplat_rows_without_its_kernels(monkeypatch, capsys):
    from splatreplace_ns.tools.bench.render import _backends

    rasterize_module = importlib.import_module("splatreplace_ns.render.rasterize")
    monkeypatch.setattr(rasterize_module, "gsplat_unavailable_reason", lambda: "no CUDA toolkit (nvcc)")
    assert _backends("cuda") == [("torch", "cuda")]
    assert "gsplat rows left out: no CUDA toolkit" in capsys.readouterr().out
    monkeypatch.setattr(rasterize_module, "gsplat_unavailable_reason", lambda: None)
    assert _backends("cuda") == [("torch", "cuda"), ("gsplat", "cuda")]
    assert _backends("cpu") == [("torch", "cpu")]


def test_gsplat_call_and_unpacking_on_cpu(monkeypatch):
    """The gsplat branch's contract with ``gsplat.rasterization`` (1.4): what it asks for (classic mode, RGB+ED,
    absgrad passed through, zero quaternions guarded, background per camera) and how it unpacks the result.
    A stand-in renders with the torch path in gsplat's output layout, so the unpacked image, depth and alpha
    must equal the torch backend's."""
    import gsplat

    # the package exports the function under the submodule's name, so import the module by path
    rasterize_module = importlib.import_module("splatreplace_ns.render.rasterize")

    calls = []

    def fake_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                           far_plane, sh_degree, packed, backgrounds, render_mode, rasterize_mode, absgrad):
        calls.append(dict(render_mode=render_mode, rasterize_mode=rasterize_mode, absgrad=absgrad, packed=packed,
                          backgrounds=backgrounds, quat_norms=quats.norm(dim=-1)))
        out = rasterize_module._rasterize_torch(means, quats, scales, opacities, colors, viewmats[0], Ks[0], width,
                                                height, sh_degree, None if backgrounds is None else backgrounds[0],
                                                near_plane, far_plane)
        render = torch.cat([out.image, out.depth], -1)[None]
        meta = {"means2d": out.means2d, "radii": out.radii, "depths": out.depths, "conics": out.conics}
        return render, out.alpha[None], meta

    monkeypatch.setattr(gsplat, "rasterization", fake_rasterization)
    W, H = 24, 16
    s = make_scene(50, W, H, seed=12, dtype=torch.float32, feat_dim=5)
    s["quats"][:3] = 0.0
    args = [s[k] for k in PARAMS] + [s["viewmat"], s["K"], W, H]
    bg = torch.linspace(0.1, 0.5, 5)
    out = rasterize_module._rasterize_gsplat(*args, None, bg, 0.01, 1e10, True)
    assert out.backend == "gsplat" and calls[-1]["absgrad"] is True
    assert calls[-1]["render_mode"] == "RGB+ED" and calls[-1]["rasterize_mode"] == "classic"
    assert calls[-1]["packed"] is False and calls[-1]["backgrounds"].shape == (1, 5)
    torch.testing.assert_close(calls[-1]["quat_norms"][:3], torch.ones(3))  # zero quaternions: the identity
    s["quats"][:3] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    ref = rasterize(*([s[k] for k in PARAMS] + [s["viewmat"], s["K"], W, H]), background=bg, backend="torch")
    assert out.image.shape == (H, W, 5) and out.depth.shape == (H, W, 1) and out.alpha.shape == (H, W, 1)
    for key in ("image", "depth", "alpha", "means2d"):
        torch.testing.assert_close(getattr(out, key), getattr(ref, key))
    assert out.info["radii"].shape == (1, 50)


def test_input_validation():
    W, H = 8, 8
    s = make_scene(3, W, H, dtype=torch.float32)
    args = [s[k] for k in PARAMS]
    with pytest.raises(ValueError, match="SH"):
        rasterize(*args, s["viewmat"], s["K"], W, H, sh_degree=1)  # colours are [N, 3], not SH
    with pytest.raises(ValueError, match="needs K"):
        rasterize(*args[:4], torch.zeros(3, 4, 3), s["viewmat"], s["K"], W, H, sh_degree=3)
    with pytest.raises(ValueError, match="background"):
        rasterize(*args, s["viewmat"], s["K"], W, H, background=torch.zeros(4))


# --------------------------------------------------------------------------- #
# CUDA: torch path vs gsplat                                                  #
# --------------------------------------------------------------------------- #


CUDA_CASES = {  # name: (make_scene arguments, edit of the scene); all at 96×64
    "random": (dict(n=2000, seed=91, viewmat="random"), None),
    "16 channels": (dict(n=2000, seed=5, feat_dim=16), None),
    "near plane": (dict(n=300, seed=3, depth_range=(0.005, 0.05)), None),
    "behind the camera": (dict(n=300, seed=10, depth_range=(-2.0, 2.0)), None),
    "degenerate scales": (dict(n=300, seed=4, scale_range=(1e-6, 1e-4)), None),
    "huge scales": (dict(n=300, seed=4, scale_range=(5.0, 50.0)), None),
    "zero quaternions": (dict(n=300, seed=6), "zero_quats"),
    "saturated opacity": (dict(n=300, seed=8, opacity_range=(0.999, 1.0)), None),
    "150 overlapping layers": (dict(n=150, seed=9, scale_range=(2.0, 3.0), margin=0.1), None),
}


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("sh_degree", [None, 3])
@pytest.mark.parametrize("case", sorted(CUDA_CASES))
def test_torch_path_matches_gsplat_on_cuda(case, sh_degree):
    W, H = 96, 64
    kwargs, edit = CUDA_CASES[case]
    kwargs = dict(kwargs)
    if kwargs.pop("viewmat", None) == "random":
        kwargs["viewmat"] = random_viewmat(3, torch.float32)
    n = kwargs.pop("n")
    s = make_scene(n, W, H, dtype=torch.float32, **kwargs)
    if edit == "zero_quats":
        s["quats"][:50] = 0.0
    if sh_degree is not None:
        g = torch.Generator().manual_seed(0)
        s["colors"] = 0.3 * torch.randn(n, 16, 3, generator=g)
    dev = torch.device("cuda")
    bg = torch.tensor([0.1, 0.2, 0.3], device=dev) if s["colors"].shape[-1] == 3 else None
    outs, grads = {}, {}
    for backend in ("torch", "gsplat"):
        leaves = [s[k].to(dev).clone().requires_grad_(True) for k in PARAMS]
        out = rasterize(*leaves, s["viewmat"].to(dev), s["K"].float().to(dev), W, H,
                        sh_degree=sh_degree, background=bg, backend=backend)
        assert out.backend == backend
        (out.image.sum() + 0.1 * out.depth.sum() + out.alpha.sum()).backward()
        outs[backend] = out
        grads[backend] = [t.grad for t in leaves]
    a, b = outs["torch"], outs["gsplat"]
    assert (a.radii != b.radii).sum() <= 2  # float32 rounding at ceil() boundaries
    # gsplat leaves the projection of a culled Gaussian at 0; the torch path computes it anyway
    visible = (a.radii > 0) & (b.radii > 0)
    torch.testing.assert_close(a.means2d[visible], b.means2d[visible], rtol=1e-4, atol=1e-3)
    # gsplat only evaluates pixels inside the tiles its 3-sigma radius touches,
    # while the torch path evaluates the exact alpha >= 1/255 footprint: the
    # images agree to about one 8-bit level.
    for key in ("image", "alpha"):
        diff = (getattr(a, key) - getattr(b, key)).abs()
        assert diff.mean() < 2e-3 and diff.max() < 5e-2, key
    mask = (a.alpha > 0.5) & (b.alpha > 0.5)
    assert ((a.depth - b.depth).abs()[mask]).mean() < 1e-2
    for key in ("image", "depth", "alpha"):
        assert torch.isfinite(getattr(a, key)).all() and torch.isfinite(getattr(b, key)).all(), key
    for ga, gb, name in zip(grads["torch"], grads["gsplat"], PARAMS):
        assert torch.isfinite(ga).all() and torch.isfinite(gb).all(), name
        cos = torch.nn.functional.cosine_similarity(ga.flatten().double(), gb.flatten().double(), dim=0)
        assert cos > 0.99, (name, cos)


# --------------------------------------------------------------------------- #
# cameras                                                                     #
# --------------------------------------------------------------------------- #


def test_world_to_camera_inverts_a_nerfstudio_pose():
    """A point at OpenCV camera coordinates p sits at c2w · (p_x, −p_y, −p_z, 1) in the world (nerfstudio's poses
    are OpenGL-style); the world→camera matrix must bring it back to p, for any rigid pose."""
    from splatreplace_ns.render import world_to_camera

    g = torch.Generator().manual_seed(4)
    c2w = torch.zeros(5, 3, 4, dtype=F64)
    for b in range(5):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))
        c2w[b, :, :3] = q * torch.sign(torch.det(q))
        c2w[b, :, 3] = 3 * torch.randn(3, generator=g, dtype=F64)
    p_cv = torch.randn(5, 7, 3, generator=g, dtype=F64)
    p_gl = p_cv * torch.tensor([1.0, -1.0, -1.0], dtype=F64)
    world = p_gl @ c2w[:, :, :3].transpose(1, 2) + c2w[:, None, :, 3]
    viewmats = world_to_camera(c2w)
    assert viewmats.shape == (5, 4, 4) and viewmats.dtype == F64
    back = world @ viewmats[:, :3, :3].transpose(1, 2) + viewmats[:, None, :3, 3]
    torch.testing.assert_close(back, p_cv, rtol=0, atol=1e-12)
    torch.testing.assert_close(viewmats[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=F64).expand(5, 4))
    square = torch.cat([c2w, torch.tensor([0.0, 0, 0, 1], dtype=F64).expand(5, 1, 4)], 1)
    torch.testing.assert_close(world_to_camera(square), viewmats)  # [B, 4, 4] poses too
    with pytest.raises(ValueError, match="camera_to_worlds"):
        world_to_camera(c2w[0])
