"""Segmentation math against hand-made cases: sampling, contrastive loss, selection, carving."""

from __future__ import annotations

import torch

from splatreplace_ns.instances.carve import carve_mask
from splatreplace_ns.features.contrastive import ContrastiveLossConfig, contrastive_loss, cosine_distance
from splatreplace_ns.datamanager.sampling import sample_contrastive_pixels
from splatreplace_ns.instances.select import masks_from_rendered_features, select_gaussians


def test_sampling_gives_every_mask_its_share():
    mask = torch.zeros(40, 50, dtype=torch.int32)
    mask[0:2, 0:2] = 3  # tiny instance: 4 pixels
    mask[10:30, 10:40] = 1
    g = torch.Generator().manual_seed(0)
    idx, labels = sample_contrastive_pixels(mask, n_uniform=1000, n_per_mask=200, generator=g)
    assert idx.shape == labels.shape == (1000 + 3 * 200,)
    assert torch.equal(mask.reshape(-1)[idx].long(), labels)
    per_mask = labels[1000:]
    for label in (0, 1, 3):
        assert (per_mask == label).sum() == 200
    # uniform part follows the area: instance 1 covers 600/2000 of the image
    share = (labels[:1000] == 1).float().mean().item()
    assert abs(share - 0.3) < 0.06


def test_contrastive_loss_prefers_separated_features():
    labels = torch.tensor([0] * 20 + [1] * 20 + [2] * 20)
    separated = torch.nn.functional.one_hot(labels, 8).float()
    mixed = torch.ones(60, 8) + 0.01 * torch.randn(60, 8)
    g = torch.Generator().manual_seed(0)
    good = contrastive_loss(separated, labels, generator=g)
    bad = contrastive_loss(mixed, labels, generator=torch.Generator().manual_seed(0))
    assert good["pull"] < 1e-6 and good["push"] < 1e-6 and good["hard_pull"] < 1e-6
    assert bad["push"] > 0.1
    assert good["unit_norm"] < 1e-8


def test_contrastive_loss_gradients_are_finite_for_zero_features():
    features = torch.zeros(30, 16, requires_grad=True)
    labels = torch.randint(0, 3, (30,))
    losses = contrastive_loss(features, labels)
    sum(losses.values()).backward()
    assert torch.isfinite(features.grad).all()


def test_contrastive_loss_single_pixel_is_zero():
    losses = contrastive_loss(torch.ones(1, 4, requires_grad=True), torch.zeros(1, dtype=torch.long))
    assert all(v.item() == 0 for v in losses.values())


def test_hard_pairs_add_pull():
    labels = torch.tensor([1, 1])
    far = torch.tensor([[1.0, 0.0], [-1.0, 0.0]])  # distance 2 > 0.5
    losses = contrastive_loss(far, labels, ContrastiveLossConfig(max_pairs=10))
    assert losses["hard_pull"] > 0 and torch.isclose(losses["hard_pull"], losses["pull"])


def test_selection_threshold():
    queries = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    feats = torch.tensor([[2.0, 0.0, 0.0], [0.0, 0.5, 0.01], [0.7, 0.7, 0.0], [0.0, 0.0, 1.0]])
    labels = select_gaussians(feats, queries, tau=0.1)
    assert labels.tolist() == [1, 2, 0, 0]
    assert cosine_distance(feats[2], queries[0]) > 0.1
    assert select_gaussians(feats, torch.zeros(0, 3)).tolist() == [0, 0, 0, 0]


def test_masks_from_rendered_features_respects_alpha():
    queries = torch.eye(2, 4)
    rendered = torch.zeros(2, 3, 4)
    rendered[0, :, 0] = 1.0
    rendered[1, :, 1] = 1.0
    alpha = torch.ones(2, 3, 1)
    alpha[1, 2] = 0.1
    masks = masks_from_rendered_features(rendered, alpha, queries)
    assert masks.tolist() == [[1, 1, 1], [2, 2, 0]]


def test_carving_removes_only_instance_leftovers_hidden_in_every_view():
    W, H = 20, 20
    K = torch.tensor([[20.0, 0, 10], [0, 20.0, 10], [0, 0, 1]])
    views = torch.stack([torch.eye(4), torch.eye(4)])
    views[1, 0, 3] = 0.5  # second camera shifted
    means = torch.tensor([
        [0.0, 0.0, 2.0],    # projects into the instance mask in both views
        [0.3, 0.3, 2.0],    # visible background in view 0
        [0.0, 0.0, -1.0],   # behind both cameras: never near an instance, kept
        [0.3, 0.3, 5.0],    # behind the rendered surface in both views, inside the mask in view 0
        [-0.6, -0.6, 5.0],  # behind the rendered surface in both views, never inside a mask: kept
    ])
    masks = torch.zeros(2, H, W, dtype=torch.bool)
    masks[0, 8:12, 8:12] = True
    masks[1, 8:12, 14:17] = True  # the first centre projects to u = 15 there
    depths = torch.full((2, H, W), 2.0)
    remove = carve_mask(means, views, torch.stack([K, K]), W, H, masks, depths)
    assert remove.tolist() == [True, False, False, True, False]
    assert carve_mask(torch.zeros(0, 3), views, torch.stack([K, K]), W, H, masks, depths).shape == (0,)


def test_carving_mask_tolerance_takes_a_leftover_just_outside_a_thin_mask():
    """A leftover whose centre projects one pixel beside a one-pixel-wide mask (a chair leg the threshold
    thinned) in one view and inside it in the other: kept without tolerance, carved with one pixel; a centre
    two pixels away stays with one pixel of tolerance."""
    W, H = 20, 20
    K = torch.tensor([[20.0, 0, 10], [0, 20.0, 10], [0, 0, 1]])
    views = torch.stack([torch.eye(4), torch.eye(4)])
    masks = torch.zeros(2, H, W, dtype=torch.bool)
    masks[0, :, 10] = True  # column 10 only
    masks[1, :, 11] = True
    depths = torch.zeros(2, H, W)  # nothing rendered: every centre in front of the camera is visible
    means = torch.tensor([
        [0.1, 0.0, 2.0],   # u = 11: beside the mask in view 0, inside it in view 1
        [0.2, 0.0, 2.0],   # u = 12: two pixels from view 0's mask
    ])
    Ks = torch.stack([K, K])
    assert carve_mask(means, views, Ks, W, H, masks, depths).tolist() == [False, False]
    assert carve_mask(means, views, Ks, W, H, masks, depths, mask_tolerance=1).tolist() == [True, False]
    # no mask anywhere: a tolerance does not make one
    assert carve_mask(means, views, Ks, W, H, torch.zeros_like(masks), depths, mask_tolerance=2).tolist() == [False, False]


def test_segmentation_scores_hand_made_case():
    from splatreplace_ns.eval.segmentation import segmentation_scores

    gt = torch.zeros(1, 4, 4, dtype=torch.long)
    gt[0, :2, :2] = 5  # 4 pixels
    gt[0, 2:, 2:] = 7  # 4 pixels
    pred = torch.zeros_like(gt)
    pred[0, :2, :3] = 1  # covers gt 5 plus 2 background pixels
    pred[0, 3, 3] = 2  # 1 of 4 pixels of gt 7
    scores = segmentation_scores(pred, gt, {1: 5, 2: 7})
    assert scores["iou"] == {5: 4 / 6, 7: 1 / 4}
    assert abs(scores["miou"] - (4 / 6 + 1 / 4) / 2) < 1e-12
    # accuracies: instance 5 → 1, instance 7 → 1/4, background → 6/8
    assert abs(scores["macc"] - (1 + 0.25 + 0.75) / 3) < 1e-12


def test_mask_coverage_counts_the_pixels_each_instance_covers_inside_its_own_mask():
    masks = torch.zeros(4, 6, dtype=torch.long)
    masks[:2, :3] = 1  # 6 pixels
    masks[2:, 3:] = 2  # 6 pixels
    alpha = torch.zeros(4, 6, 2)
    alpha[0, :3, 0] = 0.9  # instance 1 covers 3 of its 6 pixels
    alpha[1, 0, 0] = 0.49  # below min_alpha: not covered
    alpha[:, :, 1] = 0.6  # instance 2 is everywhere: only its own 6 pixels count
    from splatreplace_ns.instances.select import mask_coverage_counts

    counts = mask_coverage_counts(masks, alpha, min_alpha=0.5)
    assert counts.tolist() == [[3, 6], [6, 6]]
    empty = mask_coverage_counts(torch.zeros(4, 6, dtype=torch.long), alpha)
    assert empty.tolist() == [[0, 0], [0, 0]]  # an instance seen in no pixel of this view


def test_undercovered_instances_are_named_with_their_share():
    from splatreplace_ns.instances.select import undercovered_instances

    instances = [{"id": 1, "class": "chair", "num_gaussians": 6}, {"id": 2, "class": "table", "num_gaussians": 900}]
    messages = undercovered_instances(instances, [0.05, 0.6], min_coverage=0.2)
    assert len(messages) == 1 and messages[0].startswith("instance 1 (chair, 6 Gaussians) covers 5% ")
    assert undercovered_instances(instances, [0.2, 0.6], min_coverage=0.2) == []


def test_a_clicks_file_counts_once_it_appears_and_reads(tmp_path):
    import json

    from splatreplace_ns.datamanager.clicks import clicks_file_appeared

    path = tmp_path / "clicks.json"
    appeared = clicks_file_appeared(path)
    assert not appeared()
    path.write_text('[{"file_path": "images/0001.png", "xy": [3')  # still being written
    assert not appeared()
    path.write_text(json.dumps([{"file_path": "images/0001.png", "xy": [3, 4], "class": "chair"}]))
    assert appeared()
    assert not clicks_file_appeared(path)()  # a file there from the start is not a new answer


def test_a_wait_for_viewer_clicks_ends_when_asked_and_gives_its_lock_back():
    import threading

    from splatreplace_ns.viewer.click_controls import ClickControls

    controls = ClickControls("Panel", "a", "u", "c", "l", "s", "status")
    lock = threading.Lock()
    lock.acquire()
    calls = []
    assert controls._wait(0.01, lock, stop_when=lambda: calls.append(lock.locked()) or len(calls) > 2) is False
    assert calls[:2] == [False, False] and lock.locked()  # released while waiting, held again after
    controls._confirmed.set()
    assert controls._wait(0.01, lock, stop_when=lambda: True) is True
    lock.release()
