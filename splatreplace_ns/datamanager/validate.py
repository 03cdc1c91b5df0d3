"""The one check every command runs on a dataset before any work (:func:`check_dataset`): the JSON files against
:mod:`~splatreplace_ns.datamanager.schema`, then the files they name (:mod:`~splatreplace_ns.datamanager.file_checks`).
Every problem is one line of one ``DatasetFormatError`` that names the file and the field, instead of a
``KeyError``, an ``AssertionError`` or a ``JSONDecodeError`` from deep inside nerfstudio, or a failure after the
base stage has trained.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional

from splatreplace_ns.datamanager.click_masks import with_click_masks
from splatreplace_ns.datamanager.clicks import click_place_problems, read_clicks
from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.datamanager.file_checks import frame_file_problems, point_cloud_problems, read_json
from splatreplace_ns.datamanager.schema import SPLIT_LISTS, transforms_problems

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


def check_dataset(transforms_path: Path, clicks_path: Optional[Path] = None) -> Dict:
    """Checks a dataset before any work: ``transforms.json`` against :mod:`~splatreplace_ns.datamanager.schema`,
    then every file it names (images, masks, depth maps, the point cloud) and ``clicks.json`` when there is one.

    Every problem found is reported at once, one line each naming the file (and the field): a
    ``DatasetFormatError`` whose ``problems`` are those lines. Returns the contents of ``transforms.json``.

    Args:
        transforms_path: the dataset's ``transforms.json``.
        clicks_path: its clicks file (checked when it exists); each click must name a frame and lie on a pixel of
            its image file (whether that frame trains is the pipeline's check).
    """
    path = Path(transforms_path)
    meta = read_json(path, "transforms.json")
    problems = [f"{path}: {line}" for line in transforms_problems(meta)]
    if not isinstance(meta, dict):
        raise DatasetFormatError(problems)
    data_dir = path.parent
    # masks made from clicks are checked like given ones; the files of a frame that is not valid are not
    sizes, file_problems = frame_file_problems(meta if problems else with_click_masks(meta, data_dir), data_dir)
    problems += file_problems
    if isinstance(meta.get("ply_file_path"), str) and meta["ply_file_path"]:
        problems += point_cloud_problems(data_dir / meta["ply_file_path"])
    if clicks_path is not None and Path(clicks_path).exists():
        clicks, click_problems = read_clicks(clicks_path)
        places = click_place_problems(clicks, sizes, f"a frame of {path}")
        problems += click_problems + [f"{clicks_path}: {line}" for line in places]
    if problems:
        raise DatasetFormatError(problems)
    return meta
