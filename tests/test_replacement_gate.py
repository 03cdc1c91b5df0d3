"""The pose check against the training images: a pose that puts a one-sided detail on the wrong side is
refused, the right pose passes, a symmetric object's turn is not held against it, and an instance no view sees
is not refused for lack of evidence."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splatreplace_ns.poses.evidence import colour_fitted, psnr
from splatreplace_ns.poses.gate import ReplacementGateConfig, gate_registrations, judge, yaw_rotation
from splatreplace_ns.poses.virtual_cameras import intrinsics
from splatreplace_ns.render.cameras import look_at
from splatreplace_ns.render import rasterize

W, H = 64, 48
K = torch.tensor(intrinsics(W, H, 60.0), dtype=torch.float32)
BACKGROUND = torch.tensor([0.2, 0.25, 0.3])


def _object(with_handle: bool, seed: int):
    """Gaussians of a box 0.4 × 0.4 × 0.5 m on the floor, centred at the origin, with a red handle on its +x side."""
    g = torch.Generator().manual_seed(seed)
    n = 400
    pts = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([0.4, 0.4, 0.5]) + torch.tensor([0.0, 0.0, 0.25])
    colours = torch.tensor([0.85, 0.8, 0.6]).expand(n, 3).clone()
    colours[pts[:, 1] > 0] = torch.tensor([0.3, 0.5, 0.8])  # two-tone, so that turns are seen in colour too
    if with_handle:
        handle = torch.rand(120, 3, generator=g) * torch.tensor([0.12, 0.3, 0.15]) + torch.tensor([0.2, -0.15, 0.2])
        pts = torch.cat((pts, handle))
        colours = torch.cat((colours, torch.tensor([0.9, 0.1, 0.1]).expand(len(handle), 3)))
    return pts, colours


def _scene(with_handle: bool, yaw_i: float):
    """Background floor + the template instance (id 1) at x=-1 + instance 2 at x=+1 turned by ``yaw_i``."""
    g = torch.Generator().manual_seed(7)
    floor = torch.cat(((torch.rand(1500, 2, generator=g) - 0.5) * 5.0, torch.zeros(1500, 1)), dim=1)
    floor_col = 0.4 + 0.2 * torch.rand(1500, 1, generator=g).expand(1500, 3)
    obj, obj_col = _object(with_handle, 1)
    a = obj + torch.tensor([-1.0, 0.0, 0.0])
    Rz = yaw_rotation(torch.tensor([0.0, 0.0, 1.0]), yaw_i, torch.zeros(3))[:3, :3]
    b = obj @ Rz.T + torch.tensor([1.0, 0.0, 0.0])
    means = torch.cat((floor, a, b))
    colours = torch.cat((floor_col, obj_col, obj_col))
    labels = torch.cat((torch.zeros(len(floor)), torch.ones(len(a)), 2 * torch.ones(len(b)))).long()
    n = len(means)
    scene = {
        "means": means, "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone(),
        "log_scales": torch.full((n, 3), math.log(0.04)), "logit_opacities": torch.full((n,), 4.0),
        "sh": colours[:, None, :],  # degree 0: the "SH" is the colour itself in this test's renderer
    }
    # instance 2 → template (instance 1): undo the turn, then move from x=+1 to x=-1
    T = torch.eye(4)
    T[:3, :3] = Rz.T
    T[:3, 3] = torch.tensor([-1.0, 0.0, 0.0]) - Rz.T @ torch.tensor([1.0, 0.0, 0.0])
    return scene, labels, T


def _views():
    views = []
    for k in range(8):  # a ring around both copies, from above
        ang = 2 * math.pi * k / 8
        eye = np.array([3.2 * math.cos(ang), 3.2 * math.sin(ang), 1.8])
        views.append(torch.tensor(look_at(eye, np.array([0.0, 0.0, 0.25])), dtype=torch.float32))
    return views


def _render_fn(viewmats):
    def render(view, g, extra):
        colours = g["sh"][:, 0]
        out = rasterize(g["means"], g["quats"], torch.exp(g["log_scales"]), torch.sigmoid(g["logit_opacities"]).reshape(-1),
                        torch.cat((colours, extra), dim=-1), viewmats[view], K, W, H, backend="torch")
        rgb = out.image[..., :3] + (1 - out.alpha) * BACKGROUND
        return rgb.clamp(0, 1), out.image[..., 3:]
    return render


def _images(scene, viewmats):
    render = _render_fn(viewmats)
    return [render(v, scene, torch.zeros(len(scene["means"]), 0))[0] for v in range(len(viewmats))]


CFG = ReplacementGateConfig(turns=4, max_views=4)
ADOPT = ReplacementGateConfig(turns=4, max_views=4, adopt_turns=True)


def _gate(with_handle: bool, pose_error_deg: float, cfg=CFG, views=None):
    scene, labels, T = _scene(with_handle, yaw_i=math.radians(30))
    viewmats = _views() if views is None else views
    images = _images(scene, viewmats)
    centre_i = torch.tensor([1.0, 0.0, 0.0])
    # a wrong pose: the registered transform composed with an extra turn about instance 2's vertical axis
    wrong = T @ yaw_rotation(torch.tensor([0.0, 0.0, 1.0]), math.radians(pose_error_deg), centre_i)
    scores = gate_registrations(scene, labels, {1: "box", 2: "box"}, {1: torch.eye(4), 2: wrong}, {"box": 1},
                                images, _render_fn(viewmats), (0.0, 0.0, 1.0), cfg)
    assert set(scores) == {2}  # the template itself is not checked
    return scores[2]


def test_the_true_pose_passes_and_explains_the_pixels_as_well_as_the_instance_itself():
    score = _gate(with_handle=True, pose_error_deg=0.0)
    assert score.passed, score.reason
    assert score.psnr_pose > 30.0 and score.psnr_pose > score.psnr_own - 1.0
    assert score.psnr_own <= 50.0  # capped: a perfect pose must not be refused against inf
    assert score.views == 4 and score.pixels > 0


def test_a_half_turn_that_puts_the_handle_on_the_wrong_side_is_refused():
    score = _gate(with_handle=True, pose_error_deg=180.0)
    assert not score.passed and score.transform is None
    assert score.best_turn_deg == pytest.approx(180.0)  # turning it back is what explains the images
    assert score.psnr_best_turn > score.psnr_pose + CFG.margin_turn_db


def test_the_better_turn_is_adopted_and_is_the_true_pose():
    score = _gate(with_handle=True, pose_error_deg=180.0, cfg=ADOPT)
    assert score.passed and "under that pose" in score.reason
    _, _, T_true = _scene(True, yaw_i=math.radians(30))
    T = torch.tensor(score.transform)
    angle = torch.arccos(((torch.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2).clamp(-1, 1))
    assert math.degrees(float(angle)) < 2.0
    assert float((T[:3, 3] - T_true[:3, 3]).norm()) < 0.02


def test_a_quarter_turn_of_a_box_without_a_handle_is_corrected_when_its_two_tones_show_it():
    score = _gate(with_handle=False, pose_error_deg=90.0, cfg=ADOPT)
    assert score.transform is not None and score.best_turn_deg == pytest.approx(90.0)


def test_a_pose_a_little_off_that_no_turn_fixes_is_refused():
    score = _gate(with_handle=True, pose_error_deg=20.0)
    assert not score.passed and score.transform is None


def test_a_pose_far_off_is_refused_by_the_own_margin_even_without_turns():
    cfg = ReplacementGateConfig(turns=1, max_views=4)
    score = _gate(with_handle=True, pose_error_deg=180.0, cfg=cfg)
    assert score.psnr_best_turn is None and score.transform is None
    assert not score.passed and "worse than the instance itself" in score.reason


def test_an_instance_no_view_sees_is_replaced_with_nothing_to_check():
    away = [torch.tensor(look_at(np.array([-6.0, 0.0, 1.0]), np.array([-9.0, 0.0, 0.0])), dtype=torch.float32)]
    score = _gate(with_handle=True, pose_error_deg=180.0, views=away)
    assert score.passed and score.views == 0 and score.psnr_own is None


def test_colour_fit_undoes_a_per_channel_gain_but_cannot_flatten_a_prediction_to_the_mean():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(500, 3, generator=g) * 0.6 + 0.2
    pred = target * torch.tensor([0.7, 1.0, 1.4])  # a copy lit by a coloured light
    assert psnr(colour_fitted(pred, target), target) >= 49.0
    assert psnr(pred, target) < 25.0
    unrelated = torch.rand(500, 3, generator=g)
    mean_only = psnr(target.mean(0).expand_as(target), target)
    assert psnr(colour_fitted(unrelated, target), target) < mean_only


def test_verdicts_follow_the_margins():
    cfg = ReplacementGateConfig(margin_own_db=3.0, margin_turn_db=0.5, adopt_turns=True)
    assert judge(30.0, 27.5, 27.9, cfg)[0]
    assert not judge(30.0, 26.5, None, cfg)[0]
    assert judge(30.0, 28.0, 28.6, cfg)[0]  # the better turn is adopted
    assert not judge(30.0, 28.0, 28.6, ReplacementGateConfig(margin_own_db=3.0, adopt_turns=False))[0]
    assert not judge(30.0, 25.0, 26.0, cfg)[0]  # the better turn fails the own margin too
    assert judge(None, None, None, cfg)[0]
    with pytest.raises(ValueError):
        ReplacementGateConfig(turns=0)
