"""The files a ``transforms.json`` names, each opened and decoded whole before anything trains: an image cut short
by a copy, a mask of another picture or a depth map of NaNs is a line naming the file, not a traceback from a
worker thread halfway through training."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
from PIL import Image

from splatreplace_ns.datamanager.errors import DatasetFormatError

MAX_MASK_UPSCALE = 2.0
"""A mask may be smaller than its image by up to this factor (made at nerfstudio's ``images_2`` size while the run
reads the full-size images); a smaller one would be enlarged into outlines nobody drew, and is refused."""


def read_json(path: Path, what: str = "file") -> object:
    """A JSON file's contents, or an error that names the file and where its text stops being JSON."""
    path = Path(path)
    if not path.exists():
        raise DatasetFormatError(f"{path}: {what} not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise DatasetFormatError(f"{path}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    except UnicodeDecodeError:
        raise DatasetFormatError(f"{path}: not a text file (expected JSON)") from None


def image_size(path: Path) -> Tuple[int, int]:
    """(width, height) of an image file from its header, or an error naming it."""
    try:
        with Image.open(path) as image:
            return image.size
    except FileNotFoundError:
        raise DatasetFormatError(f"{path}: image file not found") from None
    except OSError as err:
        raise DatasetFormatError(f"{path}: not a readable image ({err})") from None


def mask_size_problem(mask_size: Tuple[int, int], image_size_: Tuple[int, int]) -> Optional[str]:
    """Why a mask of ``mask_size`` (w, h) cannot serve an image of ``image_size_`` (w, h), or None when it can: the
    same size, or the same picture at another scale (each side within one pixel of one factor) that is not more
    than :data:`MAX_MASK_UPSCALE` times smaller."""
    (mw, mh), (iw, ih) = mask_size, image_size_
    if (mw, mh) == (iw, ih):
        return None
    factor = iw / mw
    if abs(mh * factor - ih) >= 1.0 + 1e-9 or abs(ih / mh * mw - iw) >= 1.0 + 1e-9:
        return f"size {mw}x{mh} is not its image's {iw}x{ih} at any scale (another aspect ratio)"
    if factor > MAX_MASK_UPSCALE:
        return (f"size {mw}x{mh} is {factor:.3g} times smaller than its image's {iw}x{ih}; masks are enlarged at most "
                f"{MAX_MASK_UPSCALE:g} times (make them at the image's size)")
    return None


def decoded(path: Path, what: str) -> Tuple[Optional[np.ndarray], Optional[str]]:
    """(pixels [H, W] or [H, W, C], None) for a file that decodes to its last byte, or (None, the problem)."""
    if not path.is_file():
        return None, f"{path}: {what} file not found"
    try:
        if path.suffix.lower() == ".npy":
            return np.load(path, allow_pickle=False), None
        with Image.open(path) as image:
            image.load()  # the whole file: a truncated one fails here, not in a data loader later
            return np.asarray(image), None
    except (OSError, ValueError, SyntaxError) as err:
        return None, f"{path}: not a readable {what} ({err})"


def _instance_ids(meta: Dict, key: str = "instances") -> Optional[set]:
    """The ids ``instances`` (or ``key``) lists, or None when it lists none (or is not a list of objects with
    integer ids)."""
    instances = meta.get(key)
    if not isinstance(instances, list) or not instances:
        return None
    ids = [inst.get("id") if isinstance(inst, dict) else None for inst in instances]
    return set(ids) if all(isinstance(i, int) and not isinstance(i, bool) for i in ids) else None


def _expected_size(meta: Dict, frame: Dict) -> Optional[Tuple[int, int]]:
    w, h = frame.get("w", meta.get("w")), frame.get("h", meta.get("h"))
    valid = all(isinstance(v, int) and not isinstance(v, bool) for v in (w, h))
    return (w, h) if valid else None


def frame_file_problems(meta: Dict, data_dir: Path) -> Tuple[Dict[str, Optional[Tuple[int, int]]], List[str]]:
    """Decodes every frame's image, mask, depth map and instance mask.

    Checked: each file exists and decodes; an image is the frame's ``w`` x ``h``; masks and depth maps serve their
    image (the same size, or the same picture at most 2x smaller); depth maps and instance masks have one channel;
    depth maps are finite and not negative; instance masks hold only 0 and the ids of ``instances`` (when it lists
    some: one line for all the masks that hold other ids). Frames whose ``file_path`` is not a string are left to
    the schema's report.

    Returns:
        ({image file name: (width, height), or None where the image did not decode}, the problems, one line each).
    """
    problems: List[str] = []
    sizes: Dict[str, Optional[Tuple[int, int]]] = {}
    ids = {"instance_mask_path": _instance_ids(meta), "evaluation_mask_path": _instance_ids(meta, "evaluation_instances")}
    unlisted: Dict[Path, List[int]] = {}  # instance mask -> the ids it holds that 'instances' does not list
    frames = meta.get("frames") if isinstance(meta.get("frames"), list) else []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
            continue
        image_path = data_dir / frame["file_path"]
        pixels, problem = decoded(image_path, "image")
        sizes[Path(frame["file_path"]).name] = None if problem else (pixels.shape[1], pixels.shape[0])
        if problem:
            problems.append(problem)
            continue
        size = (pixels.shape[1], pixels.shape[0])
        expected = _expected_size(meta, frame)
        if expected is not None and expected != size:
            problems.append(f"{image_path}: size {size[0]}x{size[1]}, but transforms.json gives w x h = "
                            f"{expected[0]}x{expected[1]} for frames[{i}]")
        for key, what in (("mask_path", "mask"), ("depth_file_path", "depth map"),
                          ("instance_mask_path", "instance mask"), ("evaluation_mask_path", "instance mask")):
            if not isinstance(frame.get(key), str) or not frame[key]:
                continue
            path = data_dir / frame[key]
            aux, problem = decoded(path, what)
            problem = problem or _aux_problem(path, aux, what, size)
            if problem:
                problems.append(problem)
            elif ids.get(key) is not None:
                unknown = sorted(set(np.unique(aux).tolist()) - {0} - ids[key])
                if unknown:
                    unlisted[path] = unknown
    if unlisted:
        first = next(iter(unlisted))
        every = sorted({i for found in unlisted.values() for i in found})
        listed = sorted(set().union(*(v for v in ids.values() if v)))
        problems.append(f"{first}: ids {every[:10]} are not listed in transforms.json 'instances' (listed: "
                        f"{listed}); {len(unlisted)} instance mask(s) hold them")
    return sizes, problems


def _aux_problem(path: Path, pixels: np.ndarray, what: str, image_size: Tuple[int, int]) -> Optional[str]:
    """What is wrong with a decoded mask or depth map for its image of ``image_size`` (w, h), or None."""
    if what != "mask" and pixels.ndim != 2:
        return f"{path}: a {what} must have one channel, got shape {list(pixels.shape)}"
    problem = mask_size_problem((pixels.shape[1], pixels.shape[0]), image_size)
    if problem:
        return f"{path}: {problem}"
    if what == "depth map":
        values = pixels.astype(np.float64)
        if not np.isfinite(values).all() or (values < 0).any():
            return f"{path}: depth values must be finite and not negative"
    return None


def point_cloud_problems(path: Path) -> List[str]:
    """The point cloud (``ply_file_path``) exists, reads as PLY and holds at least one finite vertex."""
    from plyfile import PlyData

    if not path.is_file():
        return [f"{path}: point cloud file not found"]
    try:
        vertices = PlyData.read(str(path))["vertex"]
        xyz = np.stack([np.asarray(vertices[axis], dtype=np.float64) for axis in "xyz"], axis=-1)
    except Exception as err:  # plyfile raises many kinds on a damaged file; any of them means the same here
        return [f"{path}: not a readable PLY point cloud with x, y, z vertices ({type(err).__name__}: {err})"]
    if len(xyz) == 0 or not np.isfinite(xyz).all():
        return [f"{path}: the point cloud needs at least one vertex and finite coordinates"]
    return []
