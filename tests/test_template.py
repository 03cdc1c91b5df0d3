"""Shared templates (paper §4.3): pose parametrisation, SH rotation, building and composing the replaced scene.

Oracles: SH evaluated at rotated view directions; ground-truth object poses of the ``tiny`` preset; the
identity (a class with one instance must render exactly as before).
"""

from __future__ import annotations


import numpy as np
import pytest
import torch

from splatreplace_ns.render import rasterize
from splatreplace_ns.render.projection import quat_to_rotmat
from splatreplace_ns.render.sh import spherical_harmonics
from splatreplace_ns.render.transform import transform_gaussians
from splatreplace_ns.template.build import build_templates
from splatreplace_ns.render.transform import axis_angle_to_quat, quat_multiply, rotmat_to_quat, sh_rotation
from splatreplace_ns.template.compose import compose_scene, instance_poses, offsets_l1

torch.set_num_threads(1)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_rotation_equals_rotated_view_directions(degree):
    gen = torch.Generator().manual_seed(degree)
    R = quat_to_rotmat(axis_angle_to_quat(torch.randn(4, 3, generator=gen)))
    K = (degree + 1) ** 2
    local = torch.randn(4, K, 3, generator=gen)
    world = torch.einsum("ikl,ilc->ikc", sh_rotation(R, degree), local)
    dirs = torch.randn(4, 200, 3, generator=gen)
    seen_world = spherical_harmonics(degree, dirs, world[:, None].expand(4, 200, K, 3))
    local_dirs = torch.einsum("ijk,inj->ink", R, dirs)  # Rᵀ d
    seen_local = spherical_harmonics(degree, local_dirs, local[:, None].expand(4, 200, K, 3))
    assert torch.allclose(seen_world, seen_local, atol=1e-4)


def test_axis_angle_quaternion_at_zero_and_large_angles():
    omega = torch.zeros(3, 3, requires_grad=True)
    big = torch.tensor([[0.0, 0.0, 3.1], [1e-9, 0.0, 0.0], [10.0, -4.0, 2.0]])
    q = axis_angle_to_quat(torch.cat([omega, big]))
    assert torch.allclose(q[:3], torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(3, 4))
    assert torch.allclose(q.norm(dim=-1), torch.ones(6), atol=1e-6)
    q.sum().backward()
    assert torch.isfinite(omega.grad).all()
    # a rotation by 3.1 rad about z
    R = quat_to_rotmat(q[3:4])[0]
    assert torch.allclose(R[:2, :2], torch.tensor([[np.cos(3.1), -np.sin(3.1)], [np.sin(3.1), np.cos(3.1)]]).float(), atol=1e-5)


def test_rotmat_quat_round_trip_and_product():
    gen = torch.Generator().manual_seed(1)
    qa = axis_angle_to_quat(torch.randn(8, 3, generator=gen))
    qb = axis_angle_to_quat(torch.randn(8, 3, generator=gen))
    Ra, Rb = quat_to_rotmat(qa), quat_to_rotmat(qb)
    assert torch.allclose(quat_to_rotmat(quat_multiply(qa, qb)), Ra @ Rb, atol=1e-5)
    back = rotmat_to_quat(Ra)
    assert torch.allclose(quat_to_rotmat(back), Ra, atol=1e-5)


def _random_scene(n_bg=50, n_inst=(40, 30, 35), K=16, seed=0):
    gen = torch.Generator().manual_seed(seed)
    n = n_bg + sum(n_inst)
    params = {
        "means": torch.randn(n, 3, generator=gen),
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
        "scales": torch.randn(n, 3, generator=gen) * 0.1 - 3.0,
        "opacities": torch.randn(n, 1, generator=gen),
        "features_dc": torch.randn(n, 3, generator=gen),
        "features_rest": torch.randn(n, K - 1, 3, generator=gen) * 0.1,
        "features_contrastive": torch.randn(n, 4, generator=gen),
    }
    labels = torch.zeros(n, dtype=torch.long)
    start = n_bg
    for k, m in enumerate(n_inst, start=1):
        labels[start : start + m] = k
        start += m
    return params, labels


def _pose(omega, t):
    T = torch.eye(4)
    T[:3, :3] = quat_to_rotmat(axis_angle_to_quat(torch.tensor(omega)[None]))[0]
    T[:3, 3] = torch.tensor(t)
    return T


def _compose(out, table, lam=0.8):
    q, R, t = instance_poses(table.q0, table.t0, torch.zeros(len(table.ids), 6))
    sh = torch.cat((out["features_dc"][:, None], out["features_rest"]), dim=1)
    return compose_scene(out["means"], out["quats"], out["scales"], out["opacities"], sh, out["sh_offsets"],
                         out["template_class"][:, 0].long(), table.class_index, table.slot, table.ids, q, R, t, lam=lam)


def test_every_instance_keeps_its_own_gaussians_and_gets_the_others():
    params, labels = _random_scene()
    classes = {1: "chair", 2: "chair", 3: "table"}
    # registration: template ≈ T · instance. Instance 2 is instance 1 moved, so T_2 maps it back exactly.
    T2 = _pose([0.3, -1.0, 0.5], [1.0, 2.0, -0.5])
    transforms = {1: torch.eye(4), 2: T2, 3: torch.eye(4)}
    out, table = build_templates(params, labels, classes, transforms, {"chair": 1, "table": 3})
    assert table.classes == ["chair", "table"] and table.kept_in_background == []
    assert out["sh_offsets"].shape == (len(out["means"]), 2, 16, 3)
    scene = _compose(out, table)
    # count: background + chair template (40 + 30) twice + table template once
    assert len(scene.means) == 50 + 2 * 70 + 35
    sh_before = torch.cat((params["features_dc"][:, None], params["features_rest"]), dim=1)
    for iid, n in ((1, 40), (2, 30), (3, 35)):
        own = labels == iid
        mine = scene.instance_id == iid
        # the instance's own Gaussians come back where they were, with their own colours
        src = torch.nonzero(own).squeeze(-1)
        got_means = scene.means[mine]
        dist = torch.cdist(params["means"][src], got_means, compute_mode="donot_use_mm_for_euclid_dist")
        assert dist.min(dim=1).values.max() < 1e-4, iid
        nearest = dist.argmin(dim=1)
        assert torch.allclose(scene.sh[mine][nearest], sh_before[src], atol=1e-4)
        rot_before = quat_to_rotmat(params["quats"][src])
        rot_after = quat_to_rotmat(scene.quats[mine][nearest])
        assert torch.allclose(rot_before, rot_after, atol=1e-4)
    # background untouched
    bg = scene.instance_id == 0
    assert torch.equal(scene.means[bg], params["means"][:50])


def test_single_instance_class_renders_exactly_as_before():
    params, labels = _random_scene(n_inst=(60,))
    params["means"] = params["means"] * 0.3 + torch.tensor([0.0, 0.0, 4.0])
    out, table = build_templates(params, labels, {1: "vase"}, {1: torch.eye(4)}, {"vase": 1})
    scene = _compose(out, table)
    K = torch.tensor([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
    view = torch.eye(4)

    def render(means, quats, scales, opac, sh):
        return rasterize(means, quats, torch.exp(scales), torch.sigmoid(opac).reshape(-1), sh, view, K, 64, 48,
                         sh_degree=3, backend="torch").image

    sh = torch.cat((params["features_dc"][:, None], params["features_rest"]), dim=1)
    before = render(params["means"], params["quats"], params["scales"], params["opacities"], sh)
    after = render(scene.means, scene.quats, scene.log_scales, scene.logit_opacities, scene.sh)
    assert torch.allclose(before, after, atol=1e-4)


def test_failed_registration_stays_background():
    params, labels = _random_scene()
    out, table = build_templates(params, labels, {1: "chair", 2: "chair", 3: "table"},
                                 {1: torch.eye(4), 3: torch.eye(4)}, {"chair": 1, "table": 3})
    assert table.kept_in_background == [2]
    assert int((out["template_class"][:, 0] == 0).sum()) == 50 + 30


def test_gradients_from_one_instance_reach_the_shared_template_and_its_pose():
    params, labels = _random_scene(n_bg=0, n_inst=(30, 30))
    params["means"] = params["means"] * 0.2
    params["means"][30:] += torch.tensor([0.8, 0.0, 0.0])
    out, table = build_templates(params, labels, {1: "a", 2: "a"}, {1: torch.eye(4), 2: _pose([0, 0, 0], [-0.8, 0, 0])},
                                 {"a": 1})
    out = {k: v.clone().requires_grad_(True) for k, v in out.items()}
    delta = torch.zeros(2, 6, requires_grad=True)
    q, R, t = instance_poses(table.q0, table.t0, delta)
    sh = torch.cat((out["features_dc"][:, None], out["features_rest"]), dim=1)
    scene = compose_scene(out["means"], out["quats"], out["scales"], out["opacities"], sh, out["sh_offsets"],
                          out["template_class"][:, 0].detach().long(), table.class_index, table.slot, table.ids, q, R, t)
    # a loss on instance 2's copy only
    loss = (scene.means[scene.instance_id == 2] ** 2).sum() + scene.sh[scene.instance_id == 2].sum()
    loss.backward()
    # every template Gaussian (contributed by instance 1 or 2) gets a gradient through instance 2's copy
    assert (out["means"].grad.norm(dim=1) > 0).all()
    assert (out["features_dc"].grad.abs().sum(dim=1) > 0).all()
    assert out["sh_offsets"].grad[:, 1].abs().sum() > 0 and out["sh_offsets"].grad[:, 0].abs().sum() == 0
    assert torch.isfinite(delta.grad).all() and delta.grad[1].abs().sum() > 0 and delta.grad[0].abs().sum() == 0


def test_offsets_l1_counts_only_used_slots():
    offsets = torch.zeros(5, 3, 4, 3)
    offsets[:2, 2] = 7.0  # slot 2 unused by class 1 (two instances)
    offsets[0, 0] = 1.0
    cls = torch.tensor([1, 1, 2, 0, 0])
    value = offsets_l1(offsets, cls, {1: 2, 2: 1})
    assert value.item() == pytest.approx(12.0 / (2 * 2 * 12 + 1 * 12))
    assert offsets_l1(offsets, cls, {}).item() == 0.0


def test_composed_offsets_are_the_used_slots_so_their_mean_is_the_l1():
    params, labels = _random_scene()
    out, table = build_templates(params, labels, {1: "chair", 2: "chair", 3: "table"},
                                 {1: torch.eye(4), 2: _pose([0.3, -1.0, 0.5], [1.0, 2.0, -0.5]), 3: torch.eye(4)},
                                 {"chair": 1, "table": 3})
    out["sh_offsets"] = torch.randn_like(out["sh_offsets"])
    scene = _compose(out, table)
    assert scene.offsets.shape == (int((scene.instance_id > 0).sum()), 16, 3)
    classes = out["template_class"][:, 0].long()
    expected = offsets_l1(out["sh_offsets"], classes, table.slots_per_class)
    assert scene.offsets.abs().mean().item() == pytest.approx(expected.item(), rel=1e-6)


def test_transform_gaussians_moves_covariances_with_the_object():
    params, _ = _random_scene(n_bg=20, n_inst=())
    T = _pose([0.4, 0.2, -1.2], [0.1, 0.2, 0.3])
    sh = torch.cat((params["features_dc"][:, None], params["features_rest"]), dim=1)
    means, quats, _ = transform_gaussians(T, params["means"], params["quats"], sh)
    R = T[:3, :3]
    assert torch.allclose(means, params["means"] @ R.T + T[:3, 3], atol=1e-5)
    assert torch.allclose(quat_to_rotmat(quats), R @ quat_to_rotmat(params["quats"]), atol=1e-5)


def test_merge_keeps_one_gaussian_per_cell_and_the_most_opaque():
    params, labels = _random_scene(n_bg=0, n_inst=(200, 200))
    params["means"][200:] = params["means"][:200] + 1e-4  # instance 2 = instance 1 (already registered)
    params["opacities"][200:] = params["opacities"][:200] + 1.0  # ... but more opaque
    merged, table = build_templates(params, labels, {1: "a", 2: "a"}, {1: torch.eye(4), 2: torch.eye(4)}, {"a": 1},
                                    merge=True)
    plain, _ = build_templates(params, labels, {1: "a", 2: "a"}, {1: torch.eye(4), 2: torch.eye(4)}, {"a": 1})
    assert len(plain["means"]) == 400
    assert 150 <= len(merged["means"]) <= 260  # about one copy; random points share some cells
    # every kept Gaussian is the more opaque twin wherever both fell into one cell
    assert (merged["opacities"] >= params["opacities"][:200].min()).all()
    assert int((merged["opacities"][:, 0] > params["opacities"][:200, 0].max()).sum()) > 0
    d = torch.cdist(params["means"][:200], merged["means"]).min(dim=1).values
    spacing = torch.cdist(params["means"][:200], params["means"][:200]).topk(2, largest=False).values[:, 1].median()
    assert (d < 2 * spacing).float().mean() > 0.95  # the merged template still covers the instance


def test_merge_cell_ignores_clumps_of_near_duplicates():
    """Densification leaves clumps of near-identical Gaussians; they must not shrink the merge grid to nothing.
    Two copies that differ by a 0.5 % registration error merge to about one copy."""
    gen = torch.Generator().manual_seed(1)
    distinct = torch.nn.functional.normalize(torch.randn(300, 3, generator=gen), dim=-1)  # a unit sphere shell
    clumped = distinct.repeat_interleave(3, dim=0) + 1e-6 * torch.randn(900, 3, generator=gen)
    params, labels = _random_scene(n_bg=0, n_inst=(900, 900))
    params["means"][:900] = clumped
    params["means"][900:] = clumped + torch.tensor([0.005, 0.0, 0.0])  # the second copy, registered 0.5 % off
    merged, _ = build_templates(params, labels, {1: "a", 2: "a"}, {1: torch.eye(4), 2: torch.eye(4)}, {"a": 1},
                                merge=True)
    assert len(merged["means"]) <= 1.3 * 300, len(merged["means"])
    d = torch.cdist(distinct, merged["means"]).min(dim=1).values
    assert (d < 0.1).all()  # the merged template still covers the shell (cell = radius / 30 ≈ 0.033)


def test_merge_leaves_a_class_of_one_copy_whole():
    """A class with one registered copy overlaps nothing; the merge grid would only drop its Gaussians that share
    a cell (the clumps densification leaves), so it keeps them all while a two-copy class is merged."""
    params, labels = _random_scene(n_bg=0, n_inst=(300, 300, 300))
    params["means"][:300] = params["means"][:300][torch.arange(300) // 3]  # clumps of 3
    params["means"][600:] = params["means"][300:600] + 1e-4  # instance 3 = instance 2 (already registered)
    merged, table = build_templates(params, labels, {1: "a", 2: "b", 3: "b"},
                                    {1: torch.eye(4), 2: torch.eye(4), 3: torch.eye(4)}, {"a": 1, "b": 2}, merge=True)
    per_class = merged["template_class"][:, 0].round().long()
    assert int((per_class == 1).sum()) == 300  # class a: all of its one copy
    assert int((per_class == 2).sum()) < 400  # class b: two copies merged to about one


def test_zero_mix_puts_the_colour_in_the_offsets():
    params, labels = _random_scene(n_bg=5, n_inst=(10, 10))
    out, table = build_templates(params, labels, {1: "a", 2: "a"}, {1: torch.eye(4), 2: torch.eye(4)}, {"a": 1}, lam=0.0)
    scene = _compose(out, table, lam=0.0)
    sh_before = torch.cat((params["features_dc"][:, None], params["features_rest"]), dim=1)
    own = scene.instance_id == 1
    assert torch.allclose(scene.sh[own][:10], sh_before[5:15], atol=1e-5)


def test_colour_gain_multiplies_the_colour_in_every_direction():
    from splatreplace_ns.render.sh import sh_to_color
    from splatreplace_ns.template.compose import apply_colour_gain

    g = torch.Generator().manual_seed(3)
    coeffs = torch.randn(50, 16, 3, generator=g) * 0.2
    coeffs[:, 0] += 1.0  # colours well above the clamp at 0, where the gain is exact
    log_gain = torch.randn(50, 3, generator=g) * 0.3
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    before = sh_to_color(3, dirs, coeffs)
    after = sh_to_color(3, dirs, apply_colour_gain(coeffs, log_gain))
    assert (before > 0).all()
    assert torch.allclose(after, before * torch.exp(log_gain), atol=1e-5)
    assert torch.allclose(apply_colour_gain(coeffs, torch.zeros(50, 3)), coeffs)


def test_colour_gain_is_per_instance_and_survives_the_rotation():
    params, labels = _random_scene(n_bg=5, n_inst=(20, 20))
    T2 = _pose([0.0, 0.0, 1.2], [0.5, 0.0, 0.0])
    out, table = build_templates(params, labels, {1: "a", 2: "a"}, {1: torch.eye(4), 2: T2}, {"a": 1})
    q, R, t = instance_poses(table.q0, table.t0, torch.zeros(2, 6))
    sh = torch.cat((out["features_dc"][:, None], out["features_rest"]), dim=1)
    args = (out["means"], out["quats"], out["scales"], out["opacities"], sh, out["sh_offsets"],
            out["template_class"][:, 0].long(), table.class_index, table.slot, table.ids, q, R, t)
    gain = torch.zeros(2, 3)
    gain[list(table.ids).index(2)] = torch.tensor([-0.5, 0.0, 0.2])
    plain, gained = compose_scene(*args), compose_scene(*args, colour_gain=gain)
    from splatreplace_ns.template.compose import apply_colour_gain

    first = plain.instance_id == 1
    second = plain.instance_id == 2
    assert torch.equal(gained.sh[plain.instance_id == 0], plain.sh[plain.instance_id == 0])  # background
    assert torch.allclose(gained.sh[first], plain.sh[first])  # instance 1: gain 1
    # instance 2: its rotated colours times the gain (the gain commutes with the SH rotation)
    expected = apply_colour_gain(plain.sh[second], gain[list(table.ids).index(2)].expand(int(second.sum()), 3))
    assert torch.allclose(gained.sh[second], expected, atol=1e-5)


def test_a_loss_on_one_copy_reaches_only_its_colour_gain():
    params, labels = _random_scene(n_bg=0, n_inst=(10, 10))
    out, table = build_templates(params, labels, {1: "a", 2: "a"}, {1: torch.eye(4), 2: torch.eye(4)}, {"a": 1})
    q, R, t = instance_poses(table.q0, table.t0, torch.zeros(2, 6))
    sh = torch.cat((out["features_dc"][:, None], out["features_rest"]), dim=1)
    gain = torch.zeros(2, 3, requires_grad=True)
    scene = compose_scene(out["means"], out["quats"], out["scales"], out["opacities"], sh, out["sh_offsets"],
                          out["template_class"][:, 0].long(), table.class_index, table.slot, table.ids, q, R, t,
                          colour_gain=gain)
    scene.sh[scene.instance_id == 2].sum().backward()
    row = list(table.ids).index(2)
    assert (gain.grad[row] != 0).all() and (gain.grad[1 - row] == 0).all()
