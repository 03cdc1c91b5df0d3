"""SplatReplaceDataManager on CPU: images, depth, instance masks, instances, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from scenes import OPENCV_TO_OPENGL, look_at_cv
from splatreplace_ns.datamanager.datamanager import SplatReplaceDataManagerConfig
from splatreplace_ns.datamanager.dataparser import normalise_object_pose
from splatreplace_ns.datamanager.errors import DatasetFormatError

W, H = 32, 24


def write_dataset(root: Path, n: int = 6, mask_ids=(1, 2), depth_mm: int = 2500) -> dict:
    rng = np.random.default_rng(0)
    for sub in ("images", "masks", "depth"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        angle = 2 * np.pi * i / n
        c2w = look_at_cv(np.array([3 * np.cos(angle), 3 * np.sin(angle), 1.0]), np.zeros(3))
        cv2.imwrite(str(root / f"images/{i:04d}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        mask = np.zeros((H, W), np.uint16)
        mask[2:8, 2:10] = mask_ids[0]
        mask[12:20, 14:30] = mask_ids[1]
        cv2.imwrite(str(root / f"masks/{i:04d}.png"), mask)
        cv2.imwrite(str(root / f"depth/{i:04d}.png"), np.full((H, W), depth_mm, np.uint16))
        frames.append({
            "file_path": f"images/{i:04d}.png",
            "instance_mask_path": f"masks/{i:04d}.png",
            "depth_file_path": f"depth/{i:04d}.png",
            "transform_matrix": (c2w @ OPENCV_TO_OPENGL).tolist(),
        })
    pose = np.eye(4)
    pose[:3, 3] = [0.5, -0.25, 0.0]
    names = [f["file_path"] for f in frames]
    meta = {
        "camera_model": "PINHOLE", "fl_x": 30.0, "fl_y": 30.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H,
        "depth_unit_scale_factor": 0.001,
        "frames": frames,
        "instances": [
            {"id": 1, "class": "chair", "transform_matrix": pose.tolist(), "symmetry": "none"},
            {"id": 2, "class": "chair", "symmetry": "rot_z:4"},
        ],
        "train_filenames": names[:4], "val_filenames": names[4:], "test_filenames": names[4:],
    }
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def setup_dm(root: Path, cache_images: str = "cpu"):
    config = SplatReplaceDataManagerConfig(cache_images=cache_images)
    config.data = root
    config.dataparser.load_3D_points = False
    return config.setup(device="cpu", test_mode="val")


def test_cpu_datamanager_loads_masks_depth_and_instances(tmp_path):
    meta = write_dataset(tmp_path)
    dm = setup_dm(tmp_path, cache_images="cpu")  # nerfstudio's own path would call pin_memory() here
    camera, batch = dm.next_train(0)
    assert camera.metadata["cam_idx"] in range(4)
    assert batch["image"].shape == (H, W, 3)
    assert batch["instance_mask"].shape == (H, W, 1) and batch["instance_mask"].dtype == torch.int32
    assert set(torch.unique(batch["instance_mask"]).tolist()) == {0, 1, 2}
    # depth is in the normalised frame: millimetres → metres → dataparser scale
    scale = dm.train_dataparser_outputs.dataparser_scale
    assert torch.allclose(batch["depth"], torch.full((H, W, 1), 2.5 * scale), rtol=1e-5)
    assert len(dm.eval_dataset) == 2

    instances = dm.train_dataparser_outputs.metadata["instances"]
    assert [i["id"] for i in instances] == [1, 2] and instances[1]["symmetry"] == "rot_z:4"
    # the ground-truth pose follows the cameras into the normalised frame
    transform = dm.train_dataparser_outputs.dataparser_transform.numpy()
    origin = np.array(meta["instances"][0]["transform_matrix"])[:3, 3]
    expected = scale * (transform[:, :3] @ origin + transform[:, 3])
    assert np.allclose(instances[0]["transform_matrix"][:3, 3].numpy(), expected, atol=1e-5)
    assert "transform_matrix" not in instances[1]


def test_a_masks_base_trains_on_every_frame_whatever_the_split(tmp_path):
    """``train_on_every_frame`` (the base model ``splatreplace masks`` trains) ignores the split lists: all six
    frames train, in file order, masks and all; without it the dataset's split holds."""
    meta = write_dataset(tmp_path)
    config = SplatReplaceDataManagerConfig(cache_images="cpu")
    config.data = tmp_path
    config.dataparser.load_3D_points = False
    config.dataparser.train_on_every_frame = True
    dm = config.setup(device="cpu", test_mode="val")
    names = [Path(p).name for p in dm.train_dataparser_outputs.image_filenames]
    assert names == [Path(f["file_path"]).name for f in meta["frames"]]
    assert len(dm.train_dataparser_outputs.metadata["instance_mask_filenames"]) == 6
    assert len(setup_dm(tmp_path).train_dataset) == 4


@pytest.mark.parametrize("depth_zero", [None, "unknown", "far"])
def test_depth_zero_is_unknown_unless_the_dataset_says_far(tmp_path, depth_zero):
    """A frame's depth 0 stays 0 (a hole: unsupervised) unless transforms.json says ``"depth_zero": "far"``,
    where it is the sky, loaded as +inf (inverse depth 0); measured depths are unchanged either way."""
    meta = write_dataset(tmp_path)
    if depth_zero is not None:
        meta["depth_zero"] = depth_zero
        (tmp_path / "transforms.json").write_text(json.dumps(meta))
    for i in range(6):  # the top rows of every frame see no surface
        depth = np.full((H, W), 2500, np.uint16)
        depth[:5] = 0
        cv2.imwrite(str(tmp_path / f"depth/{i:04d}.png"), depth)
    dm = setup_dm(tmp_path)
    _, batch = dm.next_train(0)
    scale = dm.train_dataparser_outputs.dataparser_scale
    assert torch.allclose(batch["depth"][5:], torch.full((H - 5, W, 1), 2.5 * scale), rtol=1e-5)
    sky = batch["depth"][:5]
    if depth_zero == "far":
        assert torch.isinf(sky).all() and (sky > 0).all()
    else:
        assert (sky == 0).all()


def test_bad_depth_zero_is_named(tmp_path):
    meta = write_dataset(tmp_path)
    meta["depth_zero"] = "sky"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetFormatError, match=r"transforms\.json: depth_zero: Input should be 'unknown' or 'far' \(got 'sky'\)"):
        setup_dm(tmp_path)


def test_normalise_object_pose_composes_similarity():
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    transform = np.hstack([np.eye(3)[[1, 0, 2]], np.array([[0.5], [0.0], [-1.0]])])
    out = normalise_object_pose(pose, transform, 0.5)
    assert np.allclose(out[:3, 3], 0.5 * (np.array([2.0, 1.0, 3.0]) + [0.5, 0.0, -1.0]))
    assert np.allclose(out[:3, :3], 0.5 * transform[:, :3])


def test_unknown_instance_id_is_named(tmp_path):
    write_dataset(tmp_path, mask_ids=(1, 7))
    with pytest.raises(DatasetFormatError, match=r"masks/0000\.png.*ids \[7\]"):
        setup_dm(tmp_path).next_train(0)


def test_mask_size_mismatch_is_named(tmp_path):
    write_dataset(tmp_path)
    cv2.imwrite(str(tmp_path / "masks/0001.png"), np.zeros((H // 2, W), np.uint16))  # not the image's shape
    with pytest.raises(DatasetFormatError, match=r"masks/0001\.png: size 32x12 is not its image's 32x24"):
        setup_dm(tmp_path)  # found before training, not at the first step that reads the mask


def test_a_mask_of_the_image_at_another_scale_is_resized_to_it(tmp_path):
    """A mask at twice the image's size (made from the full-size files while nerfstudio reads images_2/, or the
    other way round) is the same picture: it loads, resized with the nearest label, never a blend of two ids."""
    from splatreplace_ns.datamanager.dataset import read_instance_mask

    labels = np.random.default_rng(0).integers(0, 3, size=(H, W)).astype(np.uint16)
    big = np.kron(labels, np.ones((2, 2), np.uint16))  # every pixel of the image as a 2x2 block
    cv2.imwrite(str(tmp_path / "big.png"), big)
    assert np.array_equal(read_instance_mask(tmp_path / "big.png", H, W)[..., 0].numpy(), labels)
    small = read_instance_mask(tmp_path / "big.png", H // 2, W // 2)[..., 0].numpy()
    assert small.shape == (H // 2, W // 2) and set(np.unique(small)) <= {0, 1, 2}


def test_resized_pixel_keeps_the_point_of_the_picture():
    from splatreplace_ns.datamanager.clicks import resized_pixel

    # pixels 0 and 1 of the full-size image are the two halves of pixel 0 at half size
    assert resized_pixel((0, 1), 0.5) == (-0.25, 0.25)
    assert resized_pixel((3.5, 0.5), 0.5) == (1.5, 0.0)
    assert resized_pixel(resized_pixel((7.3, 2.2), 0.25), 4.0) == pytest.approx((7.3, 2.2))


def test_missing_mask_is_named(tmp_path):
    write_dataset(tmp_path)
    (tmp_path / "masks/0002.png").unlink()
    with pytest.raises(DatasetFormatError, match=r"masks/0002\.png: instance mask file not found"):
        setup_dm(tmp_path).next_train(0)


def write_distorted_capture(root: Path, model: str) -> tuple:
    """The small dataset with lens distortion (what ns-process-data writes by default), each image a colour code of
    its mask (red = 60 × id) and depth (green = (depth mm − 1000) / 2). Returns (width, height, one mask)."""
    Wd, Hd = 96, 72
    write_dataset(root)
    meta = json.loads((root / "transforms.json").read_text())
    yy, xx = np.mgrid[0:Hd, 0:Wd]
    mask = np.zeros((Hd, Wd), np.uint16)
    mask[10:40, 8:50] = 1
    mask[30:66, 55:90] = 2
    mask[44:60, 20:40] = 3
    depth_mm = (1000 + 20 * (xx // 12) + 100 * (yy // 18)).astype(np.uint16)  # blocks, so nearest is exact
    image = np.stack([np.zeros_like(mask), (depth_mm - 1000) // 2, mask * 60], axis=-1).astype(np.uint8)  # BGR
    for frame in meta["frames"]:
        cv2.imwrite(str(root / frame["file_path"]), image)
        cv2.imwrite(str(root / frame["instance_mask_path"]), mask)
        cv2.imwrite(str(root / frame["depth_file_path"]), depth_mm)
    meta["instances"].append({"id": 3, "class": "table"})
    focal = 80.0 if model == "OPENCV" else 60.0
    meta.update(camera_model=model, w=Wd, h=Hd, fl_x=focal, fl_y=focal, cx=Wd / 2 + 1.5, cy=Hd / 2 - 2.0)
    meta.update({"k1": -0.4, "k2": 0.12, "p1": 0.004, "p2": -0.003} if model == "OPENCV" else
                {"k1": -0.3, "k2": 0.05, "k3": 0.0, "k4": 0.0})  # moves pixels by 10 px on average
    (root / "transforms.json").write_text(json.dumps(meta))
    return Wd, Hd, mask


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_masks_and_depth_follow_the_images_through_undistortion(tmp_path, model):
    """nerfstudio undistorts (and crops) the cached images of a distorted capture; the instance masks and depths
    must come out on the same pixels, which the undistorted colour codes say."""
    Wd, Hd, _ = write_distorted_capture(tmp_path, model)
    dm = setup_dm(tmp_path)
    scale = dm.train_dataparser_outputs.dataparser_scale
    for data in dm.cached_train:
        image, mask, depth = data["image"].numpy(), data["instance_mask"][..., 0].numpy(), data["depth"][..., 0].numpy()
        assert mask.shape == depth.shape == image.shape[:2]
        if model == "OPENCV":
            assert image.shape[:2] != (Hd, Wd)  # cropped to the valid region: the case that broke before
        # the linearly interpolated image holds an exact code except on the blocks' edges
        code = image[..., 0].astype(int)
        exact = np.isin(code, [0, 60, 120, 180])
        assert exact.mean() > 0.8
        assert (mask[exact] * 60 == code[exact]).mean() > 0.995
        green = image[..., 1].astype(np.float64)
        kernel = np.ones((3, 3), np.uint8)
        flat = (cv2.dilate(image[..., 1], kernel) == cv2.erode(image[..., 1], kernel)) & (depth > 0)  # constant around
        expected = (1000 + 2 * green[flat]) * 1e-3 * scale
        agree = np.isclose(depth[flat], expected, rtol=1e-3)
        assert agree.mean() > 0.99, (agree.mean(), depth[flat][~agree][:5], expected[~agree][:5])
        assert set(np.unique(mask)) <= {0, 1, 2, 3}


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_masks_scored_against_renders_are_read_where_the_cameras_render(tmp_path, model):
    """Evaluation compares renders with masks: each view's mask (train and eval split) comes out on the pixels of
    its undistorted, cropped image, and so does a reference mask given over the captured picture (the truth of a
    benchmark), also at half its size."""
    Wd, Hd, mask = write_distorted_capture(tmp_path, model)
    dm = setup_dm(tmp_path)
    half = cv2.resize(mask, (Wd // 2, Hd // 2), interpolation=cv2.INTER_NEAREST)
    for dataset, cached in ((dm.train_dataset, dm.cached_train), (dm.eval_dataset, dm.cached_eval)):
        assert len(dataset) > 0
        for idx in range(len(dataset)):
            code = cached[idx]["image"].numpy()[..., 0].astype(int)
            exact = np.isin(code, [0, 60, 120, 180])
            ours = dm.instance_mask_as_rendered(dataset, idx).numpy()
            assert ours.shape == code.shape and exact.mean() > 0.8
            assert (ours[exact] * 60 == code[exact]).mean() > 0.995
            assert np.array_equal(dm.mask_as_rendered(dataset, idx, mask).numpy(), ours)
            from_half = dm.mask_as_rendered(dataset, idx, half).numpy()
            assert from_half.shape == code.shape and (from_half[exact] * 60 == code[exact]).mean() > 0.9
    # a reference mask of an eval view scored first, before anything read the eval images (as a benchmark does
    # right after segmentation): the same pixels
    fresh = setup_dm(tmp_path)
    assert np.array_equal(fresh.mask_as_rendered(fresh.eval_dataset, 0, mask).numpy(),
                          dm.mask_as_rendered(dm.eval_dataset, 0, mask).numpy())
    # the captured mask at the same index is another part of the picture: what evaluation read before
    stored = dm.eval_dataset.get_data(0, image_type="uint8")["instance_mask"][..., 0].numpy()
    assert stored.shape != code.shape or (stored[exact] * 60 == code[exact]).mean() < 0.97


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_a_click_on_the_image_file_lands_on_the_same_object_in_the_undistorted_image(tmp_path, model):
    """clicks.json gives pixels of the image files; the segmentation stage reads features of the undistorted,
    cropped training image. Every pixel well inside an object of the file maps onto that object there."""
    _, _, mask = write_distorted_capture(tmp_path, model)
    dm = setup_dm(tmp_path)
    code = dm.cached_train[0]["image"].numpy()[..., 0].astype(int)
    inner = cv2.erode((mask > 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0  # 3 px from every edge
    hits, inside, shifts = 0, 0, []
    for row, col in zip(*np.nonzero(inner)):
        u, v = dm.train_pixel(0, (float(col), float(row)))
        shifts.append(np.hypot(u - col, v - row))
        r, c = int(np.floor(v + 0.5)), int(np.floor(u + 0.5))
        if 0 <= r < code.shape[0] and 0 <= c < code.shape[1]:  # a fisheye's far corners are cropped away
            inside += 1
            hits += code[r, c] == 60 * mask[row, col]
    assert inside > 0.9 * len(shifts) and hits >= 0.995 * inside, (hits, inside)
    assert np.mean(shifts) > 2.0  # the same pixel index would often be another place of the object, or another object


def test_pixels_map_between_a_distorted_image_and_a_pinhole_one():
    """Oracle: OpenCV's own projection of 3D points with and without the lens."""
    from splatreplace_ns.datamanager.undistort import captured_to_undistorted_pixel, undistorted_to_captured_pixel

    rng = np.random.default_rng(0)
    K = np.array([[80.0, 0, 49.5], [0, 80.0, 34.0], [0, 0, 1]])
    K_new = np.array([[70.0, 0, 44.0], [0, 70.0, 30.0], [0, 0, 1]])
    cv = lambda M: M - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # noqa: E731  pixel centres at integers
    points = np.c_[rng.uniform(-0.5, 0.5, (20, 2)), np.ones(20)]
    distortion = np.array([-0.2, 0.05, 0.01, 0.0, 0.004, -0.003])  # nerfstudio order k1 k2 k3 k4 p1 p2
    coeffs = np.array([-0.2, 0.05, 0.004, -0.003, 0.01])
    captured = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cv(K), coeffs)[0].reshape(-1, 2)
    pinhole = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cv(K_new), None)[0].reshape(-1, 2)
    for xy, expected in zip(captured, pinhole):
        assert np.allclose(captured_to_undistorted_pixel(tuple(xy), 1, K, distortion, K_new), expected, atol=1e-3)
        assert np.allclose(undistorted_to_captured_pixel(tuple(expected), 1, K_new, distortion, K), xy, atol=1e-3)
    fisheye = np.array([-0.3, 0.05, 0.0, 0.0, 0.0, 0.0])
    captured = cv2.fisheye.projectPoints(points[:, None], np.zeros(3), np.zeros(3), cv(K), fisheye[:4])[0].reshape(-1, 2)
    for xy, expected in zip(captured, pinhole):
        assert np.allclose(captured_to_undistorted_pixel(tuple(xy), 2, K, fisheye, K_new), expected, atol=1e-3)
        assert np.allclose(undistorted_to_captured_pixel(tuple(expected), 2, K_new, fisheye, K), xy, atol=1e-3)
    # no distortion: only the intrinsics change
    assert np.allclose(captured_to_undistorted_pixel((10.0, 20.0), 1, K, np.zeros(6), K), (10.0, 20.0))


@pytest.mark.parametrize("how", ["none", "applied_transform", "colmap_folder"])
def test_frame_cameras_are_the_cameras_nerfstudio_trains_with(tmp_path, how):
    """The cameras every stage renders from transforms.json (masks, clicks, evaluation) equal the datamanager's,
    also when the poses were saved through an ``applied_transform`` (``ns-process-data`` writes one) or the
    folder holds ``colmap/sparse/0`` (nerfstudio then assumes its older COLMAP convention); the ground-truth
    object poses follow the same transform."""
    from splatreplace_ns.instances.frames import frame_cameras

    meta = write_dataset(tmp_path)
    if how != "none":
        applied = np.eye(4)
        applied[:3] = np.array([[0.0, 1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, -1.0, 0.1]])
        if how == "applied_transform":
            meta["applied_transform"] = applied[:3].tolist()
        else:
            applied[:3, 3] = 0.0  # the convention nerfstudio assumes has no translation
            (tmp_path / "colmap" / "sparse" / "0").mkdir(parents=True)
        for frame in meta["frames"]:  # the saved poses are the original ones with applied_transform applied
            frame["transform_matrix"] = (applied @ np.asarray(frame["transform_matrix"])).tolist()
        for inst in meta["instances"]:
            if "transform_matrix" in inst:
                inst["transform_matrix"] = (applied @ np.asarray(inst["transform_matrix"])).tolist()
        (tmp_path / "transforms.json").write_text(json.dumps(meta))
    dm = setup_dm(tmp_path)
    outputs = dm.train_dataparser_outputs
    frames = frame_cameras(tmp_path / "transforms.json", outputs.dataparser_transform, outputs.dataparser_scale)
    for index, path in enumerate(dm.train_dataset.image_filenames):
        k = frames.index_of(str(Path(path).relative_to(tmp_path)), "test")
        assert torch.allclose(frames.cameras.camera_to_worlds[k], dm.train_dataset.cameras.camera_to_worlds[index],
                              atol=1e-5), (how, path)
    # the object seen from a camera does not depend on how the poses were saved
    reference = tmp_path.parent / f"{tmp_path.name}_plain"
    write_dataset(reference)

    def object_in_first_camera(dm) -> torch.Tensor:
        c2w = torch.eye(4)
        c2w[:3] = dm.train_dataset.cameras.camera_to_worlds[0]
        pose = dm.train_dataparser_outputs.metadata["instances"][0]["transform_matrix"]
        return torch.linalg.inv(c2w) @ pose

    assert torch.allclose(object_in_first_camera(dm), object_in_first_camera(setup_dm(reference)), atol=1e-5), how
