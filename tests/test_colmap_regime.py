"""``bench suite --inputs user --poses colmap``: the user's regime with COLMAP's poses, intrinsics and sparse cloud.

The pure part (:func:`colmap_transforms`) is checked against a capture whose "COLMAP" poses are the true ones
moved by a known similarity; the whole regime against a real ``ns-process-data`` run on a tiny scene (skipped when
``colmap`` is not installed, unless ``SPLATREPLACE_REQUIRE_COLMAP=1``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splatreplace_ns.eval.alignment import similarity_pose
from splatreplace_ns.tools.bench.colmap_poses import colmap_transforms, shrink_intrinsics


def _pose(rotvec, centre) -> np.ndarray:
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    c2w[:3, 3] = centre
    return c2w


def _scene_and_capture(rng, unposed=("images/0002.png",)):
    """A scene's transforms.json (6 training views, 2 test views, one instance) and a processed capture whose
    poses are the true ones moved by a known similarity (scale 0.5), photos 4x larger."""
    frames = [{"file_path": f"images/{i:04d}.png", "transform_matrix": _pose(rng.normal(size=3), rng.normal(size=3) * 3).tolist(),
               "instance_mask_path": f"masks/{i:04d}.png"} for i in range(8)]
    scene = {"camera_model": "PINHOLE", "fl_x": 80.0, "fl_y": 80.0, "cx": 48.0, "cy": 36.0, "w": 96, "h": 72,
             "frames": frames, "train_filenames": [f["file_path"] for f in frames[:6]],
             "val_filenames": [f["file_path"] for f in frames[6:]], "test_filenames": [f["file_path"] for f in frames[6:]],
             "instances": [{"id": 1, "class": "chair", "transform_matrix": _pose([0, 0, 0.3], [1, 2, 0]).tolist(),
                            "size": 2.0}], "ply_file_path": "points3d.ply", "depth_unit_scale_factor": 0.001}
    fit = (0.5, Rotation.from_rotvec([0.1, -0.4, 0.7]).as_matrix(), np.array([3.0, -1.0, 2.0]))
    processed = {"fl_x": 322.0, "fl_y": 321.0, "cx": 191.5, "cy": 143.5, "w": 384, "h": 288,
                 "applied_transform": [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], "ply_file_path": "sparse_pc.ply",
                 "frames": []}
    names = {}
    for k, frame in enumerate(frames[:6]):
        if frame["file_path"] in unposed:
            continue
        processed["frames"].append({"file_path": f"images/frame_{k + 1:05d}.png",
                                    "transform_matrix": similarity_pose(np.asarray(frame["transform_matrix"]), *fit).tolist()})
        names[Path(frame["file_path"]).name] = f"images/frame_{k + 1:05d}.png"
    return scene, processed, names, fit


def test_intrinsics_of_enlarged_photos_scale_back_to_the_same_rays():
    """Pixel i's centre is at i + 0.5 on both images, so the centre of small pixel i is at 4·(i + 0.5) on the 4x photo:
    every such point keeps its ray (u − cx) / fx."""
    small = shrink_intrinsics({"fl_x": 320.0, "fl_y": 300.0, "cx": 191.5, "cy": 143.5}, 4, (96, 72))
    assert small == {"fl_x": 80.0, "fl_y": 75.0, "cx": 47.875, "cy": 35.875, "w": 96, "h": 72}
    for i in (0, 10, 95):
        assert (4 * (i + 0.5) - 191.5) / 320.0 == pytest.approx((i + 0.5 - small["cx"]) / small["fl_x"])


def test_test_views_and_instances_move_by_the_fitted_similarity_and_unposed_views_leave():
    rng = np.random.default_rng(3)
    scene, processed, names, fit = _scene_and_capture(rng)
    out, report = colmap_transforms(scene, processed, names, scale=4)
    by_path = {f["file_path"]: f for f in out["frames"]}
    assert "images/0002.png" not in by_path and "images/0002.png" not in out["train_filenames"]
    assert report["posed"] == 5 and report["photos"] == 6
    assert report["similarity_scale"] == pytest.approx(0.5)
    assert report["centre_error_m"]["max"] < 1e-9 and report["rotation_error_deg"]["max"] < 1e-4  # arccos near 1
    for frame in scene["frames"][6:]:  # test views: the true camera in COLMAP's frame, the true intrinsics and masks
        moved = by_path[frame["file_path"]]
        np.testing.assert_allclose(moved["transform_matrix"], similarity_pose(np.asarray(frame["transform_matrix"]), *fit),
                                   atol=1e-9)
        assert (moved["fl_x"], moved["cx"], moved["w"]) == (80.0, 48.0, 96)
        assert moved["instance_mask_path"] == frame["instance_mask_path"]
    train = by_path["images/0001.png"]  # training views: COLMAP's pose and intrinsics, no mask
    assert train["fl_x"] == pytest.approx(322.0 / 4) and train["w"] == 96 and "instance_mask_path" not in train
    assert "fl_x" not in out and "depth_unit_scale_factor" not in out  # per-frame intrinsics; no depth
    assert out["ply_file_path"] == "sparse_pc.ply" and out["applied_transform"] == processed["applied_transform"]
    instance = out["instances"][0]
    np.testing.assert_allclose(instance["transform_matrix"],
                               similarity_pose(np.asarray(scene["instances"][0]["transform_matrix"]), *fit), atol=1e-9)
    assert instance["size"] == pytest.approx(1.0)  # object sizes in COLMAP's units


def test_too_few_posed_views_stop_with_the_reason():
    rng = np.random.default_rng(4)
    scene, processed, names, _ = _scene_and_capture(
        rng, unposed=tuple(f"images/{i:04d}.png" for i in range(4)))
    with pytest.raises(RuntimeError, match="COLMAP posed 2 of 6"):
        colmap_transforms(scene, processed, names, scale=4)


def test_a_colmap_regime_folder_trains_on_colmap_poses_and_scores_the_true_views(tmp_path):
    """ns-process-data on a tiny scene's training photos: most views posed, their rotations agree with the
    truth after the fit (within what the suite calls a right pose), and nerfstudio reads the folder: COLMAP's intrinsics for
    training, the true ones and evaluation masks for the test views, clicks on posed views."""
    from test_photos_e2e import require_colmap

    require_colmap()
    from splatreplace_ns.datamanager.dataparser import SplatReplaceDataParserConfig
    from splatreplace_ns.tools.bench.user_inputs import make_regime_folder
    from splatreplace_ns.tools.sim import make_scene

    scene = tmp_path / "scene"
    make_scene("tiny", scene, res="64x48", seed=0, n_train=24, n_test=4)
    folder = make_regime_folder(scene, "user+colmap")
    report = json.loads((folder / "inputs.json").read_text())["colmap"]
    print(report)
    assert report["posed"] >= 20, report
    assert report["command"].startswith("ns-process-data images ") and report["sparse_points"] > 100
    assert report["rotation_error_deg"]["mean"] < 5.0, report  # COLMAP varies by run: 0.36 and 1.22 measured
    meta = json.loads((folder / "transforms.json").read_text())
    clicks = json.loads((folder / "clicks.json").read_text())
    assert {c["file_path"] for c in clicks} <= set(meta["train_filenames"])
    parser = SplatReplaceDataParserConfig(data=folder).setup()
    test = parser.get_dataparser_outputs("test")
    truth = json.loads((scene / "transforms.json").read_text())
    assert len(test.image_filenames) == 4
    assert float(test.cameras.fx[0]) == pytest.approx(truth["fl_x"])
    assert test.metadata.get("instance_mask_filenames") or test.metadata.get("evaluation_mask_filenames")
    train = parser.get_dataparser_outputs("train")
    assert len(train.image_filenames) == report["posed"]
