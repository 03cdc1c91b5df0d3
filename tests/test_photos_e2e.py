"""Photos in, method out: a sim scene's photos alone → ``ns-process-data images`` (COLMAP) → ``ns-train splat-replace``.

The scene's poses, masks and depth are withheld; only the images of its training views go in. Checked against the
scene's truth: the camera centres COLMAP recovers (after a similarity alignment), the cameras every stage renders
from (the same as the datamanager's), and the run's masks, instances, registration and fine-tuning.

Skips when ``colmap`` or ``ffmpeg`` is not installed, unless ``SPLATREPLACE_REQUIRE_COLMAP=1`` (then it fails).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from splatreplace_ns.tools.bench.capture import (
    capture_clicks, ns_process_data, posed_centres, processed_names, training_photos,
)
from splatreplace_ns.eval.alignment import apply_similarity, centre_errors, invert_similarity, similarity_fit
from splatreplace_ns.tools.sim import make_scene

REPO = Path(__file__).resolve().parents[1]
RES, N_TRAIN, N_TEST = "256x192", 24, 4  # SIFT needs this size to pose the crates from every photo
DOWNSCALE = 4  # ns-train trains on ns-process-data's quarter-size copies (64x48), as for a user's large photos


def require_colmap() -> None:
    missing = [tool for tool in ("colmap", "ffmpeg") if shutil.which(tool) is None]
    if missing:
        message = (f"{' and '.join(missing)} not installed (Debian: apt-get install colmap ffmpeg); "
                   "ns-process-data needs them")
        if os.environ.get("SPLATREPLACE_REQUIRE_COLMAP") == "1":
            pytest.fail(message + " and SPLATREPLACE_REQUIRE_COLMAP=1")
        pytest.skip(message)


def tool_env() -> dict:
    """The environment of the ns-* subprocesses: this checkout importable, torch on the test's two threads."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env.setdefault("OMP_NUM_THREADS", "2")
    return env


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    require_colmap()
    root = tmp_path_factory.mktemp("photos")
    scene = root / "scene"
    make_scene("tiny", scene, res=RES, seed=0, n_train=N_TRAIN, n_test=N_TEST)
    photos = root / "photos"
    training_photos(scene, photos)
    data = root / "capture"
    processed = ns_process_data(photos, data, num_downscales=DOWNSCALE.bit_length() - 1, matching="sequential")
    print(f"ns-process-data: {processed['posed']} of {processed['photos']} photos posed in {processed['seconds']:.0f} s")
    names = processed_names(photos, data)
    (data / "clicks.json").write_text(json.dumps(capture_clicks(scene, names), indent=2))
    return {"scene": scene, "photos": photos, "data": data, "names": names, "processed": processed}


def test_colmap_poses_every_photo_where_the_truth_has_it(capture):
    """Every photo is posed, and the recovered camera centres lie on the true ones after a similarity fit."""
    meta = json.loads((capture["data"] / "transforms.json").read_text())
    assert "applied_transform" in meta and meta["camera_model"] == "OPENCV"
    assert capture["processed"]["posed"] == N_TRAIN, capture["processed"]["log"][-2000:]
    recovered, true, _ = posed_centres(capture["scene"], capture["data"], capture["names"])
    errors, (scale, _, _) = centre_errors(recovered, true)
    extent = np.linalg.norm(true - true.mean(axis=0), axis=1).max()
    print(f"camera centres after the similarity fit: mean {errors.mean() * 1000:.1f} mm, max {errors.max() * 1000:.1f} mm "
          f"(path radius {extent:.2f} m; COLMAP units → metres × {scale:.3f})")
    # COLMAP is not deterministic across runs (thread timing): measured max 13.7, 25.6 and 17.4 mm, mean 8.2, about 11 and 9.3
    # mm on a 2.16 m radius. A wrong axis, scale or pose convention is off by a large fraction of the radius.
    assert errors.max() < 0.02 * extent and errors.mean() < 0.01 * extent, errors


def test_processed_names_follow_the_pixels_not_the_order(capture, tmp_path):
    """The photo each processed frame came from is found by content: photos renamed in another order map the same."""
    photos = tmp_path / "shuffled"
    photos.mkdir()
    order = sorted(capture["names"])
    renamed = {name: f"{len(order) - k:03d}_{name}" for k, name in enumerate(order)}  # reversed sort order
    for name, new in renamed.items():
        shutil.copy2(capture["photos"] / name, photos / new)
    names = processed_names(photos, capture["data"])
    assert names == {renamed[n]: path for n, path in capture["names"].items()}


@pytest.mark.parametrize("layout", ["ns_process_data", "colmap_sparse0"])
def test_stages_render_from_the_cameras_nerfstudio_trains_with(capture, tmp_path, layout):
    """On a real ns-process-data output (transforms.json with its applied_transform) and on its COLMAP model alone
    (``sparse/0``, read through pycolmap), the cameras the masks and clicks steps render from equal the
    datamanager's training cameras, and they see the scene as the true cameras do."""
    from splatreplace_ns.datamanager.datamanager import SplatReplaceDataManagerConfig
    from splatreplace_ns.instances.frames import frame_cameras

    data = capture["data"]
    if layout == "colmap_sparse0":
        data = tmp_path / "colmap_only"
        shutil.copytree(capture["data"] / "images", data / "images")
        shutil.copytree(capture["data"] / "colmap" / "sparse" / "0", data / "sparse" / "0")
    config = SplatReplaceDataManagerConfig()
    config.data = data
    config.dataparser.eval_mode = "all"
    dm = config.setup(device="cpu", test_mode="test")
    outputs = dm.train_dataparser_outputs
    frames = frame_cameras(data / "transforms.json", outputs.dataparser_transform, outputs.dataparser_scale)
    ours = []
    for index, path in enumerate(dm.train_dataset.image_filenames):
        k = frames.index_of(str(Path(path).relative_to(data)), "test")
        assert torch.allclose(frames.cameras.camera_to_worlds[k], dm.train_dataset.cameras.camera_to_worlds[index],
                              atol=1e-5), (layout, path)
        ours.append(frames.cameras.camera_to_worlds[k].numpy())
    assert len(ours) == N_TRAIN
    # the relative poses of the rendered cameras are the true ones up to one similarity (rotations included)
    true = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"])
            for f in json.loads((capture["scene"] / "transforms.json").read_text())["frames"]}
    photo_of = {Path(v).name: k for k, v in capture["names"].items()}
    true_c2w = np.stack([true[photo_of[Path(p).name]] for p in dm.train_dataset.image_filenames])
    ours = np.stack(ours)
    errors, fit = centre_errors(ours[:, :3, 3], true_c2w[:, :3, 3])
    assert errors.max() < 0.01 * np.ptp(true_c2w[:, :3, 3], axis=0).max()
    # exactly COLMAP's cameras: each of its 3D points, carried into our frame by the similarity of the camera
    # centres (exact here: both are the same reconstruction), projects through our camera (intrinsics, distortion
    # and axes as the stages render) onto the pixel COLMAP observed it at
    names = [Path(p).name for p in dm.train_dataset.image_filenames]
    colmap = colmap_reprojection_errors(capture["data"] / "colmap" / "sparse" / "0", names, dm.train_dataset.cameras,
                                        ours)
    # and seen as the true cameras see: surface points of each true view (from its depth) land on the pixels they
    # came from. COLMAP trades a few pixels of principal point against ~1° of rotation, so pixels are the oracle
    depth_of = {Path(f["file_path"]).name: capture["scene"] / f["depth_file_path"]
                for f in json.loads((capture["scene"] / "transforms.json").read_text())["frames"]}
    truth = reprojection_errors(
        truth=json.loads((capture["scene"] / "transforms.json").read_text()), true_c2w=true_c2w,
        depths=[depth_of[photo_of[name]] for name in names], cameras=dm.train_dataset.cameras, fit=fit)
    for what, errors in (("COLMAP's points", colmap), ("the true surface", truth)):
        print(f"{layout}: reprojection of {what} through our cameras: median {np.median(errors):.2f} px, "
              f"99th percentile {np.percentile(errors, 99):.2f} px")
    # a wrong axis, pose, intrinsics or distortion convention is off by tens of pixels. COLMAP keeps observations
    # within 4 px of its own projection: measured median 0.38 px, 95th percentile 1.83, max 3.51. Against the truth
    # (the centre fit's ~1 cm, COLMAP's distortion fitted to a pinhole truth) two COLMAP runs gave medians of 1.2
    # and 2.0 px and 99th percentiles of 4.6 and 4.5: that bound is loose, COLMAP's is tight
    assert np.median(colmap) < 1.0 and np.percentile(colmap, 95) < 3.0 and colmap.max() < 5.0, \
        np.percentile(colmap, [50, 95, 100])
    assert np.median(truth) < 4.0 and np.percentile(truth, 99) < 10.0, np.percentile(truth, [50, 99])


def project(cameras, k: int, points: np.ndarray) -> np.ndarray:
    """[M, 2] pixels of world points [M, 3] (the dataparser's frame) in camera ``k`` of nerfstudio ``cameras``
    (OPENCV distortion: k1, k2, k3, k4, p1, p2), pixel centres at +0.5 as nerfstudio and COLMAP place them."""
    c2w = cameras.camera_to_worlds[k].double().numpy() @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL → OpenCV axes
    w2c = np.linalg.inv(np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]]))
    matrix = np.array([[float(cameras.fx[k]), 0.0, float(cameras.cx[k])],
                       [0.0, float(cameras.fy[k]), float(cameras.cy[k])], [0.0, 0.0, 1.0]])
    k1, k2, k3, _, p1, p2 = cameras.distortion_params[k].double().tolist()
    projected, _ = cv2.projectPoints(np.asarray(points, np.float64), cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3], matrix,
                                     np.array([k1, k2, p1, p2, k3]))
    return projected.reshape(-1, 2)


def colmap_reprojection_errors(sparse: Path, names: list, cameras, ours_c2w: np.ndarray) -> np.ndarray:
    """Pixel distances [M] between COLMAP's observations of its 3D points and their projections through our
    cameras (one per name of ``names``, ``ours_c2w`` [N, 4, 4] their poses)."""
    import pycolmap

    model = pycolmap.Reconstruction(str(sparse))
    by_name = {image.name: image for image in model.images.values()}
    images = [by_name[name] for name in names]
    fit = similarity_fit(np.stack([image.projection_center() for image in images]), ours_c2w[:, :3, 3])
    out = []
    for k, image in enumerate(images):
        seen = [p for p in image.points2D if p.has_point3D()]
        xyz = np.stack([model.points3D[p.point3D_id].xyz for p in seen])
        observed = np.stack([p.xy for p in seen])
        out.append(np.linalg.norm(project(cameras, k, apply_similarity(xyz, *fit)) - observed, axis=1))
    return np.concatenate(out)


def reprojection_errors(truth: dict, true_c2w: np.ndarray, depths: list, cameras, fit, stride: int = 8) -> np.ndarray:
    """Pixel distances [M] between where the true views saw their surface points and where our cameras project them.

    Args:
        truth: the scene's transforms.json (pinhole intrinsics ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``).
        true_c2w: [N, 4, 4] the true camera→world poses (OpenGL axes), one per camera of ``cameras``.
        depths: N paths of the true 16-bit z-depth PNGs (``depth_unit_scale_factor`` metres per unit, 0 = no hit).
        cameras: nerfstudio ``Cameras`` [N] at the truth's image size.
        fit: (scale, R, t) mapping our world onto the true one (our camera centres → the true centres).
    """
    to_ours = invert_similarity(*fit)
    scale = float(truth["depth_unit_scale_factor"])
    out = []
    for k, depth_path in enumerate(depths):
        depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED).astype(np.float64) * scale
        v, u = np.mgrid[stride // 2:depth.shape[0]:stride, stride // 2:depth.shape[1]:stride]
        z = depth[v, u]
        hit = z > 0
        u, v, z = u[hit] + 0.5, v[hit] + 0.5, z[hit]  # pixel centres, as the renderer casts them
        camera_points = np.stack([(u - truth["cx"]) / truth["fl_x"] * z, -(v - truth["cy"]) / truth["fl_y"] * z, -z], 1)
        world = camera_points @ true_c2w[k, :3, :3].T + true_c2w[k, :3, 3]
        out.append(np.linalg.norm(project(cameras, k, apply_similarity(world, *to_ours)) - np.stack([u, v], 1), axis=1))
    return np.concatenate(out)


def test_ns_train_runs_the_method_from_the_photos(capture, tmp_path):
    """``ns-train splat-replace`` on the processed photos with the scene's clicks: masks are made for every frame and
    show the clicked crates, each click becomes an instance of class crate or is left out with its reason (at least
    two become instances), registration runs on each and the registered ones are replaced by one shared template,
    and fine-tuning runs to the last step."""
    data = tmp_path / "capture"
    shutil.copytree(capture["data"], data, ignore=shutil.ignore_patterns("colmap"))
    before = (data / "transforms.json").read_bytes()
    B, C, F = 300, 200, 20
    command = [str(Path(sys.executable).parent / "ns-train"), "splat-replace", "--data", str(data),
               "--output-dir", str(tmp_path / "out"), "--timestamp", "t", "--vis", "tensorboard",
               "--pipeline.base-iterations", str(B), "--pipeline.contrastive-iterations", str(C),
               "--pipeline.finetune-iterations", str(F),
               "--pipeline.datamanager.dataparser.downscale-factor", str(DOWNSCALE),
               # COLMAP's point cloud is sparse (hundreds of points): densify from step 100, not 500, or the base
               # stage of a tiny budget never grows the crates apart and two clicks fall on one cluster
               "--pipeline.model.warmup-length", "100", "--pipeline.model.refine-every", "50",
               # at this budget often one crate alone registers: replace it too (the lone-copy rule would not), so
               # that the run reaches a shared template
               "--pipeline.registration.min-class-copies", "1"]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, timeout=1800, env=tool_env(), cwd=tmp_path)
    (tmp_path / "ns-train.log").write_text(result.stdout + result.stderr)
    log = re.sub(r"\s+", " ", result.stdout + result.stderr)
    skipped = re.findall(r"masks: skipped [^\[]*", log)
    # what the masks and segmentation steps said, for a failure's message
    stages = re.findall(r"(?:skipped|masks:|segmentation:|instance \d+ \(|click \d+ \()[^\[]{0,200}", log)
    print(f"ns-train: {time.perf_counter() - start:.0f} s")
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]

    clicks = json.loads((data / "clicks.json").read_text())
    truth = json.loads((capture["scene"] / "transforms.json").read_text())
    classes = {i["id"]: i["class"] for i in truth["instances"]}
    # every click is accounted for: it makes an instance, or it is left out with its reason, never both or neither
    made = {int(k) for k in re.findall(r"instance \d+ \((?:crate)\): \d+ Gaussians from click (\d+)\b", log)}
    left_out = {int(k) for k in re.findall(r"skipped: click (\d+)\b", log)}
    no_mask = {int(k) for k in re.findall(r"masks: skipped click (\d+)\b", log)}
    assert made.isdisjoint(left_out) and made | left_out == set(range(len(clicks))), (made, left_out, stages)
    # a click that made no mask selects nothing (the features never learnt its crate: it would take another's)
    assert no_mask <= left_out, (no_mask, stages)
    # COLMAP's sparse cloud differs from run to run (its CPU matching is not reproducible, see below). On some
    # clouds the 300-step base model is so coarse (about 1 700 Gaussians, a crate 2-3 point spacings tall) that
    # the floor plane takes a crate's lower half and a click there is left out as on the floor, with its reason.
    # Over 15 runs of this test, each with its own COLMAP run, 11 made 3 instances and 4 made 2 (one click left out
    # as on the floor at the masks step and at segmentation); 18 runs later (10 of them two at a time) one made 1:
    # two crates clicked 2.9 spacings apart were taken for one object clicked twice (the limit is now the split's
    # seed radius, 2 spacings). The two failing captures of those 18 again and 8 new runs two at a time: 9 made 3
    # and 1 made 2 (a click on the floor). A broken masks or segmentation step makes fewer.
    assert len(made) >= 2, stages
    assert re.search(rf"segmentation: {len(made)} instances", log), stages
    assert re.search(rf"registration: {len(made)} instances in {len(set(classes.values()))} classes", log)
    # posed copies' candidates are judged against the photos (chosen, or left as it was when ambiguous)
    assert re.search(r"instance \d+: (not replaced: )?candidate \d+|instance \d+: not seen in any training", log), \
        log[-3000:]
    shared = re.search(r"shared templates: (\d+) classes, (\d+) instances", log)
    # at this budget the instances are small (tens of Gaussians): at least one is registered and replaced
    assert shared and int(shared.group(1)) == 1 and int(shared.group(2)) >= 1, log[-3000:]
    run = tmp_path / "out" / data.name / "splat-replace" / "t"
    assert (run / "nerfstudio_models" / f"step-{B + C + F - 1:09d}.ckpt").exists()

    # the masks the run made from the clicks: one per frame, beside transforms.json (which stays as it was), against
    # the truth through the clicks' true ids (instance k is click k - 1)
    assert (data / "transforms.json").read_bytes() == before
    masked = [k for k in range(len(clicks)) if k not in no_mask]
    assert re.search(rf"masks: {len(masked)} instances in {len(json.loads(before)['frames'])} frames", log), log[-3000:]
    assert len(skipped) == len(no_mask), skipped
    index = json.loads((data / "instance_masks" / "index.json").read_text())
    assert [(i["id"], i["class"]) for i in index["instances"]] == [(k + 1, classes[clicks[k]["id"]]) for k in masked]
    frames = index["frames"]
    assert sorted(f["file_path"] for f in frames) == sorted(f["file_path"] for f in json.loads(before)["frames"])
    true_mask = {Path(f["file_path"]).name: capture["scene"] / f["instance_mask_path"] for f in truth["frames"]}
    photo_of = {v: k for k, v in capture["names"].items()}
    ids = sorted(classes)
    inter = np.zeros((len(clicks), len(ids)))
    union = np.zeros((len(clicks), len(ids)))
    for frame in frames:
        ours = cv2.imread(str(data / frame["instance_mask_path"]), cv2.IMREAD_UNCHANGED).astype(np.int64)
        gt = cv2.imread(str(true_mask[photo_of[frame["file_path"]]]), cv2.IMREAD_UNCHANGED)
        gt = cv2.resize(gt, ours.shape[::-1], interpolation=cv2.INTER_NEAREST).astype(np.int64)
        for k in range(len(clicks)):
            for j, gt_id in enumerate(ids):
                a, b = ours == k + 1, gt == gt_id
                inter[k, j] += (a & b).sum()
                union[k, j] += (a | b).sum()
    iou = inter / np.maximum(union, 1)
    print(f"mask IoU per click (rows) against each true crate (columns): {np.round(iou, 3).tolist()}")
    # each mask is the crate that was clicked, not another; at 64x48 from a 300-step base on COLMAP's sparse points
    # the masks are coarse. On one reconstruction this run is repeatable (the same matrix twice), but COLMAP's is not:
    # its CPU matches differ from run to run even with one matching thread and a fixed --random_seed (COLMAP 3.8).
    # Over 15 runs, each with its own COLMAP run, the clicked crate scored 0.173-0.613 and another crate at most
    # 0.074, at least 4.3 times less than the clicked one in every row (also in the 4 runs with a click left out:
    # that click still seeds the split, so its crate stays background instead of going to a clicked neighbour's
    # mask). Of 18 runs later, one gave a neighbour 0.071 of a lost click's crate against its own 0.208 (2.9 times):
    # the lost crate's foot, in the floor's band, was reclaimed by colour into the neighbour's instance; what a lost
    # click wins now holds its foot. That capture again and 8 new runs two at a time: the clicked crate 0.193-0.578,
    # another at most 0.034, at least 5.7 times less. A mask of the wrong crate fails the argmax, an empty one the
    # floor. A click left out at the masks step has no mask: its row is 0.
    own = [iou[k, ids.index(clicks[k]["id"])] for k in masked]
    others = [max(np.delete(iou[k], ids.index(clicks[k]["id"]))) for k in masked]
    assert [ids[j] for j in iou[masked].argmax(axis=1)] == [clicks[k]["id"] for k in masked], iou
    assert min(own) > 0.1 and all(o > 3 * x for o, x in zip(own, others)), iou
    assert not iou[sorted(no_mask)].any(), iou
