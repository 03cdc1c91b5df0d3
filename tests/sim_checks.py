"""Ground-truth checks shared by the tests of the named presets and of the random scenes."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from splatreplace_ns.tools.sim import load_scene_meshes


def read_image(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def camera_rays(meta: dict, frame: dict) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre rays of a frame from transforms.json alone (nerfstudio / OpenGL convention)."""
    w, h = meta["w"], meta["h"]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d_cam = np.stack([(u - meta["cx"]) / meta["fl_x"], -(v - meta["cy"]) / meta["fl_y"], -np.ones_like(u)], -1)
    c2w = np.asarray(frame["transform_matrix"])
    d = d_cam.reshape(-1, 3) @ c2w[:3, :3].T  # z-component along the optical axis is 1: t is z-depth
    o = np.broadcast_to(c2w[:3, 3], d.shape)
    return o, d


def mask_iou_against_meshes(path: Path) -> dict[int, float]:
    """Cast the posed ground-truth class meshes with every camera of a dataset's transforms.json and compare with
    its instance masks. Asserts that the depth PNGs match the geometry where both see the same instance.

    Returns:
        {instance id: IoU of its masks against the ray-cast meshes over all views}.
    """
    meta = json.loads(Path(path).read_text())
    meshes = load_scene_meshes(path)
    scene = o3d.t.geometry.RaycastingScene()
    id_of_geometry = []
    for k, mesh in meshes.items():
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        id_of_geometry.append(k)
    id_of_geometry = np.asarray(id_of_geometry)
    inter = {k: 0 for k in meshes}
    union = {k: 0 for k in meshes}
    for frame in meta["frames"]:
        mask = read_image(path.parent / frame["instance_mask_path"]).ravel()
        depth = read_image(path.parent / frame["depth_file_path"]).ravel() * meta["depth_unit_scale_factor"]
        o, d = camera_rays(meta, frame)
        hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))
        t = hit["t_hit"].numpy()
        gid = hit["geometry_ids"].numpy()
        ok = np.isfinite(t)
        # an instance is visible where it is hit and nothing of the environment lies in front of it
        visible = ok & (t <= depth + 2e-3)
        pred = np.zeros_like(mask)
        pred[visible] = id_of_geometry[gid[visible]]
        for k in meshes:
            a, b = pred == k, mask == k
            inter[k] += int((a & b).sum())
            union[k] += int((a | b).sum())
        both = (pred == mask) & (mask > 0)
        assert both.any() or not (mask > 0).any()
        assert np.abs(t[both] - depth[both]).max(initial=0.0) <= 1e-3, "depth PNG matches the ray-cast geometry"
    return {k: inter[k] / union[k] if union[k] else 0.0 for k in meshes}


def _deepest_inside(meta: dict, root: Path, instance: int) -> float:
    """Largest distance (px) from an instance's outline to a pixel of it, over the training views."""
    deepest = 0.0
    for frame in meta["frames"]:
        if frame["file_path"] in meta["train_filenames"]:
            inside = np.pad((read_image(root / frame["instance_mask_path"]) == instance).astype(np.uint8), 1)
            deepest = max(deepest, float(cv2.distanceTransform(inside, cv2.DIST_L2, 5).max()))
    return deepest


def check_clicks_inside_instances(path: Path) -> None:
    """Every instance has one click, in a training view, on its own pixels and well inside its outline (at least
    1.5 px from it, or as deep as the instance gets in any training view when it is thinner than that)."""
    meta = json.loads(Path(path).read_text())
    clicks = json.loads((path.parent / "clicks.json").read_text())
    classes = {inst["id"]: inst["class"] for inst in meta["instances"]}
    assert sorted(c["id"] for c in clicks) == sorted(classes)
    mask_of = {f["file_path"]: f["instance_mask_path"] for f in meta["frames"]}
    for c in clicks:
        assert c["file_path"] in meta["train_filenames"]
        assert c["class"] == classes[c["id"]]
        u, v = c["xy"]
        mask = read_image(path.parent / mask_of[c["file_path"]])
        assert 0 <= u < meta["w"] and 0 <= v < meta["h"]
        assert mask[v, u] == c["id"], "click on its instance"
        inside = np.pad((mask == c["id"]).astype(np.uint8), 1)
        depth = cv2.distanceTransform(inside, cv2.DIST_L2, 5)[v + 1, u + 1]
        assert depth >= 1.5 or depth >= _deepest_inside(meta, path.parent, c["id"]) - 0.5, "click deep inside the mask"
