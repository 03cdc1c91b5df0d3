"""What each regime of ``bench suite --inputs`` hands the methods, as a dataset folder beside the scene.

* ``exact``: the scene as the simulator wrote it: images, camera poses, clicks, the true instance masks and depth
  of every frame, and a dense point cloud sampled from the true depth.
* ``user``: what a user has: the images, the camera poses and ``clicks.json``. No instance masks (ours makes them
  from the clicks), no depth, and the sparse point cloud COLMAP triangulates at the known poses
  (:mod:`splatreplace_ns.tools.bench.sparse_points`; random Gaussians when it finds too few points). The true
  masks stay on the test frames alone, as evaluation masks: they only score.
* ``user+masks``, ``user+depth``, ``user+points``: the user's regime with one input of the exact regime given
  back (the true masks of every frame, the true depth, the dense point cloud), to measure what each costs.
* ``user+colmap``: the user's regime with COLMAP's camera poses, intrinsics and sparse cloud instead of the true
  ones (``bench suite --inputs user --poses colmap``, :mod:`splatreplace_ns.tools.bench.colmap_poses`).

The folder ``<scene>_<regime>`` links the scene's images (and its masks, depth or cloud where given) and holds a
``transforms.json`` of its own; the scene itself is not changed. Both methods train on the same folder.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Dict, Tuple

INPUTS: Tuple[str, ...] = ("exact", "user", "user+masks", "user+depth", "user+points", "user+colmap")
GIVEN_BACK = {"user": (), "user+masks": ("masks",), "user+depth": ("depth",), "user+points": ("points",),
              "user+colmap": ()}
SPARSE_PLY = "sparse_points.ply"
REPORT_NAME = "inputs.json"


def regime_folder(scene: Path, inputs: str) -> Path:
    """The dataset folder of ``scene`` in regime ``inputs`` (the scene itself for ``exact``)."""
    if inputs not in INPUTS:
        raise ValueError(f"--inputs must be one of {', '.join(INPUTS)}, got {inputs!r}")
    return scene if inputs == "exact" else scene.parent / f"{scene.name}_{inputs.replace('+', '-')}"


def scene_of(folder: Path, inputs: str) -> Path:
    """The scene a regime's folder was made from (:func:`regime_folder`'s inverse)."""
    suffix = "" if inputs == "exact" else f"_{inputs.replace('+', '-')}"
    return folder.parent / folder.name[: len(folder.name) - len(suffix)] if suffix and folder.name.endswith(suffix) else folder


def inputs_report(folder: Path) -> Dict:
    """The regime folder's ``inputs.json`` ({} for a scene as the simulator wrote it)."""
    path = Path(folder) / REPORT_NAME
    return json.loads(path.read_text()) if path.exists() else {}


def _link(target_dir: Path, name: str, source: Path) -> None:
    """``target_dir/name`` → ``source`` as a relative symbolic link (replaced when present)."""
    link = target_dir / name
    if link.is_symlink() or link.exists():
        link.unlink() if link.is_symlink() or link.is_file() else shutil.rmtree(link)
    link.symlink_to(os.path.relpath(source, target_dir))


def user_transforms(meta: Dict, given: Tuple[str, ...], sparse_ply: str = "") -> Dict:
    """The scene's ``transforms.json`` with what a regime withholds taken out.

    Args:
        meta: the exact scene's transforms.json (split lists, frames with ``instance_mask_path`` and
            ``depth_file_path``, ``ply_file_path``).
        given: which of "masks", "depth", "points" the regime gives back.
        sparse_ply: the sparse cloud's file name, or "" for random Gaussians (ignored when "points" is given).
    """
    out = json.loads(json.dumps(meta))
    train = set(out["train_filenames"])
    for frame in out["frames"]:
        if "depth" not in given:
            frame.pop("depth_file_path", None)
        if "masks" not in given and frame["file_path"] in train:
            frame.pop("instance_mask_path", None)  # the test frames keep theirs: evaluation masks
    if "depth" not in given:
        out.pop("depth_unit_scale_factor", None)
        out.pop("depth_zero", None)
    if "points" not in given:
        out.pop("ply_file_path", None)
        if sparse_ply:
            out["ply_file_path"] = sparse_ply
    return out


def make_regime_folder(scene: Path, inputs: str) -> Path:
    """Writes (or reuses) the dataset folder of ``scene`` in regime ``inputs``. → the folder.

    Its ``inputs.json`` records the regime and the sparse cloud's report; a folder written for the same scene
    files is reused as it is (the point cloud is triangulated once).
    """
    from splatreplace_ns.tools.bench.sparse_points import write_sparse_cloud

    folder = regime_folder(scene, inputs)
    if inputs == "exact":
        return scene
    given = GIVEN_BACK[inputs]
    meta = json.loads((scene / "transforms.json").read_text())
    stamp = {"inputs": inputs, "scene": scene.name, "scene_transforms": _digest(scene / "transforms.json")}
    report_path = folder / REPORT_NAME
    if report_path.exists():
        saved = json.loads(report_path.read_text())
        if {k: saved.get(k) for k in stamp} == stamp and (folder / "transforms.json").exists():
            return folder
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for name in ("images", "masks") + (("depth",) if "depth" in given else ()):
        _link(folder, name, scene / name)
    if inputs == "user+colmap":
        from splatreplace_ns.tools.bench.colmap_poses import write_colmap_regime

        colmap = write_colmap_regime(scene, folder)
        report_path.write_text(json.dumps({**stamp, "given_back": [], "colmap": colmap,
                                           "sparse_points": {"points": colmap["sparse_points"]}}, indent=2) + "\n")
        return folder
    shutil.copy2(scene / "clicks.json", folder / "clicks.json")
    sparse = {}
    if "points" in given:
        _link(folder, meta["ply_file_path"], scene / meta["ply_file_path"])
    else:
        sparse = write_sparse_cloud(scene, folder / SPARSE_PLY)
    transforms = user_transforms(meta, given, SPARSE_PLY if sparse.get("written") else "")
    (folder / "transforms.json").write_text(json.dumps(transforms, indent=2) + "\n")
    report_path.write_text(json.dumps({**stamp, "given_back": list(given), "sparse_points": sparse}, indent=2) + "\n")
    return folder


def _digest(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]
