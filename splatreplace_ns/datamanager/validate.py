"""Checks of a dataset's files before anything trains: each problem is one ``DatasetFormatError`` that names the
file and what is wrong with it, instead of a ``KeyError`` or a ``JSONDecodeError`` from deep inside nerfstudio, or a
failure after the base stage has trained.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Dict, Optional, Tuple

from PIL import Image

from splatreplace_ns.datamanager.errors import DatasetFormatError

SPLIT_LISTS = ("train_filenames", "val_filenames", "test_filenames")
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


def with_both_eval_splits(meta: Dict) -> Dict:
    """``transforms.json`` with ``val_filenames`` taken from ``test_filenames`` when only the latter is given (and
    the other way round): nerfstudio's parser needs the list of the split it loads, users write one of the two."""
    meta = dict(meta)
    if "train_filenames" in meta:
        if "val_filenames" not in meta and "test_filenames" in meta:
            meta["val_filenames"] = meta["test_filenames"]
        elif "test_filenames" not in meta and "val_filenames" in meta:
            meta["test_filenames"] = meta["val_filenames"]
    return meta


def check_transforms(meta: object, path: Path) -> Dict:
    """Checks what every stage relies on in a ``transforms.json`` and its files; returns it (as a dict).

    Checked: an object with a non-empty ``frames`` list; each frame's ``file_path`` and 4x4 finite
    ``transform_matrix``; each image file present and readable; split lists that name frames and hold ``train``
    together with ``test`` or ``val``; ``instances`` entries with a unique integer ``id`` > 0; each frame's
    instance mask present and of a size that serves its image (:func:`mask_size_problem`).
    """
    path = Path(path)
    data_dir = path.parent
    if not isinstance(meta, dict):
        raise DatasetFormatError(f"{path}: expected a JSON object with a 'frames' list, got {type(meta).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetFormatError(f"{path}: no 'frames' list (or it is empty); every frame needs 'file_path' and "
                                 "'transform_matrix'")
    names = set()
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise DatasetFormatError(f"{path}: frame {i} has no 'file_path'")
        where = f"{path}: frame {i} ({frame['file_path']})"
        matrix = frame.get("transform_matrix")
        if (not isinstance(matrix, list) or len(matrix) not in (3, 4)
                or not all(isinstance(row, list) and len(row) == 4 for row in matrix)
                or not all(isinstance(v, (int, float)) and math.isfinite(v) for row in matrix for v in row)):
            raise DatasetFormatError(f"{where}: 'transform_matrix' must be a 4x4 matrix of finite numbers")
        names.add(str(frame["file_path"]))
        size = image_size(data_dir / frame["file_path"])
        if "instance_mask_path" in frame:
            mask_path = data_dir / frame["instance_mask_path"]
            if not mask_path.exists():
                raise DatasetFormatError(f"{mask_path}: instance mask file not found ({where})")
            problem = mask_size_problem(image_size(mask_path), size)
            if problem:
                raise DatasetFormatError(f"{mask_path}: {problem}")
    given = [key for key in SPLIT_LISTS if key in meta]
    if given:
        if "train_filenames" not in given or given == ["train_filenames"]:
            raise DatasetFormatError(f"{path}: split lists {given}: give 'train_filenames' and 'test_filenames' "
                                     "(or 'val_filenames'), or none of them")
        for key in given:
            unknown = [str(name) for name in meta[key] if str(name) not in names]
            if unknown:
                raise DatasetFormatError(f"{path}: '{key}' names {unknown[:3]}, which no frame's 'file_path' is")
    ids = []
    for k, inst in enumerate(meta.get("instances") or []):
        if not isinstance(inst, dict) or "id" not in inst:
            raise DatasetFormatError(f"{path}: instance {k} has no 'id' (the value its pixels carry in the masks)")
        if not isinstance(inst["id"], int) or isinstance(inst["id"], bool) or inst["id"] < 1:
            raise DatasetFormatError(f"{path}: instance {k} has id {inst['id']!r}; ids are integers from 1 "
                                     "(0 is the background)")
        ids.append(inst["id"])
    duplicated = sorted({i for i in ids if ids.count(i) > 1})
    if duplicated:
        raise DatasetFormatError(f"{path}: instance ids {duplicated} are listed more than once")
    return meta
