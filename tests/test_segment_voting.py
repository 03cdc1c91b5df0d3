"""The voting lift (2D instance masks → per-Gaussian labels by blending weight) against oracles, and in a run."""

from __future__ import annotations

import json
import math

import pytest
import torch

from splatreplace_ns.render import rasterize
from splatreplace_ns.instances.lift import (
    Votes, background_query, labels_from_votes, snap_query, view_label_weights, vote_labels, voted_features,
)

W = H = 32
K = torch.tensor([[32.0, 0.0, 16.0], [0.0, 32.0, 16.0], [0.0, 0.0, 1.0]])
LOOK_ALONG_Z = torch.eye(4)  # world = OpenCV camera frame: x right, y down, z forward


def scene(means, scales, opacities):
    means = torch.tensor(means, dtype=torch.float32)
    n = means.shape[0]
    return {
        "means": means, "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n),
        "scales": torch.tensor(scales, dtype=torch.float32)[:, None].expand(n, 3).contiguous(),
        "opacities": torch.tensor(opacities, dtype=torch.float32),
    }


def renderer(gaussians, viewmats):
    def render_view(view, features):
        return rasterize(gaussians["means"], gaussians["quats"], gaussians["scales"], gaussians["opacities"], features,
                         viewmats[view], K, W, H, backend="torch").image
    return render_view


def halves(left: int, right: int) -> torch.Tensor:
    mask = torch.zeros(H, W, dtype=torch.long)
    mask[:, : W // 2], mask[:, W // 2 :] = left, right
    return mask


def pixel_weight_sums(gaussians, viewmat) -> torch.Tensor:
    """Oracle: per Gaussian, its blending weight T·α summed over all pixels, from the renders of the scene with
    one Gaussian's feature set to 1 at a time (the rendered channel is then exactly that Gaussian's weight)."""
    n = gaussians["means"].shape[0]
    out = torch.zeros(n)
    for i in range(n):
        features = torch.zeros(n, 1)
        features[i] = 1.0
        out[i] = renderer(gaussians, viewmat[None])(0, features).sum()
    return out


def test_labels_follow_the_masks_under_each_gaussian_and_unseen_ones_stay_background():
    # left Gaussian projects at column 12, right one at 20; the third is behind the camera
    g = scene([[-0.25, 0.0, 2.0], [0.25, 0.0, 2.0], [0.0, 0.0, -1.0]], [0.05] * 3, [0.9] * 3)
    votes = vote_labels(renderer(g, LOOK_ALONG_Z[None]), [halves(2, 5)], 3)
    assert votes.labels.tolist() == [2, 5, 0]
    assert votes.weights.shape == (3, 6) and votes.views == 1
    # every bit of a Gaussian's weight lands on its own label, and the totals are the rendered weights
    expected = pixel_weight_sums(g, LOOK_ALONG_Z)
    assert torch.allclose(votes.weights.sum(-1), expected, rtol=1e-5, atol=1e-6)
    assert float(votes.weights[0, 2]) == pytest.approx(float(expected[0]), rel=1e-5)
    assert float(votes.weights[2].abs().sum()) == 0.0
    assert votes.share.tolist() == pytest.approx([1.0, 1.0, 0.0])


def test_a_gaussian_straddling_two_labels_takes_the_one_with_more_of_its_weight():
    # centred on column 17.6: 1.6 px into the right half (σ ≈ 1.6 px), so most of its weight is on label 4
    g = scene([[0.05, 0.0, 2.0]], [0.1], [0.9])
    votes = vote_labels(renderer(g, LOOK_ALONG_Z[None]), [halves(3, 4)], 1)
    assert votes.labels.tolist() == [4]
    left, right = float(votes.weights[0, 3]), float(votes.weights[0, 4])
    assert 0 < left < right
    # a majority threshold above its share leaves it unlabelled
    assert labels_from_votes(votes.weights, min_share=right / (left + right) + 0.01).tolist() == [0]
    assert labels_from_votes(votes.weights, min_share=0.5).tolist() == [4]


def test_an_occluded_gaussian_gets_little_weight_and_the_front_surface_decides():
    # a large opaque Gaussian at z = 1 in front of the small one at (0.25, 0, 2)
    behind_alone = scene([[0.25, 0.0, 2.0]], [0.05], [0.9])
    both = scene([[0.25, 0.0, 2.0], [0.25, 0.0, 1.0]], [0.05, 0.2], [0.9, 0.99])
    alone = vote_labels(renderer(behind_alone, LOOK_ALONG_Z[None]), [halves(0, 1)], 1).weights.sum()
    votes = vote_labels(renderer(both, LOOK_ALONG_Z[None]), [halves(0, 1)], 2)
    assert float(votes.weights[0].sum()) < 0.25 * float(alone)
    assert float(votes.weights[1].sum()) > 20 * float(votes.weights[0].sum())
    assert votes.labels.tolist() == [1, 1]


def test_views_add_up_and_background_votes_too():
    # seen on label 3 from the first camera and on background (0) from two others: background wins 2:1
    g = scene([[-0.25, 0.0, 2.0]], [0.05], [0.9])
    views = torch.eye(4).repeat(3, 1, 1)
    votes = vote_labels(renderer(g, views), [halves(3, 3), halves(0, 0), halves(0, 7)], 1)
    assert votes.views == 3
    assert votes.labels.tolist() == [0]
    assert float(votes.weights[0, 0]) == pytest.approx(2 * float(votes.weights[0, 3]), rel=1e-5)
    assert float(votes.weights[0, 7]) == 0.0  # label 7 is only where the Gaussian is not


def test_ties_go_to_the_smaller_label_and_empty_inputs_give_background():
    weights = torch.tensor([[1.0, 1.0, 0.0], [0.0, 2.0, 2.0], [0.0, 0.0, 0.0]])
    assert labels_from_votes(weights).tolist() == [0, 1, 0]
    assert labels_from_votes(torch.zeros(0, 3)).shape == (0,)
    g = scene([[0.0, 0.0, 2.0]], [0.05], [0.9])
    no_views = vote_labels(renderer(g, LOOK_ALONG_Z[None]), [], 1)
    assert no_views.labels.tolist() == [0] and no_views.views == 0
    empty = scene([[0.0, 0.0, 2.0]], [0.05], [0.9])
    empty = {k: v[:0] for k, v in empty.items()}
    nothing = vote_labels(renderer(empty, LOOK_ALONG_Z[None]), [halves(1, 2)], 0)
    assert nothing.labels.shape == (0,) and nothing.weights.shape == (0, 3)


def test_non_finite_gaussians_stay_unlabelled_and_do_not_spoil_the_others():
    for bad in ({"opacities": (0, float("nan"))}, {"means": ((0, 0), float("nan"))}, {"scales": ((0, 0), math.inf)}):
        g = scene([[-0.25, 0.0, 2.0], [0.25, 0.0, 2.0]], [0.05] * 2, [0.9] * 2)
        (name, (index, value)), = bad.items()
        g[name][index] = value
        votes = vote_labels(renderer(g, LOOK_ALONG_Z[None]), [halves(2, 5)], 2)
        assert bool(torch.isfinite(votes.weights).all()), bad
        assert votes.labels.tolist() == [0, 5], bad


def test_mask_of_another_size_is_refused():
    g = scene([[0.0, 0.0, 2.0]], [0.05], [0.9])
    with pytest.raises(ValueError, match=r"mask of size \(16, 32\)"):
        view_label_weights(lambda f: renderer(g, LOOK_ALONG_Z[None])(0, f), torch.zeros(16, 32, dtype=torch.long), 1)


def test_queries_and_features_select_exactly_the_voted_labels():
    from splatreplace_ns.instances.from_clicks import InstanceSelection, SelectionError

    votes = Votes(labels=torch.tensor([2, 0, 2, 1]), weights=torch.ones(4, 3), views=1)
    features = voted_features(votes)
    assert features.tolist() == [[0, 0, 1], [1, 0, 0], [0, 0, 1], [0, 1, 0]]
    # a pixel where label 2 has most of the weight gives label 2's query; an empty pixel gives none
    assert snap_query(torch.tensor([0.3, 0.1, 0.5])).tolist() == [0, 0, 1]
    assert snap_query(torch.zeros(3)).tolist() == [0, 0, 0]
    selection = InstanceSelection(gaussian_features=lambda: features, background_query=background_query(votes))
    selection.add(snap_query(torch.tensor([0.3, 0.1, 0.5])), "chair", "click a")
    selection.add(snap_query(torch.tensor([0.2, 0.7, 0.0])), "table", "click b")
    assert selection.labels().tolist() == [1, 0, 1, 2]
    with pytest.raises(SelectionError, match="background"):
        selection.add(snap_query(torch.tensor([0.9, 0.05, 0.05])), "chair", "click c")
    with pytest.raises(SelectionError, match="same Gaussians as instance 1"):
        selection.add(snap_query(torch.tensor([0.0, 0.0, 0.8])), "chair", "click d")
    with pytest.raises(SelectionError, match="no feature"):
        selection.add(snap_query(torch.zeros(3)), "chair", "click e")


def test_ns_train_with_the_voting_lift_selects_the_clicked_instances(tmp_path):
    """A whole run with the voting lift: no contrastive stage, the clicks select the voted instances right after
    the base stage, masks and carving follow. The base stage is 20 steps from the scene's points made opaque (the
    vote needs geometry, not a converged model), so the test stays short."""
    from splatreplace_ns.tools.bench.segment import leftovers_by_instance
    from splatreplace_ns.method.train import make_trainer_config, run_training
    from splatreplace_ns.tools.sim import make_scene

    data = tmp_path / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path / "runs", 20, contrastive_iterations=300)
    config.pipeline.model.num_downscales = 0
    config.pipeline.segmentation.lift = "voting"
    assert config.pipeline.total_iterations == 20  # no contrastive stage (and no fine-tuning here)
    config.max_num_iterations = config.pipeline.total_iterations

    def opaque(trainer) -> None:
        trainer.pipeline.model.gauss_params["opacities"].data.fill_(float(torch.logit(torch.tensor(0.95))))

    pipeline = run_training(config, before_train=opaque).pipeline
    assert pipeline.stage_at(19) == "base" and pipeline.stage_at(20) == "segmented"
    model = pipeline.model
    clicks = json.loads((data / "clicks.json").read_text())
    assert model.stage == "segmented"
    assert [(i["id"], i["class"]) for i in model.instances] == [(k, c["class"]) for k, c in enumerate(clicks, start=1)]
    report = pipeline.segmentation_report
    assert report["lift"] == "voting" and report["vote_time_s"] > 0 and report["skipped_clicks"] == []
    assert model.instance_labels.shape == (model.num_points,)
    # instance k is click k's ground-truth object: its Gaussians sit on that object's mesh, its rendered
    # training-view masks overlap that object's masks
    instances = pipeline.datamanager.train_dataparser_outputs.metadata["instances"]
    ds = pipeline.datamanager.train_dataset
    gt = torch.stack([ds.get_data(i, image_type="uint8")["instance_mask"][..., 0].long() for i in range(len(ds))])
    ours = pipeline.instance_masks_2d.long()
    for k, click in enumerate(clicks, start=1):
        mine = model.means.detach().cpu()[model.instance_labels == k]
        assert mine.shape[0] > 10
        on_object = leftovers_by_instance(mine, torch.zeros(mine.shape[0], dtype=torch.long), instances)
        share = float(on_object[click["id"]].float().mean())
        a, b = ours == k, gt == click["id"]
        iou = float((a & b).sum()) / float((a | b).sum())
        print(f"instance {k}: {share:.2f} of its Gaussians on object {click['id']}, mask IoU {iou:.2f}")
        assert share > 0.5 and iou > 0.5, (k, share, iou)


def test_votes_from_known_labels_put_all_weight_on_each_label():
    from splatreplace_ns.instances.lift import votes_from_labels

    votes = votes_from_labels(torch.tensor([0, 2, 1, 2, 7]), 2)  # 7: beyond the largest label, clamped to it
    assert votes.labels.tolist() == [0, 2, 1, 2, 2] and votes.views == 0
    assert votes.weights.shape == (5, 3) and torch.equal(votes.weights.sum(-1), torch.ones(5))
    assert torch.equal(labels_from_votes(votes.weights), votes.labels) and torch.equal(votes.share, torch.ones(5))


def test_a_capture_without_masks_selects_the_masks_step_instances_without_a_round_trip(tmp_path):
    """Photos and clicks only: the masks step gives every Gaussian its instance id, and with the voting lift the
    clicks' instances are those ids as they are (no vote over the rendered masks, no contrastive stage); the user's
    transforms.json is left byte for byte as it was."""
    from splatreplace_ns.tools.bench.segment import leftovers_by_instance
    from splatreplace_ns.tools.sim.capture import strip_ground_truth
    from splatreplace_ns.method.train import make_trainer_config, run_training
    from splatreplace_ns.tools.sim import make_scene

    scene = tmp_path / "scene"
    make_scene("tiny", scene, n_train=12)
    capture = tmp_path / "capture"
    strip_ground_truth(scene, capture)
    given = (capture / "transforms.json").read_bytes()
    config = make_trainer_config(capture, tmp_path / "runs", 300, contrastive_iterations=1)
    config.pipeline.segmentation.lift = "voting"
    config.max_num_iterations = config.pipeline.total_iterations
    pipeline = run_training(config).pipeline
    assert (capture / "transforms.json").read_bytes() == given
    assert (capture / "instance_masks" / "index.json").exists()
    assert pipeline.segmentation_report["vote_views"] == 0  # the masks step's ids, not a vote over rendered masks
    model = pipeline.model
    clicks = json.loads((scene / "clicks.json").read_text())
    assert [(i["id"], i["class"]) for i in model.instances] == [(k, c["class"]) for k, c in enumerate(clicks, start=1)]
    instances = json.loads((scene / "transforms.json").read_text())["instances"]
    truth = pipeline.datamanager.train_dataparser_outputs  # the capture has no truth: map the scene's by the same frame
    from splatreplace_ns.datamanager.dataparser import SplatReplaceDataParser

    gt = SplatReplaceDataParser._instances({"instances": instances}, truth, scene)
    for k, click in enumerate(clicks, start=1):
        mine = model.means.detach().cpu()[model.instance_labels == k]
        assert mine.shape[0] > 10, (k, mine.shape)
        on_object = leftovers_by_instance(mine, torch.zeros(mine.shape[0], dtype=torch.long), gt)
        share = float(on_object[click["id"]].float().mean())
        assert share > 0.5, (k, share)
