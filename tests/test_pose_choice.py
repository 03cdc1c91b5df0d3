"""Choosing a pose against the training images: among candidate poses the one that explains the instance's pixels
best wins, a rival turned far from it that explains them almost as well makes the choice ambiguous, and copies of
one pose are neither rivals nor rendered twice."""

from __future__ import annotations

import math

import pytest
import torch

from splatreplace_ns.poses.decision import choose_pose, pick_with_margin
from splatreplace_ns.poses.evidence import (PlacedRenders, colour_fitted, instance_id_maps, instance_views, mean_view_psnr,
                                            pooled_psnr, psnr, subset)
from splatreplace_ns.render.transform import transform_gaussians
from splatreplace_ns.poses.candidates import yaw_rotation
from splatreplace_ns.poses.variants import registration_variant
from splatreplace_ns.poses.config import RegistrationConfig

from two_boxes import _images, _object, _render_fn, _scene, _views

UP = torch.tensor([0.0, 0.0, 1.0])
CENTRE_2 = torch.tensor([1.0, 0.0, 0.0])  # instance 2 stands here


def _turned(T: torch.Tensor, degrees: float) -> torch.Tensor:
    """The registration ``T`` (template ≈ T · instance) with the instance turned by ``degrees`` about its axis."""
    return T @ yaw_rotation(UP, math.radians(degrees), CENTRE_2)


def _setup(with_handle: bool = True):
    """The two-box scene, its training images, a render function and the scene's instance maps."""
    scene, labels, T = _scene(with_handle, yaw_i=math.radians(30))
    viewmats = _views()
    images = _images(scene, viewmats)
    render = _render_fn(viewmats)
    rgb, ids = instance_id_maps(scene, labels, range(len(images)), render)
    return scene, labels, T, images, render, ids, rgb


def _choose(with_handle: bool, candidates_deg, count_renders: bool = False, per_view: bool = False):
    scene, labels, T, images, render, ids, rgb = _setup(with_handle)
    calls = []

    def counted(view, g, extra):
        calls.append(view)
        return render(view, g, extra)

    choice = choose_pose(scene, labels, 2, 1, [_turned(T, d) for d in candidates_deg], images,
                         counted if count_renders else render, ids, rgb, margin_db=1.0, rival_deg=20.0,
                         max_views=4, per_view=per_view)
    return choice, calls


def test_pick_with_margin_against_the_best_rival_turned_far_enough():
    poses = [yaw_rotation(UP, math.radians(d), torch.zeros(3)) for d in (0.0, 5.0, 180.0, 90.0)]
    # candidate 1 is 5° from the best: the same pose, not a rival; the best rival is the half turn
    assert pick_with_margin([20.0, 19.9, 18.5, 15.0], poses, 1.0, 20.0) == (0, 2, True)
    assert pick_with_margin([20.0, 19.9, 19.5, 15.0], poses, 1.0, 20.0) == (0, 2, False)
    assert pick_with_margin([20.0, 19.9], poses[:2], 1.0, 20.0) == (0, None, True)  # no rival at all


@pytest.mark.parametrize("per_view", [False, True])
def test_the_true_pose_beats_the_half_turn_that_puts_the_handle_on_the_wrong_side(per_view):
    for order in ((0.0, 180.0), (180.0, 0.0)):  # whichever comes first
        choice, _ = _choose(with_handle=True, candidates_deg=order, per_view=per_view)
        assert order[choice.chosen] == 0.0 and choice.rival is not None
        assert choice.accepted, choice.reason
        assert choice.margin_db > 1.0
        assert choice.scores[choice.chosen] > 30.0  # the scene's own images: the true pose explains them closely


def test_a_plain_box_is_ambiguous_between_half_turns_that_look_alike():
    # one colour, no handle: the box looks the same turned by 180°, so the images cannot tell the two apart
    # (instance 2 is another sample of the same box: copies in a capture are never Gaussian for Gaussian alike)
    scene, labels, T = _scene(with_handle=False, yaw_i=math.radians(30))
    scene["sh"][labels > 0] = torch.tensor([0.85, 0.8, 0.6])
    other, _ = _object(False, seed=5)
    scene["means"][labels == 2] = other @ yaw_rotation(UP, math.radians(30), torch.zeros(3))[:3, :3].T + CENTRE_2
    viewmats = _views()
    # pixel noise as in a real capture, where even the true pose explains an instance at 15-25 dB (the dev split)
    noise = torch.Generator().manual_seed(3)
    images = [(im + 0.06 * torch.randn(im.shape, generator=noise)).clamp(0, 1) for im in _images(scene, viewmats)]
    render = _render_fn(viewmats)
    rgb, ids = instance_id_maps(scene, labels, range(len(images)), render)
    choice = choose_pose(scene, labels, 2, 1, [T, _turned(T, 180.0)], images, render, ids, rgb, 1.0, 20.0, 4)
    assert choice.rival is not None and abs(choice.margin_db) < 1.0, choice.scores
    assert not choice.accepted and "ambiguous" in choice.reason


def test_copies_of_one_pose_are_rendered_once_and_are_not_rivals():
    one, calls_one = _choose(with_handle=True, candidates_deg=(0.0,), count_renders=True)
    three, calls_three = _choose(with_handle=True, candidates_deg=(0.0, 0.0, 360.0), count_renders=True)
    assert len(calls_three) == len(calls_one)  # the same renders: one per compared view
    assert three.rival is None and three.accepted and three.scores[0] == three.scores[1]


def test_an_instance_no_view_sees_is_not_chosen_for():
    scene, labels, T, images, render, ids, rgb = _setup()
    choice = choose_pose(scene, labels, 2, 1, [T], images, render, ids, rgb, 1.0, 20.0, 4, min_pixels=10**6)
    assert choice.chosen is None and not choice.accepted and "not seen" in choice.reason


def test_the_papers_rule_compares_nothing_with_the_images():
    assert RegistrationConfig().image_choice
    assert not registration_variant("paper", RegistrationConfig()).image_choice
    assert not registration_variant("no_image_choice", RegistrationConfig()).image_choice


def test_between_a_pose_and_its_polish_the_one_that_explains_the_images_better_is_kept():
    # the pipeline keeps the upright polish of the chosen pose only where the images agree: the two are compared
    # with no rival (every turn counts as the same pose) and no margin
    scene, labels, T, images, render, ids, rgb = _setup()
    for pair, better in (([T, _turned(T, 6.0)], 0), ([_turned(T, 6.0), T], 1)):
        check = choose_pose(scene, labels, 2, 1, pair, images, render, ids, rgb, 0.0, 180.0, 4)
        assert check.chosen == better and check.rival is None and check.accepted


def test_the_mean_of_the_views_psnr_is_not_outweighed_by_one_view_every_pose_renders_badly():
    torch.manual_seed(0)
    target = [torch.rand(200, 3) * 0.8 + 0.1, torch.rand(200, 3) * 0.8 + 0.1]
    wrong_everywhere = 1.0 - target[1]  # a view no pose explains (say, an occluder)
    noise = torch.randn(200, 3)
    right = [target[0] + 0.01 * noise, wrong_everywhere]  # 40 dB in the first view
    turned = [target[0] + 0.1 * noise, wrong_everywhere]  # 20 dB there
    # one view: each score is that view's PSNR (gain ~1 here), and the two statistics agree
    assert mean_view_psnr(right[:1], target[:1]) == pytest.approx(pooled_psnr(right[:1], target[:1]))
    per_view_gap = mean_view_psnr(right, target) - mean_view_psnr(turned, target)
    pooled_gap = pooled_psnr(right, target) - pooled_psnr(turned, target)
    # the first view tells the poses apart by 20 dB; averaged with the view that cannot, half of it remains
    assert per_view_gap == pytest.approx(10.0, abs=1.0)
    assert pooled_gap < 1.0  # pooled, the bad view's error swamps the evidence


def test_the_mean_of_the_views_psnr_skips_views_without_pixels_and_fits_a_gain():
    target = [torch.full((50, 3), 0.5), torch.zeros(0, 3), torch.full((50, 3), 0.4)]
    dim = [t * 0.5 for t in target]  # the copy lit half as bright: a gain of 2 explains both views exactly
    assert mean_view_psnr(dim, target) == pytest.approx(50.0)  # capped: a perfect explanation
    assert pooled_psnr(dim, target) == pytest.approx(50.0)


def test_the_margin_on_the_pair_s_own_pixels_does_not_shrink_with_a_far_off_candidate():
    scene, labels, T, images, render, ids, rgb = _setup(with_handle=True)
    shift = torch.eye(4)
    shift[:3, 3] = torch.tensor([0.0, -1.2, 0.0])  # a candidate that puts the copy 1.2 m beside the instance
    near, turned, far = _turned(T, 0.0), _turned(T, 180.0), _turned(T, 0.0) @ shift

    def margin(candidates, where):
        choice = choose_pose(scene, labels, 2, 1, candidates, images, render, ids, rgb, 1.0, 20.0, 4,
                             margin_pixels=where)
        assert choice.chosen == 0 and choice.rival is not None
        return choice.margin_db

    # the far candidate's pixels, where the true pose and the half turn render alike, dilute the margin on all
    # pixels; on the pair's own pixels it is the same with or without that candidate
    assert margin([near, turned, far], "all") < margin([near, turned], "all") - 0.1
    assert margin([near, turned, far], "pair") == pytest.approx(margin([near, turned], "pair"), abs=1e-4)
    assert margin([near, turned], "pair") == pytest.approx(margin([near, turned], "all"), abs=1e-4)
    with pytest.raises(ValueError, match="margin_pixels"):
        choose_pose(scene, labels, 2, 1, [near, turned], images, render, ids, rgb, 1.0, 20.0, 4, margin_pixels="some")


def test_fine_turns_bring_a_candidate_left_a_few_degrees_off_to_the_pose_the_images_show():
    scene, labels, T, images, render, ids, rgb = _setup()
    candidates = [_turned(T, 6.0), _turned(T, 90.0)]
    plain = choose_pose(scene, labels, 2, 1, candidates, images, render, ids, rgb, 1.0, 20.0, 4)
    assert plain.chosen == 0 and plain.transform is None and plain.turn_deg == 0.0
    fine = choose_pose(scene, labels, 2, 1, candidates, images, render, ids, rgb, 1.0, 20.0, 4,
                       fine_turns_deg=(-6.0, -3.0, 3.0, 6.0), up=UP, centre=CENTRE_2)
    assert fine.chosen == 0 and fine.turn_deg == -6.0 and fine.accepted, fine.reason
    assert torch.allclose(torch.tensor(fine.transform), T, atol=1e-4)  # exactly the true pose
    assert fine.chosen_score > plain.scores[0] + 1.0  # and it explains the pixels clearly better
    assert fine.rival == 1 and fine.margin_db == pytest.approx(fine.chosen_score - fine.rival_score)
    assert "turned -6°" in fine.reason
    # without an axis or a pivot there is nothing to turn about: the plain choice
    assert choose_pose(scene, labels, 2, 1, candidates, images, render, ids, rgb, 1.0, 20.0, 4,
                       fine_turns_deg=(-6.0, 6.0)).transform is None


def _whole_image_scores(scene, labels, poses, images, render, views, ids, rgb, per_view):
    """The oracle: each pose (template → instance) rendered whole in every view, the compared pixels taken on the
    whole image (the instance's and every placed copy's)."""
    rest, template = subset(scene, labels != 2), subset(scene, labels == 1)
    marker = torch.cat((torch.zeros(len(rest["means"]), 1), torch.ones(len(template["means"]), 1)))
    own, target, placed = [], [], [[] for _ in poses]
    for v in views:
        renders = []
        for pose in poses:
            means, quats, sh = transform_gaussians(pose, template["means"], template["quats"], template["sh"])
            copy = {**template, "means": means, "quats": quats, "sh": sh}
            renders.append(render(v, {k: torch.cat((rest[k], copy[k])) for k in rest}, marker))
        footprint = ids[v] == 2
        for _, weight in renders:
            footprint = footprint | (weight[..., 0] >= 0.5)
        target.append(images[v][footprint])
        own.append(rgb[v][footprint])
        for k, (colour, _) in enumerate(renders):
            placed[k].append(colour[footprint])
    score = mean_view_psnr if per_view else pooled_psnr
    return [score(own, target), *[score(px, target) for px in placed], int(sum(t.shape[0] for t in target))]


def _flat(scores):
    own, per_pose, pixels = scores
    return [own, *per_pose, pixels]


@pytest.mark.parametrize("per_view", [False, True])
def test_renders_kept_in_boxes_score_as_whole_images_and_a_copy_outside_widens_the_box(per_view):
    scene, labels, T, images, render, ids, rgb = _setup()
    views = instance_views(ids, 2, 4, 16)
    shift = torch.eye(4)
    shift[:3, 3] = torch.tensor([0.0, -1.2, 0.0])  # puts the copy 1.2 m beside the instance: outside its box
    first = [torch.linalg.inv(_turned(T, d)) for d in (0.0, 90.0)]
    later = [torch.linalg.inv(_turned(T, 3.0)), torch.linalg.inv(_turned(T, 0.0) @ shift)]
    calls = []

    def counted(view, g, extra):
        calls.append(view)
        return render(view, g, extra)

    placed = PlacedRenders(scene, labels, 2, 1, counted, views, ids)
    placed.add(first)
    assert len(calls) == 2 * len(views)
    before = placed.scores(images, rgb, per_view)
    assert _flat(before) == pytest.approx(_whole_image_scores(scene, labels, first, images, render, views, ids, rgb, per_view))
    boxes = dict(placed.boxes)
    placed.add(later[:1])  # a small turn stays inside the boxes: rendered once per view, nothing again
    assert placed.boxes == boxes and len(calls) == 3 * len(views)
    placed.add(later[1:])
    widened = [v for v in views if placed.boxes[v] != boxes[v]]
    assert widened  # the far copy reaches outside the boxes: the 3 kept poses are rendered again there, only there
    assert len(calls) == 4 * len(views) + 3 * len(widened)
    every = placed.scores(images, rgb, per_view)
    assert _flat(every) == pytest.approx(_whole_image_scores(scene, labels, first + later, images, render, views, ids, rgb,
                                                      per_view))
    pair = placed.scores(images, rgb, per_view, which=[2, 0])
    assert _flat(pair) == pytest.approx(_whole_image_scores(scene, labels, [later[0], first[0]], images, render, views, ids,
                                                     rgb, per_view))


def test_fine_turns_render_only_the_new_poses():
    scene, labels, T, images, render, ids, rgb = _setup()
    calls = []

    def counted(view, g, extra):
        calls.append(view)
        return render(view, g, extra)

    choose_pose(scene, labels, 2, 1, [_turned(T, 6.0), _turned(T, 90.0)], images, counted, ids, rgb, 1.0, 20.0, 4,
                fine_turns_deg=(-6.0, -3.0, 3.0, 6.0), up=UP, centre=CENTRE_2)
    # 2 candidates and 4 turns of each of the 2 leading poses, each rendered once in each of the 4 views
    assert len(calls) == (2 + 2 * 4) * 4


def test_colour_fit_undoes_a_per_channel_gain_but_cannot_flatten_a_prediction_to_the_mean():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(500, 3, generator=g) * 0.6 + 0.2
    pred = target * torch.tensor([0.7, 1.0, 1.4])  # a copy lit by a coloured light
    assert psnr(colour_fitted(pred, target), target) >= 49.0
    assert psnr(pred, target) < 25.0
    unrelated = torch.rand(500, 3, generator=g)
    mean_only = psnr(target.mean(0).expand_as(target), target)
    assert psnr(colour_fitted(unrelated, target), target) < mean_only
