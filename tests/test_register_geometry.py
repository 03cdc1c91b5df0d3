"""Registration geometry (splatreplace_ns.poses) against ground truth."""

import math
import time

import numpy as np
import pytest
import torch

from splatreplace_ns.poses import (
    backproject,
    camera_pose_to_relative,
    fit_sphere,
    fpfh_ransac,
    framing_distance,
    make_matcher,
    project,
    rank_view_pairs,
    refine_icp,
    relative_transform_from_pnp,
    rotation_error_deg,
    solve_pnp,
    sphere_cameras,
    translation_error_rel,
)
from splatreplace_ns.render.cameras import look_at
from scenes import sample_mesh
from splatreplace_ns.tools.sim import CLASS_SYMMETRY, class_mesh

torch.set_num_threads(1)


def rot(axis, deg):
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    a = math.radians(deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def rigid(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def apply(T, p):
    return p @ T[:3, :3].T + T[:3, 3]


def inv(T):
    return rigid(T[:3, :3].T, -T[:3, :3].T @ T[:3, 3])


# ---------------------------------------------------------------- virtual cameras


def test_sphere_cameras_look_at_centre():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) * [0.3, 0.2, 0.5] + [1.0, -2.0, 0.5]
    pts[:5] += 100.0  # floaters must not blow up the sphere
    center, r_obj = fit_sphere(pts)
    assert np.linalg.norm(center - [1.0, -2.0, 0.5]) < 0.1 and r_obj < 2.0
    radius = framing_distance(r_obj, 60.0)
    W, H = 64, 48
    vms, K = sphere_cameras(center, radius, width=W, height=H, fov_deg=60.0)
    assert vms.shape == (25, 4, 4) and np.isfinite(vms).all()
    for vm in vms:
        R = vm[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-10) and np.linalg.det(R) > 0.999
        eye = -R.T @ vm[:3, 3]
        assert abs(np.linalg.norm(eye - center) - radius) < 1e-9
        uv, z = project(center[None], K, vm)
        assert z[0] > 0 and np.allclose(uv[0], [W / 2, H / 2], atol=1e-9)
        # world up maps to image up (negative v) except at the poles
        up_cam = R @ np.array([0, 0, 1.0])
        assert up_cam[1] < 0
    # poles: no NaN, still a proper look-at
    vms_pole, K = sphere_cameras(center, radius, W, H, 60.0, n_azimuth=3, n_elevation=3, elevation_range_deg=(-90, 90))
    assert np.isfinite(vms_pole).all()
    for vm in vms_pole:
        uv, z = project(center[None], K, vm)
        assert z[0] > 0 and np.allclose(uv[0], [W / 2, H / 2], atol=1e-9)
        assert abs(np.linalg.det(vm[:3, :3]) - 1) < 1e-9


# ---------------------------------------------------------------- lifting


def test_backproject_round_trip():
    rng = np.random.default_rng(1)
    W, H = 80, 60
    vm = look_at(np.array([2.0, -1.0, 1.5]), np.zeros(3))
    K = np.array([[70.0, 0, 41.3], [0, 72.0, 29.1], [0, 0, 1]])
    pts = rng.uniform(-0.5, 0.5, size=(200, 3))
    uv, z = project(pts, K, vm)
    col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    _, first = np.unique(row[ok] * W + col[ok], return_index=True)  # one point per pixel
    sel = np.flatnonzero(ok)[first]
    depth = np.zeros((H, W, 1))
    depth[row[sel], col[sel], 0] = z[sel]
    empty_r, empty_c = np.argwhere(depth[..., 0] == 0)[0]
    uv_q = np.concatenate([uv[sel], [[empty_c + 0.5, empty_r + 0.5], [-3.0, 2.0]]])  # + empty pixel, outside
    back, valid = backproject(uv_q, torch.from_numpy(depth), K, vm)
    assert valid[: len(sel)].all() and not valid[-2:].any()
    assert np.abs(back[: len(sel)] - pts[sel]).max() < 1e-5
    assert np.isnan(back[~valid]).all()


# ---------------------------------------------------------------- PnP


def _pnp_scene(n=200, seed=2):
    rng = np.random.default_rng(seed)
    W, H = 640, 480
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    pts = rng.uniform(-1, 1, size=(n, 3))
    vm = rigid(rot([0.3, -1, 0.2], 25), [0.1, -0.2, 5.0])
    uv, _ = project(pts, K, vm)
    return rng, W, H, K, pts, vm, uv


def test_pnp_with_outliers():
    rng, W, H, K, pts, vm, uv = _pnp_scene()
    out = rng.random(len(pts)) < 0.3
    uv = uv.copy()
    uv[out] = rng.uniform([0, 0], [W, H], size=(out.sum(), 2))
    res = solve_pnp(pts, uv, K, W, H)
    assert res.success, res.reason
    from splatreplace_ns.poses.errors import geodesic_deg

    assert geodesic_deg(res.world_to_camera[:3, :3], vm[:3, :3]) < 0.1
    assert np.abs(res.world_to_camera[:3, 3] - vm[:3, 3]).max() < 1e-3
    assert res.inlier_mask.shape == (len(pts),)
    assert res.num_inliers >= (~out).sum() - 2 and (res.inlier_mask & out).sum() <= 2


def test_pnp_degenerate_inputs():
    rng, W, H, K, pts, vm, uv = _pnp_scene()
    res = solve_pnp(pts[:3], uv[:3], K, W, H)
    assert not res.success and "4" in res.reason and np.isfinite(res.world_to_camera).all()
    line = np.linspace(0, 1, 20)[:, None] * np.array([[1.0, 0.5, 0.2]])
    uv_line, _ = project(line, K, vm)
    res = solve_pnp(line, uv_line, K, W, H)
    assert not res.success and "collinear" in res.reason
    # a plane seen edge-on (it holds the camera centre): every point projects onto one image line
    eye = -vm[:3, :3].T @ vm[:3, 3]
    in_plane = rng.uniform(-1, 1, (50, 2)) @ np.stack([vm[:3, :3].T @ [1.0, 0.0, 0.0], vm[:3, :3].T @ [0.0, 0.0, 1.0]])
    edge_on = eye + vm[:3, :3].T @ [0.0, 0.0, 4.0] + in_plane
    uv_edge, z_edge = project(edge_on, K, vm)
    assert (z_edge > 0).all() and np.ptp(uv_edge[:, 1]) < 1e-9
    res = solve_pnp(edge_on, uv_edge, K, W, H)
    assert not res.success and "2D points are collinear" in res.reason and np.isfinite(res.world_to_camera).all()
    bad = pts.copy()
    bad[:, :] = np.nan
    res = solve_pnp(bad, uv, K, W, H)
    assert not res.success and "finite correspondences, got 0" in res.reason


@pytest.mark.parametrize("tilt_deg", [0.0, 50.0])
def test_pnp_on_coplanar_points_gives_the_pose(tilt_deg):
    """Points on one plane, spread over it and seen obliquely by a general camera, fix the pose (P3P on planes,
    then refinement): exact without noise, within noise with noisy observations and 30 % outliers."""
    from splatreplace_ns.poses.errors import geodesic_deg

    rng, W, H, K, pts, vm, _ = _pnp_scene()
    plane = np.c_[pts[:, :2], np.zeros(len(pts))] @ rot([1.0, 0.4, 0.2], tilt_deg).T + [0.2, 0.1, 0.3]
    assert np.linalg.svd(plane - plane.mean(0), compute_uv=False)[2] < 1e-12  # truly coplanar
    uv, z = project(plane, K, vm)
    assert (z > 0).all() and (uv >= 0).all() and (uv <= [W, H]).all()
    res = solve_pnp(plane, uv, K, W, H)
    assert res.success, res.reason
    assert res.num_inliers == len(plane)
    assert geodesic_deg(res.world_to_camera[:3, :3], vm[:3, :3]) < 1e-6
    assert np.abs(res.world_to_camera[:3, 3] - vm[:3, 3]).max() < 1e-8
    noisy = uv + rng.normal(0.0, 0.5, uv.shape)
    outliers = rng.random(len(uv)) < 0.3
    noisy[outliers] = rng.uniform([0, 0], [W, H], size=(outliers.sum(), 2))
    res = solve_pnp(plane, noisy, K, W, H)
    assert res.success, res.reason
    assert geodesic_deg(res.world_to_camera[:3, :3], vm[:3, :3]) < 0.3
    assert np.abs(res.world_to_camera[:3, 3] - vm[:3, 3]).max() < 0.03  # the camera is 5 units away
    assert (res.inlier_mask & outliers).sum() <= 2 and res.num_inliers >= (~outliers).sum() - 5


def test_relative_transform_from_pnp():
    rng = np.random.default_rng(3)
    template = rng.normal(size=(150, 3)) * 0.3 + [2.0, 1.0, 0.4]
    T_true = rigid(rot([0.2, 0.1, 1.0], 130), [-3.0, 0.5, 0.1])  # template = T · source
    source = apply(inv(T_true), template)
    center, r = fit_sphere(template)
    vms, K = sphere_cameras(center, framing_distance(r, 50.0), 128, 96, 50.0)
    vm = vms[7]
    uv, z = project(template, K, vm)
    assert (z > 0).all()
    rel = relative_transform_from_pnp(source, uv, K, vm, 128, 96, max_error_px=1.0)
    assert rel.success and rel.num_inliers == len(source)
    assert np.abs(rel.transform - T_true).max() < 1e-4
    assert np.abs(apply(rel.transform, source) - template).max() < 1e-4
    assert np.allclose(camera_pose_to_relative(vm, vm), np.eye(4))


# ---------------------------------------------------------------- ICP / FPFH


def test_icp_chair_small_motion():
    mesh = class_mesh("chair")
    target = sample_mesh(mesh, 4000, seed=4)[0]
    source_obj = sample_mesh(mesh, 4000, seed=5)[0]
    T_src = rigid(rot([0.3, 0.5, 1.0], 5.0), [0.03, -0.02, 0.01])  # source = T_src · object
    source = apply(T_src, source_obj)
    T, fitness, rmse = refine_icp(source, target, np.eye(4), max_distance=0.1)
    # estimated object pose in the source frame: inv(T)
    assert rotation_error_deg(inv(T), T_src, "none") < 0.2
    diag = float(np.linalg.norm(target.max(0) - target.min(0)))
    assert translation_error_rel(inv(T), T_src, diag) < 0.01
    assert fitness > 0.9 and rmse < 0.02


def test_icp_symmetric_pawn():
    mesh = class_mesh("pawn")
    sym = CLASS_SYMMETRY["pawn"]
    assert sym == "rot_z:inf"
    target = sample_mesh(mesh, 3000, seed=6)[0]
    source_obj = sample_mesh(mesh, 3000, seed=7)[0]
    T_src = rigid(rot([0.1, 0.2, 1.0], 8.0), [0.004, -0.003, 0.002])
    source = apply(T_src, source_obj)
    diag = float(np.linalg.norm(target.max(0) - target.min(0)))
    T, fitness, _ = refine_icp(source, target, np.eye(4), max_distance=0.1 * diag)
    assert rotation_error_deg(inv(T), T_src, sym) < 1.0
    assert translation_error_rel(inv(T), T_src, diag) < 0.02
    assert fitness > 0.9


def test_fpfh_ransac_chair_large_rotation():
    mesh = class_mesh("chair")
    target = sample_mesh(mesh, 5000, seed=8)[0]
    source_obj = sample_mesh(mesh, 5000, seed=9)[0]
    T_src = rigid(rot([0.2, -0.3, 1.0], 60.0), [0.5, -0.3, 0.2])
    source = apply(T_src, source_obj)
    diag = float(np.linalg.norm(target.max(0) - target.min(0)))
    t0 = time.time()
    T, fitness = fpfh_ransac(source, target, voxel=diag / 40, seed=0, restarts=3)
    assert time.time() - t0 < 20
    assert rotation_error_deg(inv(T), T_src, CLASS_SYMMETRY["chair"]) < 5.0
    assert translation_error_rel(inv(T), T_src, diag) < 0.05
    assert fitness > 0.3


# ---------------------------------------------------------------- errors


def test_rotation_error_symmetry():
    R_gt = rot([0.4, -0.2, 0.9], 33.0)
    R_est = R_gt @ rot([0, 0, 1], 90.0)  # 90° about the object's z axis
    assert rotation_error_deg(R_est, R_gt, "rot_z:4") < 1e-6
    assert rotation_error_deg(R_est, R_gt, "rot_z:inf") < 1e-6
    assert abs(rotation_error_deg(R_est, R_gt, "none") - 90.0) < 1e-6
    assert abs(rotation_error_deg(R_est, R_gt, "rot_z:2") - 90.0) < 1e-6
    R_tilt = R_gt @ rot([1, 0, 0], 10.0) @ rot([0, 0, 1], 70.0)
    assert abs(rotation_error_deg(R_tilt, R_gt, "rot_z:inf") - 10.0) < 1e-6
    assert rotation_error_deg(R_tilt, R_gt, "rot_z:4") >= 10.0 - 1e-6
    with pytest.raises(ValueError):
        rotation_error_deg(R_gt, R_gt, "mirror")
    assert abs(translation_error_rel([1.0, 2.0, 2.0], [1.0, 0.0, 0.0], 4.0) - 0.5 * math.sqrt(2)) < 1e-12


# ---------------------------------------------------------------- matching


def _texture(h, w, seed):
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.float32)
    for sigma, weight in ((1.0, 0.3), (3.0, 0.5), (8.0, 1.0)):
        img += weight * cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), sigma)
    img -= img.min()
    return img / img.max()


def _warp_pair(seed=10):
    import cv2

    h, w = 200, 240
    img_a = _texture(h, w, seed)
    Hm = np.array([[0.95, 0.12, 8.0], [-0.08, 1.02, 5.0], [2e-4, -1e-4, 1.0]])
    img_b = cv2.warpPerspective(img_a, Hm, (w, h), flags=cv2.INTER_LINEAR)
    mask_b = cv2.warpPerspective(np.ones((h, w), np.float32), Hm, (w, h), flags=cv2.INTER_NEAREST) > 0.5
    return img_a, img_b, Hm, mask_b


def _inlier_rate(uv_a, uv_b, Hm):
    pa = np.concatenate([uv_a - 0.5, np.ones((len(uv_a), 1))], axis=1) @ Hm.T  # OpenCV: integer centres
    pred = pa[:, :2] / pa[:, 2:] + 0.5
    return float((np.linalg.norm(pred - uv_b, axis=1) < 3.0).mean())


@pytest.mark.parametrize("backend", ["sift", "orb", "xfeat", "xfeat-lighterglue"])
def test_matcher_consistent_with_homography(backend):
    img_a, img_b, Hm, mask_b = _warp_pair()
    matcher = make_matcher(backend)
    h, w = img_a.shape[:2]
    mask_a = np.zeros((h, w), bool)
    mask_a[20:-20, 20:-20] = True
    uv_a, uv_b, scores = matcher.match(img_a, torch.from_numpy(img_b), mask_a, mask_b)
    assert len(uv_a) >= 30 and uv_a.shape == uv_b.shape and scores.shape == (len(uv_a),)
    assert mask_a[np.floor(uv_a[:, 1]).astype(int), np.floor(uv_a[:, 0]).astype(int)].all()
    assert _inlier_rate(uv_a, uv_b, Hm) > 0.8


def test_rank_view_pairs():
    img_a, img_b, _, _ = _warp_pair()
    other = _texture(*img_a.shape[:2], seed=99)
    matcher = make_matcher("sift")
    shifted = np.roll(other, 9, axis=1)  # the same texture, translated
    top = rank_view_pairs(matcher, [other, img_a], [img_b, shifted], k=3)
    assert len(top) == 3
    assert {top[0][:2], top[1][:2]} == {(1, 0), (0, 1)}  # the two true pairs outrank the unrelated ones
    assert top[0][2] >= top[1][2] > 3 * max(top[2][2], 1)


def test_backproject_rendered_depth_lies_on_surface():
    """Convention check against the renderer: lifting the rendered depth of a splatted plane lands on it.

    Seen from straight above every Gaussian centre has the same depth, so the lift is exact; from an
    oblique view the expected depth is biased towards the camera (nearer Gaussians get more weight),
    which bounds the error by the Gaussians' overlap, not by the pixel/camera conventions.
    """
    from splatreplace_ns.render import rasterize

    g = torch.linspace(-0.6, 0.6, 41, dtype=torch.float32)
    xx, yy = torch.meshgrid(g, g, indexing="ij")
    means = torch.stack([xx.ravel(), yy.ravel(), torch.zeros(xx.numel())], dim=1)  # plane z = 0
    n = len(means)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    scales = torch.tensor([[0.03, 0.03, 1e-4]]).repeat(n, 1)
    W, H = 64, 48
    for elevation, tol in ((90.0, 1e-3), (50.0, 0.04)):
        vms, K = sphere_cameras(np.zeros(3), 1.5, W, H, 50.0, n_azimuth=1, n_elevation=1,
                                elevation_range_deg=(elevation, elevation))
        vm = vms[0]
        out = rasterize(
            means, quats, scales, torch.full((n,), 0.99), torch.rand(n, 3),
            torch.from_numpy(vm).float(), torch.from_numpy(K).float(), W, H,
        )
        alpha = out.alpha[..., 0].numpy()
        rows, cols = np.nonzero(alpha > 0.99)
        assert len(rows) > 0.5 * W * H
        uv = np.stack([cols + 0.5, rows + 0.5], axis=1)
        pts, valid = backproject(uv, out.depth, K, vm)
        assert valid.all()
        assert np.abs(pts[:, 2]).max() < tol, elevation
        assert np.abs(pts[:, :2]).max() < 0.6 + 3 * 0.03


# ---------------------------------------------------------------- upright ICP and the floor's up axis

TILTED_UP = np.array([0.02, -0.13, 0.99]) / np.linalg.norm([0.02, -0.13, 0.99])


def test_upright_icp_recovers_a_turn_about_a_tilted_up_axis():
    from splatreplace_ns.poses.icp import refine_icp_upright

    mesh = class_mesh("chair")
    target = sample_mesh(mesh, 4000, seed=4)[0]
    source_obj = sample_mesh(mesh, 4000, seed=5)[0]
    T_src = rigid(rot(TILTED_UP, 25.0), [0.04, -0.03, 0.01])  # a copy turned on the same (tilted) floor
    source = apply(T_src, source_obj)
    diag = float(np.linalg.norm(target.max(0) - target.min(0)))
    # start near the truth but with a 3° tilt and 4° of turn off, as a PnP pose would be
    init = rigid(rot([1.0, 0.3, 0.0], 3.0) @ rot(TILTED_UP, 4.0), [0.0, 0.0, 0.0]) @ inv(T_src)
    T, fitness = refine_icp_upright(source, target, init, TILTED_UP, max_distance=0.1 * diag)
    assert np.isfinite(T).all()
    assert np.allclose(T[:3, :3] @ TILTED_UP, TILTED_UP, atol=1e-9)  # a pure turn about up: no tilt left
    assert rotation_error_deg(inv(T), T_src, "none") < 0.2
    assert translation_error_rel(inv(T), T_src, diag) < 0.01
    assert fitness > 0.9


def test_upright_icp_hard_cases_stay_finite():
    from splatreplace_ns.poses.icp import nearest_upright, refine_icp_upright

    mesh = class_mesh("pawn")  # symmetric about up: the turn is free, the fit must still converge
    target = sample_mesh(mesh, 2000, seed=6)[0]
    source = apply(rigid(rot([0, 0, 1], 40.0), [0.01, 0.0, 0.0]), sample_mesh(mesh, 2000, seed=7)[0])
    T, fitness = refine_icp_upright(source, target, np.eye(4), [0, 0, 1], max_distance=0.05)
    assert np.isfinite(T).all() and fitness > 0.9
    assert rotation_error_deg(inv(T), rigid(rot([0, 0, 1], 40.0), [0.01, 0, 0]), "rot_z:inf") < 0.5
    # empty or tiny inputs: the (uprighted) start comes back with zero fitness, nothing raises
    for src, tgt in [(np.zeros((0, 3)), target), (source[:3], target), (source, target[:2])]:
        T, fitness = refine_icp_upright(src, tgt, np.eye(4), [0, 0, 1], max_distance=0.05)
        assert np.isfinite(T).all() and fitness == 0.0
    # far apart (no correspondence within the cut-off): no step, zero fitness
    T, fitness = refine_icp_upright(source + 10.0, target, np.eye(4), [0, 0, 1], max_distance=0.05)
    assert np.isfinite(T).all() and fitness == 0.0
    # nearest_upright keeps the heading and the centroid's image, drops the tilt
    pts = sample_mesh(class_mesh("chair"), 500, seed=1)[0]
    T = rigid(rot(TILTED_UP, 70.0) @ rot([0.0, 1.0, 0.0], 5.0), [0.3, 0.1, -0.2])
    U = nearest_upright(T, pts, TILTED_UP)
    assert np.allclose(U[:3, :3] @ TILTED_UP, TILTED_UP, atol=1e-9)
    assert rotation_error_deg(U, T, "none") < 5.5
    assert np.allclose(apply(U, pts.mean(0)[None]), apply(T, pts.mean(0)[None]), atol=1e-9)


def _plane_points(normal, n, extent, rng, offset=0.0):
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-extent, extent, (n, 2))
    return uv[:, :1] * a + uv[:, 1:] * b + (offset + rng.normal(0.0, 0.002, (n, 1))) * normal


def test_floor_up_axis_finds_the_floor_not_the_wall():
    from splatreplace_ns.poses.up_axis import floor_up_axis

    rng = np.random.default_rng(0)
    floor = _plane_points(TILTED_UP, 3000, 2.0, rng)
    wall = _plane_points(np.cross(TILTED_UP, [1.0, 0.0, 0.0]), 6000, 2.0, rng, offset=1.5)  # larger, vertical
    clutter = rng.uniform(-2.0, 2.0, (1500, 3))
    est = floor_up_axis(np.concatenate([wall, clutter, floor]))
    assert est.found and est.inliers >= 2500
    est.up[:] = 0.0  # the caller's copy: the same points give the same floor again
    again = floor_up_axis(np.concatenate([wall, clutter, floor]))
    assert np.array_equal(again.up, floor_up_axis(np.concatenate([wall, clutter, floor])).up)
    est = again
    assert np.degrees(np.arccos(min(1.0, est.up @ TILTED_UP))) < 0.5
    assert est.tilt_deg == pytest.approx(np.degrees(np.arccos(TILTED_UP[2])), abs=0.5)
    # the normal is turned to the prior's side even when the prior points down
    down = floor_up_axis(floor, prior=(0.0, 0.0, -1.0))
    assert down.found and down.up @ np.array([0.0, 0.0, -1.0]) > 0.9


def test_floor_up_axis_falls_back_to_the_prior():
    from splatreplace_ns.poses.config import RegistrationConfig
    from splatreplace_ns.poses.register import with_floor_up_axis
    from splatreplace_ns.poses.up_axis import floor_up_axis

    rng = np.random.default_rng(1)
    ball = rng.normal(0.0, 1.0, (3000, 3))  # no plane at all
    for pts in (ball, np.zeros((0, 3)), np.full((10, 3), np.nan)):
        est = floor_up_axis(pts, prior=(0.0, 0.0, 2.0))
        assert not est.found and np.allclose(est.up, [0.0, 0.0, 1.0]) and est.message
    wall_only = _plane_points([1.0, 0.0, 0.0], 3000, 2.0, rng)
    assert not floor_up_axis(wall_only).found
    # the registration settings take the floor's normal only when asked to (upright), and only the floor
    # near the instances counts
    floor = _plane_points(TILTED_UP, 3000, 2.0, rng)
    far_slope = _plane_points([0.3, 0.0, 1.0], 9000, 2.0, rng) + [20.0, 0.0, 0.0]  # bent far floor, bigger
    chairs = rng.uniform([-1.0, -1.0, 0.05], [1.0, 1.0, 1.0], (500, 3))
    cfg, message = with_floor_up_axis(RegistrationConfig(), torch.from_numpy(np.concatenate([floor, far_slope])),
                                      torch.from_numpy(chairs))
    assert np.allclose(cfg.up_axis, TILTED_UP, atol=0.01) and "floor normal" in message
    off = RegistrationConfig(upright=False)
    assert with_floor_up_axis(off, floor) == (off, "")
    # no floor near the instances (copies on a façade): full rigid ICP rather than turns about the cameras' up
    facade = _plane_points([0.0, 1.0, 0.0], 3000, 2.0, rng, offset=1.05)
    cfg, message = with_floor_up_axis(RegistrationConfig(), np.concatenate([facade, far_slope]), chairs)
    assert not cfg.upright and cfg.up_axis == RegistrationConfig().up_axis and "full rigid ICP" in message
