"""Synthetic scenes: the ground truth must be consistent, deterministic and loadable by nerfstudio."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from sim_checks import check_clicks_inside_instances, mask_iou_against_meshes, read_image

from splatreplace_ns.tools.sim import PRESETS, load_scene_meshes, make_scene

SMALL = {  # preset → (resolution, n_train, n_test): small enough for unit tests
    "tiny": ((64, 48), 8, 4),
    "office": ((96, 72), 12, 4),
    "temple": ((96, 72), 8, 3),
    "chess": ((96, 72), 8, 3),
    "lighting": ((96, 72), 8, 3),
}


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("sim")
    out = {}
    for name, (res, n_train, n_test) in SMALL.items():
        out[name] = make_scene(name, root / name, res=res, n_train=n_train, n_test=n_test, seed=0)
    return out


def _meta(path: Path) -> dict:
    return json.loads(path.read_text())


@pytest.mark.parametrize("name", list(SMALL))
def test_files_and_format(datasets, name):
    path = datasets[name]
    meta = _meta(path)
    root = path.parent
    res, n_train, n_test = SMALL[name]
    assert meta["camera_model"] in ("PINHOLE", "OPENCV")
    assert (meta["w"], meta["h"]) == res
    assert meta["depth_unit_scale_factor"] == 0.001
    # depth 0 is a ray that hits nothing: the sky outdoors (supervised as far), the void above an indoor room's walls
    assert meta.get("depth_zero") == ("far" if PRESETS[name].open_sky else None)
    assert (root / meta["ply_file_path"]).exists()
    assert (root / "contact_sheet.png").exists()
    assert len(meta["frames"]) == n_train + n_test
    assert len(meta["train_filenames"]) == n_train and len(meta["test_filenames"]) == n_test
    assert meta["val_filenames"] == meta["test_filenames"]
    assert not set(meta["train_filenames"]) & set(meta["test_filenames"])
    ids = [inst["id"] for inst in meta["instances"]]
    assert len(set(ids)) == len(ids) and min(ids) >= 1
    for inst in meta["instances"]:
        assert inst["symmetry"] == "none" or inst["symmetry"].startswith("rot_z:")
        t = np.asarray(inst["transform_matrix"])
        assert np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(t[:3, :3]), 1.0)
        assert np.allclose(t[3], [0, 0, 0, 1])
    for frame in meta["frames"]:
        rgb = read_image(root / frame["file_path"])
        mask = read_image(root / frame["instance_mask_path"])
        depth = read_image(root / frame["depth_file_path"])
        assert rgb.shape == (res[1], res[0], 3) and rgb.dtype == np.uint8
        assert mask.shape == res[::-1] and mask.dtype == np.uint16
        assert depth.shape == res[::-1] and depth.dtype == np.uint16
        assert set(np.unique(mask).tolist()) <= set(ids) | {0}, "mask ids must be listed in instances"
        assert (mask == 0).any(), "there must be background to segment against"
        assert (depth[mask > 0] > 0).all(), "instance pixels have depth"


@pytest.mark.parametrize("name", list(SMALL))
def test_ground_truth_geometry_matches_masks_and_depth(datasets, name):
    """Posed GT meshes, cast with each camera of transforms.json, reproduce masks (IoU >= 0.98) and depth."""
    for k, iou in mask_iou_against_meshes(datasets[name]).items():
        assert iou >= 0.98, f"instance {k}: IoU {iou:.3f}"


@pytest.mark.parametrize("name", list(SMALL))
def test_clicks_inside_instances(datasets, name):
    check_clicks_inside_instances(datasets[name])


def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes(tmp_path):
    a = make_scene("tiny", tmp_path / "a", seed=3, workers=1)
    b = make_scene("tiny", tmp_path / "b", seed=3, workers=2)  # spreading frames over processes changes nothing
    ta, tb = _tree_bytes(a.parent), _tree_bytes(b.parent)
    assert ta.keys() == tb.keys() and len(ta) > 30
    assert all(ta[k] == tb[k] for k in ta), [k for k in ta if ta[k] != tb[k]]
    c = make_scene("tiny", tmp_path / "c", seed=4)
    assert c.read_bytes() != a.read_bytes()


def test_rewrite_same_folder_and_refuse_foreign(tmp_path):
    first = make_scene("tiny", tmp_path / "d", n_train=5, n_test=2)
    make_scene("tiny", tmp_path / "d", n_train=4, n_test=2)
    assert len(list((first.parent / "images").iterdir())) == 6, "stale frames of the earlier run are removed"
    foreign = tmp_path / "e"
    (foreign / "images").mkdir(parents=True)
    (foreign / "images" / "keep.png").write_bytes(b"x")
    with pytest.raises(FileExistsError):
        make_scene("tiny", foreign)
    with pytest.raises(ValueError, match="unknown preset"):
        make_scene("nope", tmp_path / "f")
    with pytest.raises(ValueError, match="320x240"):
        make_scene("tiny", tmp_path / "f", res="big")


def test_loads_through_nerfstudio_parser(datasets):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    path = datasets["tiny"]
    meta = _meta(path)
    parser = NerfstudioDataParserConfig(data=path.parent, load_3D_points=True).setup()
    train = parser.get_dataparser_outputs("train")
    test = parser.get_dataparser_outputs("test")
    assert len(train.image_filenames) == len(meta["train_filenames"])
    assert len(test.image_filenames) == len(meta["test_filenames"])
    assert int(train.cameras.width[0]) == meta["w"] and int(train.cameras.height[0]) == meta["h"]
    assert len(train.metadata["depth_filenames"]) == len(meta["train_filenames"])
    pts = train.metadata["points3D_xyz"]
    ply = o3d.io.read_point_cloud(str(path.parent / meta["ply_file_path"]))
    assert pts.shape == (len(ply.points), 3) and len(ply.points) >= 200
    assert train.metadata["points3D_rgb"].shape == (len(ply.points), 3)


def test_points_are_noisy_surface_samples(datasets):
    path = datasets["tiny"]
    meta = _meta(path)
    ply = o3d.io.read_point_cloud(str(path.parent / meta["ply_file_path"]))
    xyz = np.asarray(ply.points)
    assert len(np.unique(np.asarray(ply.colors), axis=0)) > 50, "coloured points"
    meshes = load_scene_meshes(path)
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes.values():
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    near_instances = scene.compute_distance(o3d.core.Tensor(xyz.astype(np.float32))).numpy() < 0.03
    on_floor = np.abs(xyz[:, 2]) < 0.03
    assert 0.1 < near_instances.mean() < 0.9, "points on the objects and on the background"
    assert (near_instances | on_floor | (xyz[:, 1] > 2.4)).mean() > 0.97, "points lie on surfaces (within noise)"
    assert np.abs(xyz[on_floor & ~near_instances, 2]).mean() > 1e-4, "positions carry noise"


def test_mean_test_distance_reflects_far_test_views(datasets):
    dist = {n: _meta(p)["sim"]["mean_test_to_train_distance"] for n, p in datasets.items()}
    assert PRESETS["temple"].effects.far_test_views and not PRESETS["office"].effects.far_test_views
    assert dist["temple"] > 5.0 > dist["office"]


def _local_azimuth_gaps(path: Path, cls: str, min_pixels: int = 20) -> tuple[list[float], float]:
    """Largest unseen azimuth range (degrees, object frame) per instance of a class, and for their union."""
    meta = _meta(path)
    train = set(meta["train_filenames"])
    seen: dict[int, list[float]] = {}
    for frame in meta["frames"]:
        if frame["file_path"] not in train:
            continue
        mask = read_image(path.parent / frame["instance_mask_path"])
        centre = np.asarray(frame["transform_matrix"])[:3, 3]
        for inst in meta["instances"]:
            if inst["class"] == cls and (mask == inst["id"]).sum() >= min_pixels:
                t = np.asarray(inst["transform_matrix"])
                local = t[:3, :3].T @ (centre - t[:3, 3])
                seen.setdefault(inst["id"], []).append(math.degrees(math.atan2(local[1], local[0])) % 360.0)

    def gap(az: list[float]) -> float:
        a = np.sort(az)
        return float(np.diff(np.r_[a, a[0] + 360.0]).max())

    return [gap(a) for a in seen.values()], gap([x for a in seen.values() for x in a])


@pytest.mark.parametrize("name, cls", [("office", "chair"), ("temple", "pillar")])
def test_unseen_sides_are_shown_by_other_copies(datasets, name, cls):
    """Coverage imbalance: every copy misses a wide range of directions, the copies together miss little."""
    per_instance, union = _local_azimuth_gaps(datasets[name], cls)
    assert min(per_instance) > 100.0, per_instance
    assert union < 0.5 * min(per_instance), (union, per_instance)


def test_scene_from_an_older_generator_is_made_again(tmp_path):
    """A cached scene whose transforms.json an older generator wrote (version 1: an open-sky scene without
    ``depth_zero``) is no longer current, and the benchmarks' cache writes it again; a current one is reused
    untouched."""
    from splatreplace_ns.tools.bench.scenes import cached_scene
    from splatreplace_ns.tools.sim import is_current_scene

    data = cached_scene("temple", "48x36", 8, 1, tmp_path)
    assert is_current_scene(data)
    meta_path = data / "transforms.json"
    stamp = meta_path.stat().st_mtime_ns
    assert cached_scene("temple", "48x36", 8, 1, tmp_path) == data and meta_path.stat().st_mtime_ns == stamp
    meta = _meta(meta_path)
    meta["sim"]["generator_version"] = 1
    del meta["depth_zero"]
    meta_path.write_text(json.dumps(meta))
    assert not is_current_scene(data) and not is_current_scene(tmp_path / "missing")
    cached_scene("temple", "48x36", 8, 1, tmp_path)
    assert is_current_scene(data) and _meta(meta_path)["depth_zero"] == "far"


def test_click_in_the_middle_of_a_column_not_at_its_capital():
    """A column: a 5 px shaft with 9 px wide plinth and capital, cut by the top edge of the frame. Its deepest
    pixels tie along the plinth and capital; a person clicks the middle of the shaft."""
    from splatreplace_ns.tools.sim.writer import choose_click_view, click_candidates

    ids = np.zeros((60, 40), np.uint16)
    ids[0:6, 10:19] = 3  # capital at the frame's top edge
    ids[6:54, 12:17] = 3  # shaft
    ids[54:60, 10:19] = 3  # plinth
    dist, area, u, v = click_candidates(ids)[3]
    assert area == int((ids == 3).sum()) and dist >= 2.5
    assert 12 <= u < 17 and 20 <= v <= 40, (u, v)  # on the shaft, near its middle
    inside = np.pad((ids == 3).astype(np.uint8), 1)
    assert cv2.distanceTransform(inside, cv2.DIST_L2, 5)[v + 1, u + 1] >= max(0.5 * dist, 2.0)
    # views: equally deep ones → the one that shows most of the instance; a clearly deeper one wins
    assert choose_click_view({0: (3.0, 100, 1, 1), 4: (3.2, 400, 2, 2), 7: (2.0, 900, 3, 3)}) == 4
    assert choose_click_view({0: (6.0, 100, 1, 1), 4: (3.2, 400, 2, 2)}) == 0
