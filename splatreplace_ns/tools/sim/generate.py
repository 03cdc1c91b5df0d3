"""Generate a dataset: cameras → rendered frames → files (images, masks, depth, JSON, PLY, contact sheet).

Everything random is drawn from generators seeded by ``(seed, stream[, frame])``, so the bytes written
depend only on the arguments, not on how frames are spread over worker processes.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import shutil
import warnings
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional, Union

import cv2
import numpy as np

from splatreplace_ns.tools.sim.cameras import PinholeCamera, intrinsics, nearest_distances, trajectory
from splatreplace_ns.tools.sim.presets import Preset, get_preset
from splatreplace_ns.tools.sim.render import Frame, Renderer
from splatreplace_ns.tools.sim.scene import instances_json
from splatreplace_ns.tools.sim.writer import (
    DEPTH_SCALE,
    contact_sheet,
    choose_click_view,
    click_candidates,
    depth_to_u16,
    write_json,
    write_ply,
    write_rgb,
    write_u16,
)

GENERATOR_VERSION = 4  # 2: open-sky scenes' transforms.json says depth 0 is far (the sky); 3: clicks in the middle;
# 4: effects list slanted_sun and per_copy_appearance; instance coverage of the training views; random scenes
_SUBDIRS = ("images", "masks", "depth")
_STREAM_CAMERAS, _STREAM_POINTS = 1, 2  # stream 0 is the layout (Preset.layout)
_POINT_VOXEL = 0.015  # metres; SfM-like points are thinned to one per voxel

Resolution = Union[str, tuple[int, int], None]


def parse_res(res: Resolution) -> Optional[tuple[int, int]]:
    """``"WxH"`` or (W, H) → (W, H); None stays None."""
    if res is None:
        return None
    if isinstance(res, str):
        parts = res.lower().split("x")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise ValueError(f"resolution must look like 320x240, got {res!r}")
        res = (int(parts[0]), int(parts[1]))
    w, h = int(res[0]), int(res[1])
    if w < 8 or h < 8:
        raise ValueError(f"resolution {w}x{h} is too small (minimum 8x8)")
    return w, h


def _frame_name(i: int) -> str:
    return f"{i:04d}.png"


def _sample_points(frame: Frame, rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """SfM-like surface samples of one training view: noisy positions (noise grows with depth), noisy colours.

    Returns:
        xyz (K, 3) float32, rgb (K, 3) uint8 with K <= count.
    """
    hit = np.flatnonzero(frame.depth.ravel() > 0)
    pick = np.sort(rng.choice(hit, size=min(count, hit.size), replace=False))
    depth = frame.depth.ravel()[pick].astype(np.float64)
    xyz = frame.points.reshape(-1, 3)[pick].astype(np.float64)
    xyz += rng.normal(0.0, 1.0, xyz.shape) * (0.002 + 0.003 * depth)[:, None]
    rgb = frame.rgb.reshape(-1, 3)[pick].astype(np.float64) + rng.normal(0.0, 3.0, (pick.size, 3))
    return xyz.astype(np.float32), np.clip(np.round(rgb), 0, 255).astype(np.uint8)


def _thin(xyz: np.ndarray, rgb: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Keep the first point of every voxel (order preserved); (N, 3), (N, 3) → (M, 3), (M, 3)."""
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    return xyz[first], rgb[first]


# ----------------------------------------------------------------------------- rendering jobs

FrameResult = tuple[int, dict, Optional[tuple[np.ndarray, np.ndarray]]]
_worker_state: dict = {}  # per worker process: the renderer and the job constants


def _render_frames(
    renderer: Renderer, jobs: list[tuple[int, PinholeCamera, bool]], out: Path, seed: int, n_points: int
) -> list[FrameResult]:
    """Render frames and write their PNGs.

    Args:
        renderer: the scene's renderer.
        jobs: (frame index, camera, is a training view) per frame.
        out: dataset folder.
        seed: dataset seed (point noise is drawn from (seed, stream, frame index)).
        n_points: SfM-like samples drawn per training view.
    Returns:
        per frame: (index, click candidates (training views; else {}), (xyz, rgb) samples or None).
    """
    results = []
    for index, cam, is_train in jobs:
        frame = renderer.render(cam)
        name = _frame_name(index)
        write_rgb(out / "images" / name, frame.rgb)
        write_u16(out / "masks" / name, frame.ids)
        write_u16(out / "depth" / name, depth_to_u16(frame.depth))
        if is_train:
            samples = _sample_points(frame, np.random.default_rng([seed, _STREAM_POINTS, index]), n_points)
            results.append((index, click_candidates(frame.ids), samples))
        else:
            results.append((index, {}, None))
    return results


def resolve_preset(name: str, seed: int = 0) -> Preset:
    """A named preset, or ``"random"``: the random scene drawn from ``seed``
    (:func:`~splatreplace_ns.tools.sim.random_scenes.random_preset`)."""
    if name == "random":
        from splatreplace_ns.tools.sim.random_scenes import random_preset

        return random_preset(seed)
    return get_preset(name)


def _init_worker(preset_name: str, seed: int, out: Path, n_points: int, light: str = "preset") -> None:
    """Worker-process initialiser: rebuild the (deterministic) scene once per process."""
    p = resolve_preset(preset_name, seed)
    _worker_state.update(
        renderer=Renderer(p.layout(seed, light).scene, supersample=p.supersample), out=out, seed=seed, n_points=n_points
    )


def _worker_job(jobs: list[tuple[int, PinholeCamera, bool]]) -> list[FrameResult]:
    st = _worker_state
    return _render_frames(st["renderer"], jobs, st["out"], st["seed"], st["n_points"])


def _render_all(
    p: Preset,
    seed: int,
    cams: list[PinholeCamera],
    n_train: int,
    out: Path,
    n_points: int,
    workers: int,
    progress: Optional[Callable[[int, int], None]],
    light: str = "preset",
) -> dict[int, tuple[dict, Optional[tuple[np.ndarray, np.ndarray]]]]:
    """Render every camera, in this process or spread over ``workers`` processes (same bytes either way)."""
    total = len(cams)
    chunk = max(1, min(8, -(-total // (4 * max(workers, 1)))))
    chunks = [[(i, cams[i], i < n_train) for i in range(s, min(s + chunk, total))] for s in range(0, total, chunk)]
    results: dict[int, tuple[dict, Optional[tuple[np.ndarray, np.ndarray]]]] = {}

    def collect(batch: list[FrameResult]) -> None:
        for index, candidates, samples in batch:
            results[index] = (candidates, samples)
        if progress is not None:
            progress(len(results), total)

    if workers > 1:
        try:
            ctx = mp.get_context("spawn")  # no fork: the parent may hold threads (open3d, torch)
            with ProcessPoolExecutor(
                workers, mp_context=ctx, initializer=_init_worker, initargs=(p.name, seed, out, n_points, light)
            ) as ex:
                for batch in ex.map(_worker_job, chunks):
                    collect(batch)
            return results
        except BrokenProcessPool:
            warnings.warn("worker processes could not start; rendering in this process", RuntimeWarning, stacklevel=3)
    renderer = Renderer(p.layout(seed, light).scene, supersample=p.supersample)
    for jobs in chunks:
        if not all(j[0] in results for j in jobs):
            collect(_render_frames(renderer, jobs, out, seed, n_points))
    return results


def is_current_scene(out: Path) -> bool:
    """Whether OUT holds a scene written by this version of the generator (an older one is made again: the
    files it wrote then may say less than they do now)."""
    meta = Path(out) / "transforms.json"
    if not meta.exists():
        return False
    try:
        return json.loads(meta.read_text()).get("sim", {}).get("generator_version") == GENERATOR_VERSION
    except (json.JSONDecodeError, OSError, AttributeError):
        return False


def _prepare_output(out: Path) -> None:
    """Create OUT and empty sub-folders; refuse to clobber folders this generator did not write."""
    out.mkdir(parents=True, exist_ok=True)
    ours = False
    meta = out / "transforms.json"
    if meta.exists():
        try:
            ours = "sim" in json.loads(meta.read_text())
        except (json.JSONDecodeError, OSError):
            ours = False
        if not ours:
            raise FileExistsError(f"{meta} was not written by `splatreplace sim`; choose another OUT")
    for sub in _SUBDIRS:
        d = out / sub
        if d.exists() and any(d.iterdir()):
            if not ours:
                raise FileExistsError(
                    f"{d} is not empty and {out} was not written by `splatreplace sim`; choose another OUT"
                )
            shutil.rmtree(d)
        d.mkdir(exist_ok=True)


def make_scene(
    preset: str,
    out: Union[str, Path],
    *,
    res: Resolution = None,
    seed: int = 0,
    n_train: Optional[int] = None,
    n_test: Optional[int] = None,
    workers: Optional[int] = None,
    progress: Optional[Callable[[int, int], None]] = None,
    light: str = "preset",
) -> Path:
    """Write a synthetic repetitive scene with ground truth.

    Args:
        preset: name in :data:`PRESETS`, or "random" (the random scene drawn from ``seed``).
        out: output folder (created).
        res: "WxH" or (W, H); default: the preset's.
        seed: layout, camera and point-noise seed; the same arguments give the same bytes.
        n_train: training views (default: the preset's).
        n_test: test views (default: the preset's); val = test.
        workers: rendering processes (default: up to 2, fewer for small jobs); 1 renders in this process.
        progress: called as ``progress(done, total)`` after each rendered chunk.
        light: "preset" (as the preset draws it) or "overhead" (every directional light at the zenith:
            :func:`~splatreplace_ns.tools.sim.presets.overhead_lighting`).
    Returns:
        Path of the written transforms.json.
    """
    p: Preset = resolve_preset(preset, seed)
    out = Path(out)
    w, h = parse_res(res) or p.res
    n_train = p.n_train if n_train is None else int(n_train)
    n_test = p.n_test if n_test is None else int(n_test)
    if n_train < 1 or n_test < 1:
        raise ValueError(f"need at least one training and one test view, got n_train={n_train}, n_test={n_test}")

    layout = p.layout(seed, light)
    scene = layout.scene
    cam_rng = np.random.default_rng([seed, _STREAM_CAMERAS])
    poses = trajectory(layout.train_path, n_train, cam_rng) + trajectory(layout.test_path, n_test, cam_rng, phase=0.5)
    fx, fy, cx, cy = intrinsics(w, h, p.fov_deg)
    cams = [PinholeCamera(c2w, fx, fy, cx, cy, w, h) for c2w in poses]

    _prepare_output(out)
    n_points = max(200, (w * h) // 150)
    total = len(cams)
    if workers is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        workers = min(2, cores) if total * w * h >= 1_000_000 else 1
    results = _render_all(p, seed, cams, n_train, out, n_points, workers, progress, light)

    names = [f"images/{_frame_name(i)}" for i in range(total)]
    train_names, test_names = names[:n_train], names[n_train:]

    # clicks: for each instance, the middle of it in the training view that shows it best (click_candidates)
    per_instance: dict[int, dict[int, tuple[float, int, int, int]]] = {}
    for i in range(n_train):
        for k, candidate in results[i][0].items():
            per_instance.setdefault(k, {})[i] = candidate
    clicks = []
    for inst in scene.instances:
        if inst.id not in per_instance:
            raise ValueError(
                f"preset {p.name!r}, seed {seed}: instance {inst.id} ({inst.cls}) is never visible in the "
                f"{n_train} training views; use more training views"
            )
        i = choose_click_view(per_instance[inst.id])
        _, _, u, v = per_instance[inst.id][i]
        clicks.append({"file_path": names[i], "xy": [u, v], "class": inst.cls, "id": inst.id})

    coverage = {
        str(k): {"train_views": len(views), "train_pixels": int(sum(c[1] for c in views.values()))}
        for k, views in sorted(per_instance.items())
    }

    xyz = np.concatenate([results[i][1][0] for i in range(n_train)])
    rgb = np.concatenate([results[i][1][1] for i in range(n_train)])
    xyz, rgb = _thin(xyz, rgb, _POINT_VOXEL)
    write_ply(out / "points3d.ply", xyz, rgb)

    centres = np.stack([c.center for c in cams])
    mean_dist = float(nearest_distances(centres[n_train:], centres[:n_train]).mean())
    frames = [
        {
            "file_path": names[i],
            "transform_matrix": cams[i].c2w.tolist(),
            "instance_mask_path": f"masks/{_frame_name(i)}",
            "depth_file_path": f"depth/{_frame_name(i)}",
        }
        for i in range(total)
    ]
    meta = {
        "camera_model": "PINHOLE",
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx,
        "cy": cy,
        "w": w,
        "h": h,
        "depth_unit_scale_factor": DEPTH_SCALE,
        "ply_file_path": "points3d.ply",
        **({"depth_zero": "far"} if p.open_sky else {}),  # depth 0 is the sky there, not unknown depth
        "frames": frames,
        "train_filenames": train_names,
        "val_filenames": test_names,
        "test_filenames": test_names,
        "instances": instances_json(scene.instances),
        "sim": {
            "generator_version": GENERATOR_VERSION,
            "preset": p.name,
            "seed": seed,
            "effects": asdict(p.effects_lit(light)),
            "light": light,
            "resolution": [w, h],
            "n_train": n_train,
            "n_test": n_test,
            "supersample": p.supersample,
            "world_up": [0.0, 0.0, 1.0],
            "n_points": int(xyz.shape[0]),
            "mean_test_to_train_distance": mean_dist,
            "instance_coverage": coverage,
            **({"scene": p.details} if p.details else {}),
        },
    }
    transforms = out / "transforms.json"
    write_json(transforms, meta)
    write_json(out / "clicks.json", clicks)

    picks = [("train", i) for i in np.unique(np.linspace(0, n_train - 1, 3).round().astype(int))]
    picks += [("test", n_train + i) for i in np.unique(np.linspace(0, n_test - 1, 3).round().astype(int))]
    tiles = []
    for split, i in picks:
        rgb_i = cv2.imread(str(out / names[i]), cv2.IMREAD_COLOR)[..., ::-1]
        ids_i = cv2.imread(str(out / "masks" / _frame_name(i)), cv2.IMREAD_UNCHANGED)
        tiles.append((f"{split} {_frame_name(i)[:-4]}", rgb_i, ids_i))
    write_rgb(out / "contact_sheet.png", contact_sheet(tiles))
    return transforms
