"""Export a synthetic scene as a COLMAP model (what ``colmap mapper`` leaves behind), through pycolmap.

Writes ``OUT/images/`` (the scene's images, same names) and ``OUT/sparse/0/`` (cameras.bin, images.bin,
points3D.bin, plus rigs/frames in pycolmap's current format): one PINHOLE camera, every frame's
world→camera pose, and the scene's SfM-like points with their colours. Masks, depth and instances are
not exported — a COLMAP model is what a real capture has.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [P, 3] float64, rgb [P, 3] uint8) of a PLY point cloud."""
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], -1).astype(np.float64)
    if all(c in vertex.data.dtype.names for c in ("red", "green", "blue")):
        rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], -1).astype(np.uint8)
    else:
        rgb = np.full((len(xyz), 3), 128, dtype=np.uint8)
    return xyz, rgb


def export_colmap(scene: Path, out: Path) -> Path:
    """Writes a sim scene as a COLMAP model.

    Args:
        scene: a ``splatreplace sim`` folder (transforms.json with one shared PINHOLE camera).
        out: output folder (created; ``images/`` and ``sparse/0`` are replaced).

    Returns:
        ``out / "sparse" / "0"``.
    """
    import pycolmap

    scene, out = Path(scene), Path(out)
    meta = json.loads((scene / "transforms.json").read_text())
    if meta.get("camera_model", "PINHOLE") != "PINHOLE":
        raise ValueError(f"{scene / 'transforms.json'}: only PINHOLE scenes can be exported, got {meta['camera_model']}")
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        model="PINHOLE", width=int(meta["w"]), height=int(meta["h"]),
        params=[float(meta["fl_x"]), float(meta["fl_y"]), float(meta["cx"]), float(meta["cy"])], camera_id=1,
    )
    reconstruction.add_camera_with_trivial_rig(camera)
    if (out / "images").exists():
        shutil.rmtree(out / "images")
    (out / "images").mkdir(parents=True)
    for image_id, frame in enumerate(meta["frames"], start=1):
        name = Path(frame["file_path"]).name
        shutil.copy2(scene / frame["file_path"], out / "images" / name)
        camera_to_world = np.asarray(frame["transform_matrix"], dtype=np.float64) @ OPENGL_TO_OPENCV
        world_to_camera = np.linalg.inv(camera_to_world)
        image = pycolmap.Image(name=name, camera_id=1, image_id=image_id)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(world_to_camera[:3]))
    if "ply_file_path" in meta:
        xyz, rgb = read_ply_points(scene / meta["ply_file_path"])
        for p, c in zip(xyz, rgb):
            reconstruction.add_point3D(p, pycolmap.Track(), c)
    sparse = out / "sparse" / "0"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    reconstruction.write(str(sparse))
    return sparse
