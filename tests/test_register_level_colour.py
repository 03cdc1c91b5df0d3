"""Level-face colour agreement (splatreplace_ns.register.level_colour) and its part in registration.

Oracle: two copies of a box that is 2-fold symmetric in shape, with an asymmetric pattern on its top only,
lit by one directional light in the world. The source copy is turned by 180° against the template, so a pose
that keeps the copies world-aligned matches the lit side faces (and wins on overall colour) while only the
true pose matches the tops.
"""

from dataclasses import replace

import numpy as np
import pytest
import torch

from splatreplace_ns.register.level_colour import (
    gaussian_normals,
    level_colour_difference,
    prefer_level_colour,
)
from splatreplace_ns.register.errors import geodesic_deg
from splatreplace_ns.register.pipeline import InstanceGaussians, RegistrationConfig, register_instance

torch.set_num_threads(1)

LIGHT = np.array([0.0, -0.8, 0.6]) / np.linalg.norm([0.0, -0.8, 0.6])  # from the -y side, above


def turn_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def lit_box(pose: np.ndarray, n_per_m2: int = 2500, seed: int = 0) -> InstanceGaussians:
    """Flat Gaussians on a 1.0 × 0.6 × 0.5 box (bottom open), posed by ``pose`` (object → world).

    Albedo: grey sides; the top's x > 0 half light, x < 0 half dark (the only asymmetry). Colour = albedo ×
    (0.3 + 0.7 max(0, n_world · LIGHT)), so a side face's colour depends on where it points in the world.
    """
    rng = np.random.default_rng(seed)
    sx, sy, sz = 0.5, 0.3, 0.5
    faces = [  # (normal, centre, two in-plane half-extents along the axes u, v)
        (np.array([0, 0, 1.0]), np.array([0, 0, sz]), (np.array([1.0, 0, 0]), sx), (np.array([0, 1.0, 0]), sy)),
        (np.array([0, 1.0, 0]), np.array([0, sy, sz / 2]), (np.array([1.0, 0, 0]), sx), (np.array([0, 0, 1.0]), sz / 2)),
        (np.array([0, -1.0, 0]), np.array([0, -sy, sz / 2]), (np.array([1.0, 0, 0]), sx), (np.array([0, 0, 1.0]), sz / 2)),
        (np.array([1.0, 0, 0]), np.array([sx, 0, sz / 2]), (np.array([0, 1.0, 0]), sy), (np.array([0, 0, 1.0]), sz / 2)),
        (np.array([-1.0, 0, 0]), np.array([-sx, 0, sz / 2]), (np.array([0, 1.0, 0]), sy), (np.array([0, 0, 1.0]), sz / 2)),
    ]
    means, quats, colours = [], [], []
    for normal, centre, (u, hu), (v, hv) in faces:
        n = int(n_per_m2 * 4 * hu * hv)
        a, b = rng.uniform(-1, 1, (2, n))
        local = centre + a[:, None] * hu * u + b[:, None] * hv * v
        albedo = np.full((n, 3), 0.5)
        if normal[2] > 0.5:
            albedo[local[:, 0] < 0] = 0.15
            albedo[local[:, 0] >= 0] = 0.85
        n_world = pose[:3, :3] @ normal
        colours.append(albedo * (0.3 + 0.7 * max(0.0, float(n_world @ LIGHT))))
        means.append(local @ pose[:3, :3].T + pose[:3, 3])
        # the Gaussian's flat axis (its local z) along the face normal
        t = np.cross(normal, [0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        R_local = np.stack([t / np.linalg.norm(t), np.cross(normal, t / np.linalg.norm(t)), normal], axis=1)
        quats.append(np.repeat(matrix_to_quat(pose[:3, :3] @ R_local)[None], n, axis=0))
    means, quats, colours = (np.concatenate(x) for x in (means, quats, colours))
    spacing = 1.0 / np.sqrt(n_per_m2)
    scales = np.tile([0.6 * spacing, 0.6 * spacing, 0.05 * spacing], (len(means), 1))
    return InstanceGaussians(
        means=torch.tensor(means, dtype=torch.float32), quats=torch.tensor(quats, dtype=torch.float32),
        scales=torch.tensor(scales, dtype=torch.float32), opacities=torch.full((len(means),), 0.95),
        colors=torch.tensor(np.clip(colours, 0, 1), dtype=torch.float32),
    )


def test_gaussian_normals_follow_the_flat_axis_and_survive_zero_quaternions():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4))
    flat = rng.integers(0, 3, 50)
    scales = np.ones((50, 3))
    scales[np.arange(50), flat] = 1e-3
    normals = gaussian_normals(q, scales)
    for k in range(50):
        expected = quat_to_matrix(q[k])[:, flat[k]]
        assert abs(abs(float(normals[k] @ expected)) - 1.0) < 1e-9
    zero = gaussian_normals(np.zeros((2, 4)), np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 1.0]]))
    assert np.allclose(zero, [[0, 0, 1], [1, 0, 0]])


def test_level_faces_tell_a_turned_copy_from_its_lit_look_alike():
    """Overall colour prefers the world-aligned (wrong) pose; level faces prefer the true one."""
    P_tpl = turn_z(10.0)
    P_tpl[:3, 3] = [0.0, 0.0, 0.0]
    P_src = turn_z(190.0)
    P_src[:3, 3] = [3.0, 0.5, 0.0]
    tpl, src = lit_box(P_tpl, seed=1), lit_box(P_src, seed=2)
    true_T = P_tpl @ np.linalg.inv(P_src)
    flipped_T = P_tpl @ turn_z(180.0) @ np.linalg.inv(P_src)

    def parts(g):
        return g.centres(), g.colors.numpy().astype(np.float64), gaussian_normals(g.quats.numpy(), g.scales.numpy())

    (s, s_rgb, s_n), (t, t_rgb, t_n) = parts(src), parts(tpl)
    right, right_pairs = level_colour_difference(s, s_rgb, s_n, t, t_rgb, t_n, true_T, 0.05, (0, 0, 1))
    wrong, wrong_pairs = level_colour_difference(s, s_rgb, s_n, t, t_rgb, t_n, flipped_T, 0.05, (0, 0, 1))
    assert right_pairs > 500 and wrong_pairs > 500
    assert right < 0.01 and wrong > 0.2  # tops: same albedo and light under the true pose, halves swapped otherwise

    from scipy.spatial import cKDTree

    def overall(T):
        d, idx = cKDTree(t).query(s @ T[:3, :3].T + T[:3, 3], k=1, distance_upper_bound=0.05)
        hit = np.isfinite(d)
        return float(np.abs(s_rgb[hit] - t_rgb[idx[hit]]).mean())

    assert overall(flipped_T) < overall(true_T)  # what made the overall score pick the flip

    empty, pairs = level_colour_difference(s[:0], s_rgb[:0], s_n[:0], t, t_rgb, t_n, true_T, 0.05, (0, 0, 1))
    assert pairs == 0 and np.isnan(empty)


def test_prefer_level_colour_only_among_shape_peers_with_enough_pairs():
    poses = [turn_z(0.0), turn_z(180.0), turn_z(90.0), turn_z(3.0)]
    fitness = [0.95, 0.90, 0.50, 0.95]
    diffs = [(0.12, 300), (0.08, 300), (0.01, 300), (0.02, 300)]
    # the 180° peer wins; the 90° turn fits the shape too badly; the 3° one is the same pose
    assert prefer_level_colour(poses, fitness, diffs, 0, 0.85, 0.15, 50) == 1
    assert prefer_level_colour(poses, [0.95, 0.75, 0.5, 0.95], diffs, 0, 0.85, 0.15, 50) is None
    assert prefer_level_colour(poses, fitness, [(0.12, 300), (0.11, 300), (0.01, 300), (0.0, 300)], 0, 0.85, 0.15, 50) is None
    assert prefer_level_colour(poses, fitness, [(0.12, 30), (0.08, 300), (0.0, 300), (0.0, 300)], 0, 0.85, 0.15, 50) is None
    assert prefer_level_colour(poses, fitness, [(0.12, 300), (0.08, 30), (0.0, 300), (0.0, 300)], 0, 0.85, 0.15, 50) is None
    assert prefer_level_colour(poses, fitness, [(float("nan"), 0)] * 4, 0, 0.85, 0.15, 50) is None
    assert abs(geodesic_deg(poses[0][:3, :3], poses[1][:3, :3]) - 180.0) < 1e-6


def test_registration_picks_the_true_turn_of_a_lit_near_symmetric_copy():
    """End to end: with the level-face choice the copy turned by 180° registers; without it, it flips."""
    P_tpl = turn_z(10.0)
    P_src = turn_z(190.0)
    P_src[:3, 3] = [3.0, 0.5, 0.0]
    tpl = replace(lit_box(P_tpl, seed=1), id=2)
    src = replace(lit_box(P_src, seed=2), id=1)
    # only the multi-start turns pose it (no PnP), so the test isolates the choice between candidates
    cfg = RegistrationConfig(image_size=(64, 48), min_inliers=10**6, multistart_turns=12)
    truth = P_tpl @ np.linalg.inv(P_src)
    on = register_instance(src, tpl, cfg)
    off = register_instance(src, tpl, replace(cfg, level_colour=False))
    assert on.success and off.success, (on.message, off.message)
    assert geodesic_deg(on.transform[:3, :3], truth[:3, :3]) < 1.0, on.message
    assert "level faces chose a turn of 180°" in on.message
    assert geodesic_deg(off.transform[:3, :3], truth[:3, :3]) > 179.0, off.message
