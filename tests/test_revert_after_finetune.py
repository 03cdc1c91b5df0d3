"""The check after fine-tuning: a copy that explains its instance's training pixels worse than the instance's own
Gaussians is reverted (its own Gaussians back in the background, out of the template), a copy that explains them
as well is kept, and the stored scene after reverting composes to exactly the expected Gaussians."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splatreplace_ns.poses.virtual_cameras import intrinsics
from splatreplace_ns.render.cameras import look_at
from splatreplace_ns.render import rasterize
from splatreplace_ns.template.build import build_templates
from splatreplace_ns.template.compose import compose_scene, instance_poses
from splatreplace_ns.template.revert import RevertGateConfig, decide, revert_instances, score_replaced_instances

W, H = 48, 36
K = torch.tensor(intrinsics(W, H, 60.0), dtype=torch.float32)
BACKGROUND = torch.tensor([0.2, 0.25, 0.3])


def _box(seed: int, centre, colour):
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(300, 3, generator=g) - 0.5) * 0.4 + torch.tensor(centre)
    return pts, torch.tensor(colour).expand(300, 3).clone()


def _gaussians(means, colours):
    n = len(means)
    return {"means": means, "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone(),
            "log_scales": torch.full((n, 3), math.log(0.04)), "logit_opacities": torch.full((n, 1), 4.0),
            "sh": colours[:, None, :]}


def _render_fn():
    views = [torch.tensor(look_at(np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 1.5]), np.zeros(3)), dtype=torch.float32)
             for a in np.linspace(0, 2 * math.pi, 6, endpoint=False)]

    def render(view, g, extra):
        out = rasterize(g["means"], g["quats"], torch.exp(g["log_scales"]), torch.sigmoid(g["logit_opacities"]).reshape(-1),
                        torch.cat((g["sh"][:, 0], extra.to(g["means"])), dim=-1), views[view], K, W, H, backend="torch")
        return (out.image[..., :3] + (1 - out.alpha) * BACKGROUND).clamp(0, 1), out.image[..., 3:]

    return render, len(views)


def _cat(*parts):
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


@pytest.fixture(scope="module")
def truth():
    """Instance 1 (red box at x = -0.6) and instance 2 (blue box at x = +0.6); rendered into 6 training views."""
    one = _gaussians(*_box(1, [-0.6, 0.0, 0.0], [0.9, 0.1, 0.1]))
    two = _gaussians(*_box(2, [0.6, 0.0, 0.0], [0.1, 0.2, 0.9]))
    render, n = _render_fn()
    scene = _cat(one, two)
    images = [render(v, scene, torch.zeros(len(scene["means"]), 0))[0] for v in range(n)]
    return one, two, render, images


def test_a_copy_that_explains_the_pixels_as_well_is_kept_and_a_wrong_one_is_reverted(truth):
    one, two, render, images = truth
    wrong = dict(two, sh=torch.tensor([0.9, 0.1, 0.1]).expand(len(two["means"]), 1, 3))  # the right shape, red
    for copy_of_two, expect_revert in ((two, False), (wrong, True)):
        scene = _cat(one, copy_of_two)
        ids = torch.cat((torch.ones(len(one["means"])), 2 * torch.ones(len(two["means"])))).long()
        scores = score_replaced_instances(scene, ids, {1: one, 2: two}, images, render, RevertGateConfig(margin_db=1.0))
        assert sorted(scores) == [1, 2]
        assert not scores[1].revert and scores[1].loss_db == pytest.approx(0.0, abs=1e-6)
        assert scores[2].revert is expect_revert, scores[2]
        assert scores[2].views == 6 and scores[2].pixels > 0
        if expect_revert:  # the own Gaussians are the truth: the red copy loses by far
            assert scores[2].loss_db > 10.0 and "put back" in scores[2].reason


def test_an_instance_no_view_sees_is_kept_for_lack_of_evidence(truth):
    one, two, render, images = truth
    far = dict(two, means=two["means"] + torch.tensor([0.0, 0.0, 100.0]))
    scene = _cat(one, far)
    ids = torch.cat((torch.ones(len(one["means"])), 2 * torch.ones(len(far["means"])))).long()
    own_far = {1: one, 2: far}
    scores = score_replaced_instances(scene, ids, own_far, images, render, RevertGateConfig())
    assert scores[2].views == 0 and not scores[2].revert and scores[2].loss_db is None
    assert decide(None, 20.0, 1.0)[0] is False


def _stored(seed=0):
    """A background and three instances of one class (1 is the template), as build_templates stores them."""
    g = torch.Generator().manual_seed(seed)
    n_bg, n = 50, 40
    offsets = {1: torch.tensor([0.0, 0.0, 0.0]), 2: torch.tensor([2.0, 0.0, 0.0]), 3: torch.tensor([0.0, 3.0, 0.0])}
    shape = torch.rand(n, 3, generator=g)
    means = torch.cat([torch.rand(n_bg, 3, generator=g) * 10] + [shape + offsets[i] for i in (1, 2, 3)])
    total = len(means)
    params = {"means": means, "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(total, 4).clone(),
              "scales": torch.full((total, 3), -3.0), "opacities": torch.zeros(total, 1),
              "features_dc": torch.rand(total, 3, generator=g), "features_rest": torch.zeros(total, 3, 3)}
    labels = torch.cat([torch.zeros(n_bg)] + [torch.full((n,), float(i)) for i in (1, 2, 3)]).long()
    transforms = {}
    for i in (1, 2, 3):
        T = torch.eye(4)
        T[:3, 3] = -offsets[i]
        transforms[i] = T
    stored, table = build_templates(params, labels, {1: "box", 2: "box", 3: "box"}, transforms, {"box": 1}, lam=0.8)
    own = {i: {k: v[labels == i] for k, v in params.items()} for i in (1, 2, 3)}
    return stored, table, own, params, labels


def _composed_means(stored, table, delta):
    q, R, t = instance_poses(table.q0, table.t0, delta)
    sh = torch.cat((stored["features_dc"][:, None], stored["features_rest"]), 1)
    return compose_scene(stored["means"], stored["quats"], stored["scales"], stored["opacities"], sh, stored["sh_offsets"],
                         stored["template_class"][:, 0].round().long(), table.class_index, table.slot, table.ids,
                         q, R, t, lam=0.8)


def test_reverting_one_instance_keeps_the_other_copies_and_puts_its_own_gaussians_back():
    stored, table, own, params, labels = _stored()
    delta = torch.zeros(len(table.ids), 6)
    before = _composed_means(stored, table, delta)
    new, new_table, new_delta = revert_instances(stored, table, delta, own, [3])
    assert new_table.ids.tolist() == [1, 2] and new_delta.shape == (2, 6) and 3 in new_table.kept_in_background
    after = _composed_means(new, new_table, new_delta)
    for i in (1, 2):  # the remaining copies are where they were
        assert torch.allclose(after.means[after.instance_id == i], before.means[before.instance_id == i])
    assert int((after.instance_id == 3).sum()) == 0
    background = after.means[after.instance_id == 0]
    assert len(background) == int((labels == 0).sum()) + int((labels == 3).sum())
    assert torch.equal(background[-int((labels == 3).sum()):], params["means"][labels == 3])
    assert (new["sh_offsets"][new["template_class"][:, 0] == 0] == 0).all()


def test_reverting_every_instance_leaves_no_template_gaussians():
    stored, table, own, params, labels = _stored()
    new, new_table, new_delta = revert_instances(stored, table, torch.zeros(3, 6), own, [1, 2, 3])
    assert len(new_table.ids) == 0 and new_delta.shape == (0, 6) and not new_table.template_ids
    assert (new["template_class"] == 0).all()
    assert len(new["means"]) == len(params["means"])  # the scene as it was before replacement, reordered
    assert torch.equal(new["means"].sort(0).values, params["means"].sort(0).values)


def test_config_is_checked():
    with pytest.raises(ValueError):
        RevertGateConfig(at_fraction=1.5)
    with pytest.raises(ValueError):
        RevertGateConfig(margin_db=float("nan"))
    assert RevertGateConfig(at_fraction=0.5).steps_before(1000) == 500
    assert RevertGateConfig(at_fraction=0.0).steps_before(10) == 1
