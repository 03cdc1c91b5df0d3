"""Instance masks made from clicks live beside ``transforms.json``, never in it.

``splatreplace masks`` and ``ns-train splat-replace`` (on a capture without masks) write ``instance_masks/NNNN.png``
(16-bit, 0 = background, k = instance id) and ``instance_masks/index.json``; the user's ``transforms.json`` is
left byte for byte as it was. The index says which frame each mask belongs to (by ``file_path``), which instances
the masks hold and which clicks made them::

    {"source": "clicks", "clicks_digest": "...", "instances": [{"id": 1, "class": "chair"}, ...],
     "frames": [{"file_path": "images/frame_00001.png", "instance_mask_path": "instance_masks/0000.png"}, ...]}

:func:`with_click_masks` gives the ``transforms.json`` contents as if the masks were in it, so every reader of the
dataset (the dataparser, the stale-clicks check, the benchmarks) sees one view of it. Masks given in
``transforms.json`` itself (ground truth, or a person's) always win over the index.

**Evaluation masks.** Masks given on exactly the evaluation frames (every frame that ``train_filenames`` does not
list, and no other) score the test views and nothing else: the training frames get their masks from the clicks.
:func:`with_click_masks` moves them to ``frames[].evaluation_mask_path`` (and the listed ``instances`` to
``evaluation_instances``), so that no reader takes them for training masks.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional

from splatreplace_ns.datamanager.errors import DatasetFormatError

MASKS_DIR = "instance_masks"
INDEX_NAME = "index.json"
MASKS_SOURCE_KEY = "instance_masks_source"
"""Where the instance masks come from: ``"clicks"`` (made from one click per instance and the base model) or
``"ground_truth"`` (the default when absent: a synthetic scene's, or a person's)."""
EVALUATION_MASK_KEY = "evaluation_mask_path"
"""A frame's evaluation mask (given on the evaluation frames alone; see the module's docstring)."""
EVALUATION_INSTANCES_KEY = "evaluation_instances"
"""The ``instances`` that ``transforms.json`` lists beside evaluation masks: the ids those masks hold."""
CLICKS_DIGEST_KEY = "instance_masks_clicks"
"""The fingerprint (``datamanager.clicks.clicks_digest``) of the clicks the masks were made from."""


def index_path(data_dir: Path) -> Path:
    """``DATA/instance_masks/index.json``."""
    return Path(data_dir) / MASKS_DIR / INDEX_NAME


def mask_path(frame_index: int) -> str:
    """``instance_masks/NNNN.png`` for a frame (relative to the dataset folder)."""
    return f"{MASKS_DIR}/{frame_index:04d}.png"


def make_index(file_paths: List[str], instances: List[Dict], clicks_digest: str = "") -> Dict:
    """The index for masks ``instance_masks/0000.png, 0001.png, ...`` of the frames ``file_paths`` (in order)."""
    return {
        "source": "clicks",
        "clicks_digest": clicks_digest,
        "instances": [dict(inst) for inst in instances],
        "frames": [{"file_path": str(p), "instance_mask_path": mask_path(i)} for i, p in enumerate(file_paths)],
    }


def read_index(data_dir: Path) -> Optional[Dict]:
    """The checked index, or None when there is none."""
    path = index_path(data_dir)
    if not path.exists():
        return None
    try:
        index = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DatasetFormatError(f"{path}: not valid JSON ({err}); delete {path.parent} to make the masks again "
                                 "from clicks.json") from None
    if (not isinstance(index, dict) or not isinstance(index.get("frames"), list)
            or not isinstance(index.get("instances"), list)
            or not all(isinstance(f, dict) and "file_path" in f and "instance_mask_path" in f for f in index["frames"])):
        raise DatasetFormatError(f"{path}: expected 'frames' (each with 'file_path' and 'instance_mask_path') and "
                                 f"'instances'; delete {path.parent} to make the masks again from clicks.json")
    return index


def has_given_masks(meta: Dict) -> bool:
    """Whether ``transforms.json`` itself lists masks that were not made from clicks."""
    listed = any("instance_mask_path" in f for f in meta.get("frames", []))
    return listed and meta.get(MASKS_SOURCE_KEY, "ground_truth") != "clicks"


def evaluation_frames(meta: Dict) -> Optional[set]:
    """The ``file_path`` of every frame that ``train_filenames`` does not list; None without split lists."""
    train = meta.get("train_filenames")
    if not isinstance(train, list):
        return None
    return {f.get("file_path") for f in meta.get("frames", []) if isinstance(f, dict)} - set(train)


def masks_on_evaluation_frames_only(meta: Dict) -> bool:
    """Whether ``transforms.json`` gives instance masks on exactly its evaluation frames (and on no training
    frame): evaluation masks."""
    having = {f.get("file_path") for f in meta.get("frames", []) if isinstance(f, dict) and "instance_mask_path" in f}
    evaluation = evaluation_frames(meta)
    return bool(having) and evaluation is not None and having == evaluation


def split_evaluation_masks(meta: Dict) -> Dict:
    """``meta`` itself, or, when its masks are evaluation masks, a copy with them moved to
    ``frames[].evaluation_mask_path`` and its ``instances`` to ``evaluation_instances``."""
    if not masks_on_evaluation_frames_only(meta):
        return meta
    out = json.loads(json.dumps(meta))
    for frame in out["frames"]:
        if "instance_mask_path" in frame:
            frame[EVALUATION_MASK_KEY] = frame.pop("instance_mask_path")
    out[EVALUATION_INSTANCES_KEY] = out.pop("instances", [])
    return out


def with_click_masks(meta: Dict, data_dir: Path) -> Dict:
    """``transforms.json``'s contents with the masks of ``instance_masks/index.json`` in it (evaluation masks moved
    aside first, :func:`split_evaluation_masks`).

    Returns ``meta`` itself when there is no index, when ``transforms.json`` gives masks of its own, or when the
    index does not cover every frame (``transforms.json`` changed since: the masks are then made again). Otherwise a
    copy with ``frames[i].instance_mask_path``, ``instances``, ``instance_masks_source: "clicks"`` and the clicks'
    digest set from the index.
    """
    meta = split_evaluation_masks(meta)
    index = read_index(data_dir)
    if index is None or has_given_masks(meta):
        return meta
    by_file = {str(f["file_path"]): str(f["instance_mask_path"]) for f in index["frames"]}
    frames = meta.get("frames", [])
    if any(str(f.get("file_path")) not in by_file for f in frames):
        return meta
    for frame in frames:
        path = Path(data_dir) / by_file[str(frame["file_path"])]
        if not path.exists():
            raise DatasetFormatError(f"{path}: instance mask listed in {index_path(data_dir)} not found; delete "
                                     f"{path.parent} to make the masks again from clicks.json")
    out = json.loads(json.dumps(meta))
    for frame in out["frames"]:
        frame["instance_mask_path"] = by_file[str(frame["file_path"])]
    out["instances"] = index["instances"]
    out[MASKS_SOURCE_KEY] = "clicks"
    out.pop(CLICKS_DIGEST_KEY, None)
    if index.get("clicks_digest"):
        out[CLICKS_DIGEST_KEY] = index["clicks_digest"]
    return out


def read_dataset_meta(data_dir: Path) -> Dict:
    """``DATA/transforms.json`` as :func:`with_click_masks` gives it."""
    return with_click_masks(json.loads((Path(data_dir) / "transforms.json").read_text()), data_dir)
