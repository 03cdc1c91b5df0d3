"""Free-space check of registration (register.free_space): a placed template must not fill space the cameras
saw through. Oracle: analytic depth maps of one camera (a wall at a known depth)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from scenes import look_at_cv
from test_register_pipeline import tiny  # noqa: F401  (the fixture: ideal Gaussians of the tiny scene's crates)
from splatreplace_ns.register.free_space import (
    ObservedDepth,
    free_space_violation,
    pooled_depth,
    scaled_intrinsics,
)

W, H = 64, 48
K = np.array([[50.0, 0.0, W / 2], [0.0, 50.0, H / 2], [0.0, 0.0, 1.0]])


def wall_view(depth: float, eye=(0.0, -5.0, 0.0), target=(0.0, 0.0, 0.0)) -> ObservedDepth:
    """One camera whose every pixel sees a surface at camera depth ``depth``."""
    viewmat = np.linalg.inv(look_at_cv(np.array(eye), np.array(target)))
    return ObservedDepth(viewmat[None], K[None], np.full((1, H, W), depth))


def cloud(centre, n=200, spread=0.2, seed=0):
    return np.asarray(centre) + np.random.default_rng(seed).uniform(-spread, spread, (n, 3))


def test_points_in_front_of_the_seen_surface_violate_and_points_behind_do_not():
    observed = wall_view(5.0)  # the camera sits 5 in front of the origin and sees a wall through it
    assert free_space_violation(cloud((0, 0, 0)), observed, margin=0.5) == pytest.approx(0.0)  # on the wall
    assert free_space_violation(cloud((0, -2, 0)), observed, margin=0.5) == pytest.approx(1.0)  # in front
    assert free_space_violation(cloud((0, 3, 0)), observed, margin=0.5) == pytest.approx(0.0)  # hidden behind
    # nothing opaque seen there (inf): everything in view is in free space
    empty = ObservedDepth(observed.viewmats, observed.Ks, np.full((1, H, W), np.inf))
    assert free_space_violation(cloud((0, 0, 0)), empty, margin=0.5) == pytest.approx(1.0)
    # two views, one sees through, one sees the surface: half
    both = ObservedDepth(np.concatenate([observed.viewmats] * 2), np.concatenate([observed.Ks] * 2),
                         np.concatenate([observed.depths, empty.depths]))
    assert free_space_violation(cloud((0, 0, 0)), both, margin=0.5) == pytest.approx(0.5)


def test_points_no_view_sees_and_degenerate_inputs_cost_nothing():
    observed = wall_view(5.0)
    assert free_space_violation(cloud((0, -8, 0)), observed, 0.5) == 0.0  # behind the camera
    assert free_space_violation(cloud((40, 0, 0)), observed, 0.5) == 0.0  # outside the image
    assert free_space_violation(np.zeros((0, 3)), observed, 0.5) == 0.0
    assert free_space_violation(np.full((5, 3), np.nan), observed, 0.5) == 0.0
    no_views = ObservedDepth(np.zeros((0, 4, 4)), np.zeros((0, 3, 3)), np.zeros((0, H, W)))
    assert free_space_violation(cloud((0, 0, 0)), no_views, 0.5) == 0.0


def test_pooled_depth_keeps_the_nearest_surface_and_projects_consistently():
    depth = torch.full((H, W), float("inf"))
    depth[10:14, 20:24] = 3.0
    depth[11, 21] = 2.0
    pooled, factor = pooled_depth(depth, max_width=16)
    assert factor == 4.0 and pooled.shape == (12, 16)
    assert float(pooled[2, 5]) == 2.0 and float(pooled[3, 5]) == 3.0  # blocks (8..11, 20..23), (12..15, ...)
    assert torch.isinf(pooled[0, 0])
    same, one = pooled_depth(depth, max_width=W)
    assert one == 1.0 and torch.equal(same, depth)
    # a point that falls in pixel (u, v) at full size falls in pixel (u // s, v // s) of the pooled map
    Kp = scaled_intrinsics(K, factor)
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (100, 2)), rng.uniform(2, 6, 100)]
    full = np.floor(pts[:, :2] / pts[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]).astype(int)
    small = np.floor(pts[:, :2] / pts[:, 2:] * [Kp[0, 0], Kp[1, 1]] + Kp[:2, 2]).astype(int)
    np.testing.assert_array_equal(small, full // 4)


def test_registration_rejects_a_placement_in_seen_free_space(tiny):
    """The same registration is accepted when the cameras saw nothing in front of the source, and rejected,
    with the reason named, when they saw straight through where it would stand."""
    from splatreplace_ns.register.pipeline import RegistrationConfig, register_instance

    torch.set_num_threads(1)
    g, poses = tiny["gaussians"], tiny["poses"]
    source, template = replace(g[1], id=1), replace(g[2], id=2)  # 2 has the most Gaussians: the template
    centre = poses[1][:3, 3]
    eye = centre + np.array([0.0, -6.0, 2.0])
    cfg = RegistrationConfig(image_size=(128, 96))
    distance = float(np.linalg.norm(eye - centre))
    hidden = register_instance(source, template, cfg, observed=wall_view(distance - 3.0, eye, centre))
    assert hidden.success, hidden.message
    assert "free-space violation 0.000" in hidden.message
    seen_through = register_instance(source, template, cfg, observed=wall_view(distance + 5.0, eye, centre))
    assert not seen_through.success
    assert "instance 1" in seen_through.message and "free-space violation" in seen_through.message
    np.testing.assert_allclose(hidden.transform[:3, 3], (poses[2] @ np.linalg.inv(poses[1]))[:3, 3], atol=0.05)
    # off: no check, no violation in the message
    off = register_instance(source, template, replace(cfg, max_free_space_violation=0.0),
                            observed=wall_view(distance + 5.0, eye, centre))
    assert off.success and "free-space" not in off.message


def test_views_of_different_sizes():
    """A capture's views may differ in size: each depth map is read with its own shape."""
    big = wall_view(5.0)
    small_K = scaled_intrinsics(K, 2.0)
    mixed = ObservedDepth(np.concatenate([big.viewmats] * 2), np.stack([K, small_K]),
                          [big.depths[0], np.full((H // 2, W // 2), np.inf)])
    # seen on the wall in the full-size view, seen through in the half-size one
    assert free_space_violation(cloud((0, 0, 0)), mixed, margin=0.5) == pytest.approx(0.5)
