"""The user's regime: evaluation masks on the test frames alone, the folder each ``bench suite --inputs`` regime
trains on, COLMAP's sparse points at known poses, and the demo's masked figures only against the same masks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from test_datamanager import setup_dm, write_dataset
from splatreplace_ns.datamanager.click_masks import with_click_masks
from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.datamanager.validate import check_dataset


def evaluation_masks_only(root: Path) -> dict:
    """``write_dataset``'s capture (frames 0-3 train, 4-5 eval) with instance masks on the eval frames alone."""
    meta = write_dataset(root)
    for frame in meta["frames"]:
        if frame["file_path"] in meta["train_filenames"]:
            frame.pop("instance_mask_path")
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def test_masks_on_the_eval_frames_alone_are_accepted_and_masks_on_some_train_frames_are_not(tmp_path):
    evaluation_masks_only(tmp_path)
    check_dataset(tmp_path / "transforms.json", tmp_path / "clicks.json")  # no error
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["frames"][0]["instance_mask_path"] = "masks/0000.png"  # one training frame too: neither rule holds
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetFormatError, match="'instance_mask_path' is given in 3 of 6 frames"):
        check_dataset(tmp_path / "transforms.json", tmp_path / "clicks.json")


def test_evaluation_masks_score_the_eval_split_and_never_train(tmp_path):
    """Train split: no masks (ours makes them from the clicks). Eval split: the given masks, as ground truth,
    with the listed instances (and their poses). Once masks are made from clicks, training takes those and the
    eval split keeps the given ones."""
    from splatreplace_ns.datamanager.mask_writer import write_dataset_masks

    evaluation_masks_only(tmp_path)
    dm = setup_dm(tmp_path)
    assert not dm.has_instance_masks
    train_meta = dm.train_dataparser_outputs.metadata
    assert train_meta["instance_mask_filenames"] is None and train_meta["instances"] == []
    eval_meta = dm.eval_dataset.metadata
    assert [p.name for p in eval_meta["instance_mask_filenames"]] == ["0004.png", "0005.png"]
    assert dm.eval_dataset.instance_masks_source == "ground_truth"
    assert {i["id"] for i in eval_meta["instances"]} == {1, 2} and "transform_matrix" in eval_meta["instances"][0]
    batch = dm.eval_dataset[0]
    assert set(np.unique(batch["instance_mask"].numpy()).tolist()) == {0, 1, 2}

    made = np.zeros((24, 32), np.uint16)
    made[0:4, 0:4] = 7  # an id the clicks gave, not the ground truth's
    write_dataset_masks(tmp_path, [made] * 6, [{"id": 7, "class": "chair"}], "digest")
    dm.reload_instance_masks()
    assert dm.has_instance_masks and dm.train_dataset.instance_masks_source == "clicks"
    assert set(np.unique(dm.train_dataset[0]["instance_mask"].numpy()).tolist()) == {0, 7}
    assert dm.eval_dataset.instance_masks_source == "ground_truth"
    assert set(np.unique(dm.eval_dataset[0]["instance_mask"].numpy()).tolist()) == {0, 1, 2}
    # every reader sees the given masks aside and the clicks' masks on every frame
    meta = with_click_masks(json.loads((tmp_path / "transforms.json").read_text()), tmp_path)
    assert all(f["instance_mask_path"].startswith("instance_masks/") for f in meta["frames"])
    assert [f.get("evaluation_mask_path") for f in meta["frames"]][4:] == ["masks/0004.png", "masks/0005.png"]


def test_an_evaluation_mask_with_an_unlisted_id_is_named(tmp_path):
    import cv2

    evaluation_masks_only(tmp_path)
    mask = np.zeros((24, 32), np.uint16)
    mask[:4, :4] = 9
    cv2.imwrite(str(tmp_path / "masks/0005.png"), mask)
    with pytest.raises(DatasetFormatError, match=r"masks/0005.png: ids \[9\] are not listed"):
        check_dataset(tmp_path / "transforms.json", tmp_path / "clicks.json")


def test_each_regime_withholds_what_it_says():
    from splatreplace_ns.tools.bench.user_inputs import user_transforms

    frames = [{"file_path": f"images/{i}.png", "instance_mask_path": f"masks/{i}.png",
               "depth_file_path": f"depth/{i}.png", "transform_matrix": np.eye(4).tolist()} for i in range(4)]
    meta = {"frames": frames, "train_filenames": ["images/0.png", "images/1.png", "images/2.png"],
            "test_filenames": ["images/3.png"], "ply_file_path": "points3d.ply", "depth_unit_scale_factor": 0.001,
            "instances": [{"id": 1}]}
    user = user_transforms(meta, (), "sparse.ply")
    assert [("instance_mask_path" in f, "depth_file_path" in f) for f in user["frames"]] == \
        [(False, False)] * 3 + [(True, False)]
    assert user["ply_file_path"] == "sparse.ply" and "depth_unit_scale_factor" not in user
    assert "ply_file_path" not in user_transforms(meta, (), "")  # too few points: random Gaussians
    masks = user_transforms(meta, ("masks",), "sparse.ply")
    assert all("instance_mask_path" in f and "depth_file_path" not in f for f in masks["frames"])
    depth = user_transforms(meta, ("depth",), "sparse.ply")
    assert all("depth_file_path" in f for f in depth["frames"]) and depth["depth_unit_scale_factor"] == 0.001
    assert user_transforms(meta, ("points",), "sparse.ply")["ply_file_path"] == "points3d.ply"
    assert meta["frames"][0]["instance_mask_path"] == "masks/0.png"  # the scene's own is not changed


def test_sparse_points_triangulated_at_the_known_poses_lie_on_the_scene(tmp_path):
    """COLMAP's points of a textured scene at its true poses: enough of them, and each near a true Gaussian
    (the scene's Gaussians are 0.04-0.1 wide; a point triangulated with a wrong pose convention lands metres off)."""
    from scenes import write_gaussian_scene
    from splatreplace_ns.tools.bench.sparse_points import triangulate_training_views

    truth = write_gaussian_scene(tmp_path, n_gaussians=300, n_views=36, width=128, height=96)
    xyz, rgb, report = triangulate_training_views(tmp_path, upsample=2)
    # measured: 254 points, median distance 0.076 to the nearest Gaussian's centre (the points lie on the blobs'
    # visible sides, not at their centres)
    assert report["points"] == len(xyz) == len(rgb) >= 100
    distance = np.linalg.norm(xyz[:, None] - truth["means"].numpy()[None], axis=-1).min(axis=1)
    assert np.median(distance) < 0.15 and np.mean(distance < 0.25) > 0.8, (np.median(distance), len(xyz))


def test_a_regime_folder_links_the_scene_and_is_reused(tmp_path, monkeypatch):
    from splatreplace_ns.tools.bench import sparse_points
    from splatreplace_ns.tools.bench.user_inputs import make_regime_folder, scene_of

    scene = tmp_path / "scene"
    write_dataset(scene)
    (scene / "clicks.json").write_text(json.dumps([{"file_path": "images/0000.png", "xy": [5, 4], "class": "chair"}]))
    calls = []

    def fake_cloud(source, out_ply, upsample=4):  # the triangulation itself is tested above
        calls.append(source)
        return {"points": 3, "written": False}

    monkeypatch.setattr(sparse_points, "write_sparse_cloud", fake_cloud)
    folder = make_regime_folder(scene, "user")
    assert folder.name == "scene_user" and scene_of(folder, "user") == scene
    meta = json.loads((folder / "transforms.json").read_text())
    assert "ply_file_path" not in meta and not (folder / "depth").exists()
    assert (folder / "images" / "0000.png").read_bytes() == (scene / "images" / "0000.png").read_bytes()
    check_dataset(folder / "transforms.json", folder / "clicks.json")
    assert make_regime_folder(scene, "user") == folder and len(calls) == 1  # reused
    assert make_regime_folder(scene, "exact") == scene
    with pytest.raises(ValueError, match="--inputs"):
        make_regime_folder(scene, "oracle")


def test_a_masks_run_in_the_users_regime_starts_from_the_sparse_cloud(tmp_path, monkeypatch):
    """``bench masks --inputs user`` (and ``bench mask-passes``) strip their capture from the user's folder: the
    sparse cloud, not the scene's dense one; no masks, no depth; the same images and clicks."""
    from splatreplace_ns.tools.bench import sparse_points
    from splatreplace_ns.tools.bench.masks import regime_source
    from splatreplace_ns.tools.sim.capture import strip_ground_truth

    scene = tmp_path / "scene"
    meta = write_dataset(scene)
    meta["ply_file_path"] = "dense.ply"
    (scene / "dense.ply").write_text("dense")
    (scene / "transforms.json").write_text(json.dumps(meta))
    (scene / "clicks.json").write_text(json.dumps([{"file_path": "images/0000.png", "xy": [5, 4], "class": "chair"}]))

    def fake_cloud(source, out_ply, upsample=4):  # the triangulation itself is tested above
        Path(out_ply).write_text("sparse")
        return {"points": 30, "written": True}

    monkeypatch.setattr(sparse_points, "write_sparse_cloud", fake_cloud)
    assert regime_source(scene, "exact") == scene
    capture = tmp_path / "capture"
    strip_ground_truth(regime_source(scene, "user"), capture)
    stripped = json.loads((capture / "transforms.json").read_text())
    assert (capture / stripped["ply_file_path"]).read_text() == "sparse"
    assert not any("instance_mask_path" in f or "depth_file_path" in f for f in stripped["frames"])
    assert (capture / "images" / "0000.png").read_bytes() == (scene / "images" / "0000.png").read_bytes()
    assert json.loads((capture / "clicks.json").read_text())[0]["xy"] == [5, 4]


def test_the_demo_shows_masked_figures_only_when_both_use_the_true_masks():
    from splatreplace_ns.tools.demo import comparable_masks

    truth = {"instance_masks": "ground truth"}
    assert comparable_masks(truth, truth) is None
    clicks = {"instance_masks": "made from the clicks (splatreplace masks or ns-train), not ground truth"}
    assert "no masked figures" in comparable_masks({"instance_masks": None}, clicks)
    assert "no masked figures" in comparable_masks(truth, clicks)
