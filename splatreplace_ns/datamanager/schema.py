"""The dataset's JSON files, declared once: ``transforms.json`` (what nerfstudio's parser and ours read) and
``clicks.json``, with types, ranges and the rules that tie one field to another. Files are checked in
:mod:`splatreplace_ns.datamanager.validate`, which runs these models first.

Unknown keys are allowed (``ns-process-data`` and other tools write their own); every key that a stage reads is
declared here.
"""

from __future__ import annotations

from typing import Any, Dict, List, Literal, Optional

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, StrictStr, TypeAdapter, ValidationError
from typing_extensions import Annotated

RIGID_TOLERANCE = 1e-2
"""Largest |R^T R - I| entry of a pose's rotation block: poses are rigid, written to a few decimals."""
MAX_TRANSLATION = 1e6
"""Largest |t| of a pose, in the dataset's units: beyond it, nerfstudio's auto-scaling collapses every other pose."""
MAX_DISTORTION = 10.0
"""Largest |k| or |p| of a lens: beyond it, the undistortion map folds over."""
MAX_FOCAL_PER_PIXEL = 1000.0
"""Largest focal length in units of the image's larger side (a field of view of about 0.06 degrees)."""
MAX_IMAGE_SIDE = 100_000
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
SPLIT_LISTS = ("train_filenames", "val_filenames", "test_filenames")
CAMERA_MODELS = ("OPENCV", "OPENCV_FISHEYE", "EQUIRECTANGULAR", "PINHOLE", "SIMPLE_PINHOLE")
"""nerfstudio's ``camera_model`` names."""

Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Distortion = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-MAX_DISTORTION, le=MAX_DISTORTION)]
Focal = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]
ImageSide = Annotated[int, Field(strict=True, gt=0, le=MAX_IMAGE_SIDE)]
RelativePath = Annotated[StrictStr, Field(min_length=1)]


def rigid_problem(matrix: List[List[float]], rows: int) -> Optional[str]:
    """Why a pose (``rows`` x 4, finite numbers) is not rigid, or None.

    Args:
        matrix: [rows, 4] nested lists; rows 3 or 4 (a 4th row must be [0, 0, 0, 1]).
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (rows, 4) and not (rows == 4 and m.shape == (3, 4)):
        return f"must be a {rows}x4 matrix, got {m.shape[0]}x{m.shape[1] if m.ndim == 2 else '?'}"
    if m.shape[0] == 4 and np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-6:
        return f"the last row must be [0, 0, 0, 1], got {m[3].tolist()}"
    rotation = m[:3, :3]
    if np.abs(rotation.T @ rotation - np.eye(3)).max() > RIGID_TOLERANCE or np.linalg.det(rotation) <= 0:
        return "the 3x3 rotation block is not a rotation (orthonormal, determinant +1)"
    if np.abs(m[:3, 3]).max() > MAX_TRANSLATION:
        return f"translation {m[:3, 3].tolist()} is beyond {MAX_TRANSLATION:g}"
    return None


Matrix = List[Annotated[List[Finite], Field(min_length=4, max_length=4)]]


def _rigid(rows: int):
    """A validator: a pose of ``rows`` x 4 finite numbers that is rigid (:func:`rigid_problem`)."""
    def check(value):
        problem = rigid_problem(value, rows)
        if problem:
            raise ValueError(problem)
        return value
    return AfterValidator(check)


Pose = Annotated[Matrix, Field(min_length=3, max_length=4), _rigid(4)]
"""Camera→world: 3x4, or 4x4 with [0, 0, 0, 1] below."""
ObjectPose = Annotated[Matrix, Field(min_length=4, max_length=4), _rigid(4)]
"""Object→world, 4x4."""
Pose3x4 = Annotated[Matrix, Field(min_length=3, max_length=3), _rigid(3)]


class Intrinsics(BaseModel):
    """The camera fields nerfstudio reads from the top level or from each frame."""

    model_config = ConfigDict(extra="allow")

    fl_x: Optional[Focal] = None
    fl_y: Optional[Focal] = None
    cx: Optional[Finite] = None
    cy: Optional[Finite] = None
    w: Optional[ImageSide] = None
    h: Optional[ImageSide] = None
    k1: Optional[Distortion] = None
    k2: Optional[Distortion] = None
    k3: Optional[Distortion] = None
    k4: Optional[Distortion] = None
    p1: Optional[Distortion] = None
    p2: Optional[Distortion] = None


class Frame(Intrinsics):
    file_path: RelativePath
    transform_matrix: Pose
    """Camera→world, OpenGL convention."""
    mask_path: Optional[RelativePath] = None
    depth_file_path: Optional[RelativePath] = None
    instance_mask_path: Optional[RelativePath] = None


class Instance(BaseModel):
    model_config = ConfigDict(extra="allow")

    id: Annotated[int, Field(strict=True, ge=1, le=65535)]
    """The value its pixels carry in the 16-bit instance masks (0 is the background)."""
    class_: StrictStr = Field("object", alias="class", min_length=1)
    symmetry: StrictStr = "none"
    size: Optional[Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]] = None
    transform_matrix: Optional[ObjectPose] = None
    """Object→world, ground truth (scores registration)."""


class Transforms(Intrinsics):
    """``transforms.json``."""

    frames: List[Frame] = Field(min_length=1)
    camera_model: Optional[Literal[CAMERA_MODELS]] = None
    train_filenames: Optional[List[RelativePath]] = None
    val_filenames: Optional[List[RelativePath]] = None
    test_filenames: Optional[List[RelativePath]] = None
    instances: Optional[List[Instance]] = None
    ply_file_path: Optional[RelativePath] = None
    applied_transform: Optional[Pose3x4] = None
    applied_scale: Optional[Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]] = None
    orientation_override: Optional[Literal["pca", "up", "vertical", "none"]] = None
    depth_unit_scale_factor: Optional[Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]] = None
    depth_zero: Optional[Literal["unknown", "far"]] = None
    instance_masks_source: Optional[Literal["ground_truth", "clicks"]] = None


def cross_field_problems(raw: Dict) -> List[str]:
    """The rules that tie fields together, one message each. They read the parsed JSON itself, taking only values
    of the right type, so that they are reported beside the problems of single fields."""
    frames = [f for f in raw.get("frames") or [] if isinstance(f, dict)] if isinstance(raw.get("frames"), list) else []
    problems = []
    for key in INTRINSICS:  # nerfstudio: fixed at the top level, or given in every frame
        if key not in raw:
            missing = [i for i, f in enumerate(frames) if key not in f]
            if missing:
                problems.append(f"'{key}' is given neither at the top level nor in frames {_first(missing)} "
                                f"({len(missing)} of {len(frames)} frames)")
    camera_problems: Dict[str, List[int]] = {}  # one line per problem, naming the frames it is found in
    for i, frame in enumerate(frames):
        w, h, fx, fy, cx, cy = (_number(frame, raw, key) for key in INTRINSICS[4:] + INTRINSICS[:4])
        if w is None or h is None or w <= 0 or h <= 0:
            continue
        if any(f is not None and f > MAX_FOCAL_PER_PIXEL * max(w, h) for f in (fx, fy)):
            camera_problems.setdefault(f"focal length {max(fx or 0, fy or 0):g} is more than {MAX_FOCAL_PER_PIXEL:g} "
                                       f"times the image's larger side {max(w, h):g}", []).append(i)
        if (cx is not None and not 0 <= cx <= w) or (cy is not None and not 0 <= cy <= h):
            camera_problems.setdefault(f"principal point (cx, cy) = ({cx}, {cy}) lies outside the {w:g}x{h:g} "
                                       "image", []).append(i)
    for message, where in camera_problems.items():
        problems.append(f"{message} (frames {_first(where)}: {len(where)} of {len(frames)})")
    names = [f["file_path"].split("/")[-1] for f in frames if isinstance(f.get("file_path"), str)]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        problems.append(f"frames: image file names {repeated[:3]} appear more than once (masks and depth pair "
                        "with images by file name)")
    train = set(raw["train_filenames"]) if isinstance(raw.get("train_filenames"), list) else None
    for key in ("mask_path", "depth_file_path", "instance_mask_path"):
        having = [i for i, f in enumerate(frames) if key in f]
        evaluation_only = train is not None and {i for i, f in enumerate(frames) if f.get("file_path") not in train}
        if key == "instance_mask_path" and having and set(having) == evaluation_only:
            continue  # evaluation masks: they score the test views; the training frames' come from the clicks
        if having and len(having) != len(frames):
            without = [i for i in range(len(frames)) if i not in set(having)]
            problems.append(f"'{key}' is given in {len(having)} of {len(frames)} frames (not in frames "
                            f"{_first(without)}); give it for every frame or for none"
                            + (" (or, for instance masks, on exactly the frames train_filenames does not list)"
                               if key == "instance_mask_path" else ""))
    given = [key for key in SPLIT_LISTS if key in raw]
    if given and ("train_filenames" not in given or given == ["train_filenames"]):
        problems.append(f"split lists {given}: give 'train_filenames' and 'test_filenames' (or 'val_filenames'), "
                        "or none of them")
    known = {f.get("file_path") for f in frames}
    for key in given:
        if isinstance(raw[key], list):
            unknown = [name for name in raw[key] if name not in known]
            if unknown:
                problems.append(f"'{key}' names {unknown[:3]}, which no frame's 'file_path' is")
    instances = raw.get("instances") if isinstance(raw.get("instances"), list) else []
    ids = [inst.get("id") for inst in instances if isinstance(inst, dict) and isinstance(inst.get("id"), int)]
    duplicated = sorted({i for i in ids if ids.count(i) > 1})
    if duplicated:
        problems.append(f"instances: ids {duplicated} are listed more than once")
    return problems


def _number(frame: Dict, raw: Dict, key: str) -> Optional[float]:
    """A frame's own value of ``key``, else the top level's; None unless it is a finite number."""
    value = frame.get(key, raw.get(key))
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
    return float(value) if ok else None


class ClickEntry(BaseModel):
    """One click of ``clicks.json``: a pixel (u = column, v = row) of a frame's image file."""

    model_config = ConfigDict(extra="allow")

    file_path: RelativePath
    xy: Annotated[List[Finite], Field(min_length=2, max_length=2)]
    class_: StrictStr = Field("object", alias="class", min_length=1)


def _short(value: Any, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _first(indices: List[int], shown: int = 3) -> str:
    return ", ".join(map(str, indices[:shown])) + (", ..." if len(indices) > shown else "")


def location(loc: tuple, raw: Any) -> str:
    """``frames[3] (images/0003.png).transform_matrix[0][1]`` from pydantic's error location in ``raw``: indices
    in brackets, and a frame's ``file_path`` beside its index."""
    parts, node = [], raw
    for key in loc:
        if isinstance(key, int):
            node = node[key] if isinstance(node, list) and 0 <= key < len(node) else None
            label = f"[{key}]"
            if isinstance(node, dict) and isinstance(node.get("file_path"), str) and len(parts) == 1:
                label += f" ({node['file_path']})"
            parts.append(label)
        else:
            name = "class" if key == "class_" else str(key)
            parts.append(("." if parts else "") + name)
            node = node.get(name) if isinstance(node, dict) else None
    return "".join(parts)


def _lines(err: ValidationError, raw: Any) -> List[str]:
    lines = []
    for error in err.errors():
        where = location(tuple(error["loc"]), raw)
        message = "required, but missing" if error["type"] == "missing" else error["msg"].removeprefix("Value error, ")
        if error["type"] not in ("missing", "value_error"):
            message += f" (got {_short(error['input'])})"
        lines.append(f"{where}: {message}" if where else message)
    return lines


def transforms_problems(raw: Any) -> List[str]:
    """Every problem of a parsed ``transforms.json``, one ``field: message`` line each; [] when it is valid."""
    if not isinstance(raw, dict):
        return [f"expected a JSON object with a 'frames' list, got {type(raw).__name__}"]
    try:
        Transforms.model_validate(raw)
        problems = []
    except ValidationError as err:
        problems = _lines(err, raw)
    return problems + cross_field_problems(raw)


_CLICK = TypeAdapter(ClickEntry)


def click_problems(index: int, entry: Any) -> List[str]:
    """The problems of one click of ``clicks.json`` (entry ``index``), one line each; [] when it is valid."""
    try:
        _CLICK.validate_python(entry)
    except ValidationError as err:
        return [f"click {index}{_click_label(entry)}: {line}" for line in _lines(err, entry)]
    return []


def _click_label(entry: Any) -> str:
    return f" ({entry['file_path']})" if isinstance(entry, dict) and isinstance(entry.get("file_path"), str) else ""
