"""COLMAP input: a ``sparse/0`` model (read with pycolmap) becomes a nerfstudio ``transforms.json``.

For a capture that went through COLMAP but not ``ns-process-data`` (which writes transforms.json
itself). Poses stay in COLMAP's world frame (OpenCV cameras turned into nerfstudio's OpenGL ones);
the model's 3D points become ``sparse_pc.ply``, the base stage's initialisation.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.datamanager.files import write_atomically
from splatreplace_ns.render.cameras import OPENCV_TO_OPENGL

SPARSE_CANDIDATES = ("sparse/0", "colmap/sparse/0", "sparse")

# COLMAP camera model → nerfstudio camera_model and how its parameters map to transforms.json keys.
CAMERA_MODELS: Dict[str, tuple] = {
    "SIMPLE_PINHOLE": ("PINHOLE", ("f", "cx", "cy")),
    "PINHOLE": ("PINHOLE", ("fl_x", "fl_y", "cx", "cy")),
    "SIMPLE_RADIAL": ("OPENCV", ("f", "cx", "cy", "k1")),
    "RADIAL": ("OPENCV", ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": ("OPENCV", ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2")),
}


def find_sparse_model(data: Path) -> Optional[Path]:
    """The first folder under ``data`` that holds a COLMAP model (cameras + images), or None."""
    for candidate in SPARSE_CANDIDATES:
        folder = Path(data) / candidate
        if any((folder / f"cameras{ext}").exists() for ext in (".bin", ".txt")):
            return folder
    return None


def camera_entry(model_name: str, params, width: int, height: int, source: str) -> Dict:
    """transforms.json intrinsics of one COLMAP camera."""
    if model_name not in CAMERA_MODELS:
        raise DatasetFormatError(
            f"{source}: COLMAP camera model {model_name} is not supported; use PINHOLE/OPENCV/SIMPLE_RADIAL/RADIAL "
            "(or undistort with colmap image_undistorter first)"
        )
    ns_model, keys = CAMERA_MODELS[model_name]
    entry: Dict = {"camera_model": ns_model, "w": int(width), "h": int(height)}
    for key, value in zip(keys, [float(p) for p in params]):
        if key == "f":
            entry["fl_x"] = entry["fl_y"] = value
        else:
            entry[key] = value
    return entry


def colmap_to_transforms(data: Path, sparse: Optional[Path] = None, images_dir: str = "images") -> Path:
    """Writes ``data/transforms.json`` (and ``sparse_pc.ply``) from a COLMAP model.

    Args:
        data: capture folder with the images in ``data/images_dir``.
        sparse: the model folder (default: :func:`find_sparse_model`).

    Returns:
        the written transforms.json.
    """
    import pycolmap

    data = Path(data)
    sparse = sparse or find_sparse_model(data)
    if sparse is None:
        raise DatasetFormatError(
            f"{data}: no transforms.json and no COLMAP model (looked for {', '.join(SPARSE_CANDIDATES)})"
        )
    reconstruction = pycolmap.Reconstruction()
    reconstruction.read(str(sparse))
    cameras = {cid: cam for cid, cam in reconstruction.cameras.items()}
    entries = {
        cid: camera_entry(cam.model.name, cam.params, cam.width, cam.height, f"{sparse} camera {cid}")
        for cid, cam in cameras.items()
    }
    shared = len(entries) == 1
    frames = []
    for image_id in sorted(reconstruction.reg_image_ids(), key=lambda i: reconstruction.image(i).name):
        image = reconstruction.image(image_id)
        if not (data / images_dir / image.name).exists():
            raise DatasetFormatError(f"{sparse}: image '{image.name}' not found in {data / images_dir}")
        world_to_camera = np.eye(4)
        world_to_camera[:3] = image.cam_from_world().matrix()
        frame = {
            "file_path": f"{images_dir}/{image.name}",
            "transform_matrix": (np.linalg.inv(world_to_camera) @ OPENCV_TO_OPENGL).tolist(),
        }
        if not shared:
            frame.update({k: v for k, v in entries[image.camera_id].items() if k != "camera_model"})
        frames.append(frame)
    if not frames:
        raise DatasetFormatError(f"{sparse}: the model has no registered images")
    models = {e["camera_model"] for e in entries.values()}
    meta: Dict = {"camera_model": "OPENCV" if "OPENCV" in models else "PINHOLE"}
    if shared:
        meta.update({k: v for k, v in next(iter(entries.values())).items() if k != "camera_model"})
    meta["frames"] = frames
    if reconstruction.num_points3D():
        ply = data / "sparse_pc.ply"
        reconstruction.export_PLY(str(ply))
        meta["ply_file_path"] = ply.name
    transforms = data / "transforms.json"
    write_atomically(transforms, json.dumps(meta, indent=2) + "\n")
    return transforms
