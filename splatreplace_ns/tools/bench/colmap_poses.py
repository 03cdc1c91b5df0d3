"""The user's regime with COLMAP's camera poses (``bench suite --inputs user --poses colmap``).

A user's capture has no true camera poses either: ``ns-process-data images`` poses the photos with COLMAP. This
regime gives both methods what that leaves, for a suite scene:

1. the *photos*: the scene rendered again from the same cameras at ``PHOTO_SCALE`` times its size (a user's photos
   are large; nerfstudio trains on smaller copies), training views only, go to ``ns-process-data images``
   (COLMAP, CPU SIFT, exhaustive matching, one pinhole camera), which poses them, estimates the intrinsics and
   triangulates the sparse cloud. COLMAP may pose none of them: then the regime has no dataset and says why;
2. the dataset folder ``<scene>_user-colmap`` trains on the scene's own images at their size (those every other
   regime trains on) with COLMAP's poses and intrinsics (scaled back from the photos), COLMAP's sparse cloud and
   the clicks; a training view
   COLMAP did not pose is left out, and a click on it moves to the posed view that shows its instance largest
   (``capture.capture_clicks``);
3. the test views keep their true images, evaluation masks and intrinsics; their true cameras are moved into
   COLMAP's frame by the similarity that best maps the true centres of the posed training cameras onto COLMAP's
   (the ground truth only places what is scored, as ``bench capture`` does). The true instance poses move the
   same way, to score registration.

The method never reads the test frames, so nothing true reaches training.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Dict, Tuple

import numpy as np

PHOTO_SCALE = 4
"""The photos COLMAP sees are the scene rendered at this multiple of its size."""

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def shrink_intrinsics(meta: Dict, scale: int, size: Tuple[int, int]) -> Dict:
    """Pinhole intrinsics of photos ``scale`` times larger → those of the images at ``size`` (w, h).

    COLMAP and nerfstudio place pixel i's centre at i + 0.5 (the image spans [0, w]), so a point at u on the small
    image is at ``scale · u`` on the large one: every intrinsic divides by ``scale`` (what nerfstudio's own
    downscaling does).
    """
    return {"fl_x": float(meta["fl_x"]) / scale, "fl_y": float(meta["fl_y"]) / scale,
            "cx": float(meta["cx"]) / scale, "cy": float(meta["cy"]) / scale, "w": int(size[0]), "h": int(size[1])}


def camera_similarity_fit(true_c2w: np.ndarray, colmap_c2w: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """The similarity (scale, R [3, 3], t [3]) from the true frame to COLMAP's that best maps true cameras [N, 4, 4]
    onto COLMAP's [N, 4, 4] (camera→world, the same axes convention): R the chordal mean of the cameras' relative
    rotations ``R_colmap · R_trueᵀ``, scale from the centres' spread about their means (Umeyama's, with that R),
    t from the means.

    A fit to the centres alone leaves the rotation about the axis of a ring of cameras to their small errors (on a
    tiny scene 1.4° off in every camera); the cameras' own rotations pin it.
    """
    true_c2w, colmap_c2w = np.asarray(true_c2w, dtype=np.float64), np.asarray(colmap_c2w, dtype=np.float64)
    u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", colmap_c2w[:, :3, :3], true_c2w[:, :3, :3]))
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    src, dst = true_c2w[:, :3, 3], colmap_c2w[:, :3, 3]
    src_c, dst_c = src - src.mean(axis=0), dst - dst.mean(axis=0)
    scale = float(np.einsum("ni,ni->", dst_c, src_c @ rotation.T) / max(float((src_c ** 2).sum()), 1e-12))
    if not scale > 0:
        raise RuntimeError("COLMAP's camera centres do not follow the true ones (the fitted scale is not positive)")
    return scale, rotation, dst.mean(axis=0) - scale * rotation @ src.mean(axis=0)


def photo_scene(scene: Path, scale: int = PHOTO_SCALE) -> Path:
    """The scene rendered again from the same cameras at ``scale`` times its size, beside it (reused when current).

    The simulator draws layout, lights and cameras from the seed alone, so only the pixels differ.
    """
    from splatreplace_ns.tools.sim import is_current_scene, make_scene

    sim = json.loads((Path(scene) / "transforms.json").read_text())["sim"]
    w, h = (int(v) * scale for v in sim["resolution"])
    out = Path(scene).parent / f"{Path(scene).name}_photos{w}x{h}"
    if not is_current_scene(out):
        make_scene(sim["preset"], out, res=f"{w}x{h}", seed=int(sim["seed"]), n_train=int(sim["n_train"]),
                   n_test=int(sim["n_test"]), light=sim.get("light", "preset"))
    return out


def colmap_transforms(scene_meta: Dict, processed_meta: Dict, names: Dict[str, str], scale: int) -> Tuple[Dict, Dict]:
    """The regime's ``transforms.json`` from the scene's and the processed capture's.

    Args:
        scene_meta: the exact scene's transforms.json (true poses, split lists, instances).
        processed_meta: ``ns-process-data``'s transforms.json (COLMAP's poses of the enlarged photos, saved with its
            ``applied_transform``; ``ply_file_path``).
        names: training image name → the processed frame's ``file_path`` (``capture.processed_names``).
        scale: how many times larger the photos were than the scene's images.
    Returns:
        (transforms, report): every frame with its own intrinsics (COLMAP's for the training views, the true ones
        for the test views), the training views COLMAP posed, the test views and instances moved by the fitted
        similarity; report {"posed", "photos", "centre_error_m": {"mean", "max"}, "rotation_error_deg":
        {"mean", "max"}, "similarity_scale"} (errors of the posed training cameras against the truth after the fit,
        centres in the scene's units).
    """
    from splatreplace_ns.eval.alignment import apply_similarity, similarity_pose

    size = (int(scene_meta["w"]), int(scene_meta["h"]))
    true_intrinsics = {k: scene_meta[k] for k in INTRINSIC_KEYS}
    colmap_intrinsics = shrink_intrinsics(processed_meta, scale, size)
    saved = {f["file_path"]: np.asarray(f["transform_matrix"], dtype=np.float64) for f in processed_meta["frames"]}
    frames_by_name = {Path(f["file_path"]).name: f for f in scene_meta["frames"]}
    train_names = [Path(p).name for p in scene_meta["train_filenames"]]
    posed = [n for n in train_names if n in names]
    if len(posed) < 3:
        raise RuntimeError(f"COLMAP posed {len(posed)} of {len(train_names)} training images: too few to place the "
                           "test views")
    true_c2w = np.stack([np.asarray(frames_by_name[n]["transform_matrix"], dtype=np.float64) for n in posed])
    colmap_c2w = np.stack([saved[names[n]] for n in posed])
    fit = camera_similarity_fit(true_c2w, colmap_c2w)  # true frame → COLMAP's saved frame
    moved = similarity_pose(true_c2w, *fit)
    errors = np.linalg.norm(apply_similarity(true_c2w[:, :3, 3], *fit) - colmap_c2w[:, :3, 3], axis=1) / fit[0]
    cosines = (np.einsum("nij,nij->n", moved[:, :3, :3], colmap_c2w[:, :3, :3]) - 1.0) / 2.0
    rotation_errors = np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))

    out = {k: v for k, v in scene_meta.items() if k not in INTRINSIC_KEYS + ("frames", "ply_file_path")}
    out.pop("depth_unit_scale_factor", None)
    out.pop("depth_zero", None)
    out["applied_transform"] = processed_meta.get("applied_transform")
    if out["applied_transform"] is None:
        out.pop("applied_transform")
    if processed_meta.get("ply_file_path"):
        out["ply_file_path"] = processed_meta["ply_file_path"]
    held_out = set(scene_meta.get("test_filenames", [])) | set(scene_meta.get("val_filenames", []))
    frames = []
    for frame in scene_meta["frames"]:
        name = Path(frame["file_path"]).name
        if frame["file_path"] in held_out:  # scored only: the true camera moved into COLMAP's frame
            entry = {"file_path": frame["file_path"],
                     "transform_matrix": similarity_pose(np.asarray(frame["transform_matrix"]), *fit).tolist(),
                     **true_intrinsics}
            if "instance_mask_path" in frame:  # evaluation masks
                entry["instance_mask_path"] = frame["instance_mask_path"]
        elif name in names:
            entry = {"file_path": frame["file_path"], "transform_matrix": saved[names[name]].tolist(),
                     **colmap_intrinsics}
        else:
            continue  # a training image COLMAP did not pose: a user's run has no camera for it
        frames.append(entry)
    out["frames"] = frames
    out["train_filenames"] = [p for p in scene_meta["train_filenames"] if Path(p).name in names]
    scale = float(fit[0])
    out["instances"] = [dict(inst, transform_matrix=similarity_pose(np.asarray(inst["transform_matrix"]), *fit).tolist(),
                             **({"size": float(inst["size"]) * scale} if "size" in inst else {}))
                        if "transform_matrix" in inst else dict(inst) for inst in scene_meta.get("instances", [])]
    report = {"posed": len(posed), "photos": len(train_names), "similarity_scale": scale,
              "centre_error_m": {"mean": float(errors.mean()), "max": float(errors.max())},
              "rotation_error_deg": {"mean": float(rotation_errors.mean()), "max": float(rotation_errors.max())}}
    return out, report


def write_colmap_regime(scene: Path, folder: Path, scale: int = PHOTO_SCALE) -> Dict:
    """Runs COLMAP (``ns-process-data``) on the training photos (:func:`photo_scene`) and writes the regime's dataset
    into ``folder`` (already made, with ``images`` and ``masks`` linked to the scene's). → the report of
    :func:`colmap_transforms` with ``seconds`` (COLMAP's) and ``sparse_points``.

    Raises:
        RuntimeError: when ``ns-process-data`` fails (COLMAP made no model) or poses fewer than three training
            images.
    """
    from splatreplace_ns.tools.bench.capture import capture_clicks, ns_process_data, processed_names, training_photos

    scene, folder = Path(scene), Path(folder)
    work = folder / "colmap"
    photos, processed = work / "photos", work / "processed"
    start = time.perf_counter()
    big = photo_scene(scene, scale)
    training_photos(big, photos)
    if processed.exists():
        shutil.rmtree(processed)
    render_s = time.perf_counter() - start
    print(f"[colmap] ns-process-data on the {len(list(photos.iterdir()))} training photos at {scale}x the size ...",
          flush=True)
    start = time.perf_counter()
    colmap = ns_process_data(photos, processed, num_downscales=0, matching="exhaustive", camera_type="pinhole")
    (work / "ns_process_data.log").write_text(colmap["log"])
    names = processed_names(photos, processed)  # photo name → processed file_path
    scene_meta = json.loads((scene / "transforms.json").read_text())
    processed_meta = json.loads((processed / "transforms.json").read_text())
    transforms, report = colmap_transforms(scene_meta, processed_meta, names, scale)
    points = 0
    if transforms.get("ply_file_path"):
        ply = processed / transforms["ply_file_path"]
        shutil.copy2(ply, folder / transforms["ply_file_path"])
        points = _point_count(ply)
    by_name = {Path(p).name: p for p in transforms["train_filenames"]}
    clicks = capture_clicks(scene, by_name)  # clicks on an image COLMAP did not pose move to a posed one
    (folder / "clicks.json").write_text(json.dumps(clicks, indent=2) + "\n")
    (folder / "transforms.json").write_text(json.dumps(transforms, indent=2) + "\n")
    command = colmap["command"].split(" ", 1)  # the executable by name: its folder is this machine's
    report.update(seconds=time.perf_counter() - start, photos_render_s=render_s, sparse_points=points,
                  command=" ".join([Path(command[0]).name] + command[1:]))
    print(f"[colmap] posed {report['posed']} of {report['photos']} training images in {report['seconds']:.0f} s, "
          f"{points} sparse points; after the similarity fit the camera centres are "
          f"{report['centre_error_m']['mean']:.3f} m off on average, the rotations "
          f"{report['rotation_error_deg']['mean']:.2f} deg", flush=True)
    return report


def _point_count(path: Path) -> int:
    """Points in a PLY point cloud (open3d reads it)."""
    import open3d as o3d

    return len(o3d.io.read_point_cloud(str(path)).points)
