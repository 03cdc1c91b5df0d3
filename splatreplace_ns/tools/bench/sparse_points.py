"""The sparse point cloud a user's capture has: COLMAP's features, matches and triangulation at the known poses.

A suite scene's ``points3d.ply`` is sampled from the true depth: dense and exact, what no capture gives. In the
user's regime (``bench suite --inputs user``) both methods start instead from what ``ns-process-data`` would leave:
COLMAP's SIFT features matched across the training images and triangulated (``pycolmap.triangulate_points``) at
the scene's camera poses, with COLMAP's own track filtering. Only the training images are used.

SIFT finds about 20 keypoints on a 96x72 image and COLMAP verifies no pair from them, so the images are enlarged
(``upsample``, bicubic) before the features are found, as a user's full-size photos would be before nerfstudio
downscales them for training. No new detail comes in: the points are found on the same pixels.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Dict, Tuple

import numpy as np

MIN_POINTS = 20
"""Fewer triangulated points than this and the cloud is dropped: the run starts from random Gaussians."""

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def camera_from_world(camera_to_world_gl: np.ndarray) -> np.ndarray:
    """[4, 4] camera→world in nerfstudio's OpenGL convention → [4, 4] world→camera in COLMAP's (OpenCV) one."""
    return np.linalg.inv(np.asarray(camera_to_world_gl, dtype=np.float64) @ OPENGL_TO_OPENCV)


def triangulate_training_views(scene: Path, upsample: int = 4) -> Tuple[np.ndarray, np.ndarray, Dict]:
    """COLMAP's sparse points of a scene's training images at its known camera poses.

    Args:
        scene: a dataset folder with ``transforms.json`` (shared PINHOLE intrinsics ``fl_x, fl_y, cx, cy``),
            ``train_filenames`` and the images.
        upsample: factor the images are enlarged by before feature extraction (1: as they are).
    Returns:
        xyz [N, 3] float64 in the frame of ``transforms.json``, rgb [N, 3] uint8, and a report {"points",
        "mean_reprojection_error_px" (in the enlarged images), "mean_track_length", "images", "upsample"}.
    """
    import cv2
    import pycolmap

    meta = json.loads((scene / "transforms.json").read_text())
    train = set(meta.get("train_filenames") or [f["file_path"] for f in meta["frames"]])
    frames = [f for f in meta["frames"] if f["file_path"] in train]
    poses = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], dtype=np.float64) for f in frames}
    with tempfile.TemporaryDirectory(prefix="sparse_points_") as tmp:
        work = Path(tmp)
        images = work / "images"
        images.mkdir()
        for frame in frames:
            pixels = cv2.imread(str(scene / frame["file_path"]), cv2.IMREAD_COLOR)
            if upsample > 1:
                pixels = cv2.resize(pixels, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
            cv2.imwrite(str(images / Path(frame["file_path"]).name), pixels)
        # pixel centres: x_big + 0.5 = upsample * (x + 0.5)
        fx, fy = meta["fl_x"] * upsample, meta["fl_y"] * upsample
        cx, cy = (meta["cx"] + 0.5) * upsample - 0.5, (meta["cy"] + 0.5) * upsample - 0.5
        database = work / "database.db"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = 1  # the same points on every run
        pycolmap.extract_features(
            database, images, camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=pycolmap.ImageReaderOptions(camera_model="PINHOLE", camera_params=f"{fx},{fy},{cx},{cy}"),
            extraction_options=extraction, device=pycolmap.Device.cpu)
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = 1
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        known = pycolmap.Reconstruction()
        db = pycolmap.Database.open(database)
        try:
            for camera in db.read_all_cameras():
                known.add_camera_with_trivial_rig(camera)
            for image in db.read_all_images():
                w2c = camera_from_world(poses[image.name])
                posed = pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id)
                known.add_image_with_trivial_frame(posed, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
        finally:
            db.close()
        output = work / "sparse"
        output.mkdir()
        triangulated = pycolmap.triangulate_points(known, database, images, output)
        points = list(triangulated.points3D.values())
        xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
        rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
        report = {"points": len(points), "images": len(frames), "upsample": upsample,
                  "mean_reprojection_error_px": float(np.mean([p.error for p in points])) if points else None,
                  "mean_track_length": float(np.mean([p.track.length() for p in points])) if points else None}
    return xyz, rgb, report


def write_sparse_cloud(scene: Path, out_ply: Path, upsample: int = 4) -> Dict:
    """Triangulates ``scene``'s training views (:func:`triangulate_training_views`) and writes the points to
    ``out_ply`` when there are at least :data:`MIN_POINTS`. → the report, with ``"written"``."""
    from splatreplace_ns.tools.sim.writer import write_ply

    xyz, rgb, report = triangulate_training_views(scene, upsample)
    report["written"] = len(xyz) >= MIN_POINTS
    if report["written"]:
        write_ply(out_ply, xyz.astype(np.float32), rgb)
    elif out_ply.exists():
        out_ply.unlink()
    return report


__all__ = ["MIN_POINTS", "camera_from_world", "triangulate_training_views", "write_sparse_cloud"]
