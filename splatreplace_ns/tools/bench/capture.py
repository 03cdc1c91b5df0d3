"""``splatreplace bench capture``: the photos-only path (COLMAP poses) against exact poses, ours and 3DGS*.

One synthetic preset, as a user would capture it:

1. the scene is rendered twice from the same cameras: at the training size (the demo's, the truth for scoring)
   and, as the *photos*, at ``photo_scale`` times that size (SIFT finds too few features at 128x96 for COLMAP to
   pose such a scene);
2. only the photos of the training views go to ``ns-process-data images`` (COLMAP, CPU SIFT, offline), which
   also writes their copies downscaled to the training size; the clicks are moved onto the processed file names;
3. ours and the 3DGS* baseline train on the posed photos at the training size, with the same budget, side by side
   (``bench.template.train_ours_and_baseline``); and again on the exact poses (the path every other benchmark
   takes);
4. scoring happens on the *true* test views: a similarity fitted from the COLMAP-posed training cameras to their
   true cameras maps the true test cameras into the COLMAP frame (a view COLMAP did not pose is still scored),
   and each run renders them there. Masked PSNR inside the union of the true instance masks, full PSNR, mIoU of
   ours' replaced scene against the true masks, wall time of every stage including COLMAP.
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import cv2
import numpy as np
import torch

from splatreplace_ns.tools.bench.output import fmt_number as _fmt, write_result_json
from splatreplace_ns.tools.demo import DemoCommand
from splatreplace_ns.eval.alignment import centre_errors, similarity_pose


# ------------------------------------------------------------------ photos → ns-process-data → a capture
def training_photos(scene: Path, out: Path) -> List[str]:
    """Copies the images of a scene's training views (``train_filenames``) into ``out`` — what a user has: photos
    without poses, masks or depth. Returns the copied file names, sorted."""
    meta = json.loads((Path(scene) / "transforms.json").read_text())
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    names = []
    for file_path in meta.get("train_filenames") or [f["file_path"] for f in meta["frames"]]:
        shutil.copy2(Path(scene) / file_path, out / Path(file_path).name)
        names.append(Path(file_path).name)
    return sorted(names)


def ns_process_data(photos: Path, out: Path, num_downscales: int = 0,
                    matching: Literal["sequential", "exhaustive"] = "sequential",
                    camera_type: Literal["perspective", "pinhole"] = "perspective") -> Dict:
    """Runs ``ns-process-data images`` on a folder of photos, offline (COLMAP with CPU SIFT; ``sequential`` or
    ``exhaustive`` matching need no vocabulary tree download). ``perspective``: COLMAP's OPENCV camera (focal
    lengths, principal point, radial and tangential distortion), what ns-process-data uses by default; ``pinhole``:
    no distortion.

    Returns:
        {"seconds", "posed", "photos", "log"} (``posed``: frames in the written transforms.json).
    Raises:
        RuntimeError: with the end of the log when it fails or writes no transforms.json.
    """
    command = [str(Path(sys.executable).parent / "ns-process-data"), "images", "--data", str(photos),
               "--output-dir", str(out), "--no-gpu", "--matching-method", matching,
               "--num-downscales", str(num_downscales), "--camera-type", camera_type]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    log = result.stdout + result.stderr
    transforms = Path(out) / "transforms.json"
    if result.returncode != 0 or not transforms.exists():
        raise RuntimeError(f"ns-process-data failed on {photos} (exit {result.returncode}): ...{log[-2000:]}")
    posed = len(json.loads(transforms.read_text())["frames"])
    return {"seconds": seconds, "posed": posed, "photos": len(list(Path(photos).iterdir())), "log": log,
            "command": " ".join(command)}


def _read_rgb(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(f"{path}: not a readable image")
    return image.astype(np.float32)


def processed_names(photos: Path, processed: Path) -> Dict[str, str]:
    """Which processed frame each photo became: photo file name → ``file_path`` in the processed transforms.json.

    ``ns-process-data`` renames the photos (``frame_00001.png``, ...) and leaves out those COLMAP did not pose. Each
    processed image is matched to the photo it is a copy of by its pixels (smallest mean squared difference; a
    copy is exact or nearly so), not by the order of the names. A photo with no posed frame is absent.
    """
    meta = json.loads((Path(processed) / "transforms.json").read_text())
    photo_paths = sorted(p for p in Path(photos).iterdir() if p.is_file())
    photo_pixels = np.stack([_read_rgb(p) for p in photo_paths])  # [P, H, W, 3]
    out: Dict[str, str] = {}
    for frame in meta["frames"]:
        image = _read_rgb(Path(processed) / frame["file_path"])
        if image.shape != photo_pixels.shape[1:]:
            raise ValueError(f"{frame['file_path']}: {image.shape[1]}x{image.shape[0]}, the photos are "
                             f"{photo_pixels.shape[2]}x{photo_pixels.shape[1]}")
        errors = ((photo_pixels - image[None]) ** 2).mean(axis=(1, 2, 3))
        best = int(np.argmin(errors))
        if errors[best] > 4.0:  # a copy differs by rounding at most
            raise ValueError(f"{frame['file_path']} is a copy of no photo (closest {photo_paths[best].name}, "
                             f"mean squared difference {errors[best]:.1f})")
        if photo_paths[best].name in out:
            raise ValueError(f"{frame['file_path']} and {out[photo_paths[best].name]} are both {photo_paths[best].name}")
        out[photo_paths[best].name] = frame["file_path"]
    return out


def _inner_pixel(mask: np.ndarray) -> Tuple[int, int]:
    """(x, y) of the pixel of a boolean [H, W] mask furthest from its border."""
    distance = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)
    y, x = np.unravel_index(int(np.argmax(distance)), distance.shape)
    return int(x), int(y)


def capture_clicks(scene: Path, names: Dict[str, str], scale: float = 1.0) -> List[Dict]:
    """The scene's clicks on the processed file names (pixels multiplied by ``scale``: processed size / scene size).

    A click on a photo COLMAP did not pose moves to the posed training view that shows its instance largest (at
    the pixel furthest inside the instance's true mask there). The true ``id`` of each click is kept.
    """
    scene = Path(scene)
    clicks = json.loads((scene / "clicks.json").read_text())
    meta = json.loads((scene / "transforms.json").read_text())
    mask_of = {Path(f["file_path"]).name: scene / f["instance_mask_path"] for f in meta["frames"]}
    out = []
    for click in clicks:
        name = Path(click["file_path"]).name
        xy = click["xy"]
        if name not in names:
            areas = {n: int((cv2.imread(str(mask_of[n]), cv2.IMREAD_UNCHANGED) == click["id"]).sum()) for n in names}
            name = max(areas, key=areas.get)
            if areas[name] == 0:
                raise ValueError(f"instance {click['id']} is in no photo COLMAP posed")
            xy = _inner_pixel(cv2.imread(str(mask_of[name]), cv2.IMREAD_UNCHANGED) == click["id"])
        out.append(dict(click, file_path=names[name], xy=[float(xy[0]) * scale, float(xy[1]) * scale]))
    return out


def posed_centres(scene: Path, processed: Path, names: Dict[str, str]) -> Tuple[np.ndarray, np.ndarray, List[str]]:
    """Camera centres of the posed photos: (recovered [N, 3] as saved in the processed transforms.json, true [N, 3]
    from the scene, photo names [N])."""
    true = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"])
            for f in json.loads((Path(scene) / "transforms.json").read_text())["frames"]}
    saved = {f["file_path"]: np.asarray(f["transform_matrix"])
             for f in json.loads((Path(processed) / "transforms.json").read_text())["frames"]}
    order = sorted(names)
    return (np.stack([saved[names[n]][:3, 3] for n in order]), np.stack([true[n][:3, 3] for n in order]), order)


def capture_at_size(processed: Path, factor: int, out: Path, clicks: List[Dict]) -> Path:
    """The processed capture at 1/``factor`` of its size, as a dataset folder of its own: the ``images_<factor>``
    copies ``ns-process-data`` wrote, the intrinsics divided by ``factor`` (what nerfstudio's own
    ``downscale_factor`` does), ``applied_transform`` and point cloud kept, every frame a training frame (two
    listed as test frames: the benchmark scores the true test views itself), and ``clicks`` (already on the
    processed names, in pixels of the smaller images) as its clicks.json."""
    processed, out = Path(processed), Path(out)
    meta = json.loads((processed / "transforms.json").read_text())
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    source = processed / (f"images_{factor}" if factor > 1 else "images")
    for frame in meta["frames"]:
        shutil.copy2(source / Path(frame["file_path"]).name, out / "images" / Path(frame["file_path"]).name)
    for key in ("fl_x", "fl_y", "cx", "cy"):
        meta[key] = float(meta[key]) / factor
    meta["w"], meta["h"] = int(meta["w"]) // factor, int(meta["h"]) // factor
    names = sorted(f["file_path"] for f in meta["frames"])
    meta["train_filenames"], meta["test_filenames"] = names, names[:2]
    if meta.get("ply_file_path"):
        shutil.copy2(processed / meta["ply_file_path"], out / meta["ply_file_path"])
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    (out / "clicks.json").write_text(json.dumps(clicks, indent=2) + "\n")
    return out


# ------------------------------------------------------------------ scoring on the true test views
def _read_image(path: Path) -> torch.Tensor:
    """[H, W, 3 or 4] float in [0, 1], RGB(A)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FileNotFoundError(f"{path}: not a readable image")
    image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA if image.shape[-1] == 4 else cv2.COLOR_BGR2RGB)
    return torch.from_numpy(image.astype(np.float32) / 255.0)


@torch.no_grad()
def score_true_views(pipeline, data: Path, c2w_saved: np.ndarray, intrinsics: Dict, images: List[Path],
                     masks: List[Path]) -> Dict:
    """Renders a trained run from given cameras and scores it against the true images inside their true masks.

    Args:
        pipeline: a trained splat-replace pipeline (ours or the baseline).
        data: the dataset folder it trained on (its transforms.json says how its saved poses reach the model's
            normalised frame: ``applied_transform``, dataparser transform and scale).
        c2w_saved: [V, 4, 4] camera→world (OpenGL axes) in the frame of the poses saved in ``data``'s
            transforms.json (for a COLMAP capture: the true cameras moved there by the similarity fit).
        intrinsics: {"fl_x", "fl_y", "cx", "cy", "w", "h"} of the true views (pinhole).
        images, masks: [V] the true images and instance masks (16-bit ids, 0 = background).
    Returns:
        {"psnr", "psnr_masked": means over the views, "miou", "iou", "per_view": [...]} (``miou`` of the
        rendered instance ids against the true masks, through the clicks' true ids; None for a run without
        instances).
    """
    from nerfstudio.cameras.cameras import Cameras, CameraType

    from splatreplace_ns.datamanager.dataparser import saved_to_normalised
    from splatreplace_ns.eval.metrics import psnr
    from splatreplace_ns.eval.report import instance_gt_ids
    from splatreplace_ns.eval.segmentation import segmentation_scores

    model = pipeline.model
    model.eval()
    outputs_meta = pipeline.datamanager.train_dataparser_outputs
    meta = json.loads((Path(data) / "transforms.json").read_text())
    to_model = saved_to_normalised(np.asarray(outputs_meta.dataparser_transform), meta, Path(data))
    scale = float(outputs_meta.dataparser_scale)
    with_instances = bool(getattr(model, "instances", None)) and hasattr(pipeline, "clicks_path")
    mapping = instance_gt_ids(pipeline)[0] if with_instances else {}
    rows, preds, gts = [], [], []
    for view, (c2w, image_path, mask_path) in enumerate(zip(c2w_saved, images, masks)):
        pose = to_model @ np.asarray(c2w, dtype=np.float64)
        pose[:3, 3] *= scale
        camera = Cameras(camera_to_worlds=torch.from_numpy(pose[:3]).float()[None],
                         fx=float(intrinsics["fl_x"]), fy=float(intrinsics["fl_y"]), cx=float(intrinsics["cx"]),
                         cy=float(intrinsics["cy"]), width=int(intrinsics["w"]), height=int(intrinsics["h"]),
                         camera_type=CameraType.PERSPECTIVE).to(pipeline.device)
        outputs = model.get_outputs_for_camera(camera)
        gt_rgb = model.composite_with_background(model.get_gt_img(_read_image(image_path).to(pipeline.device)),
                                                 outputs["background"])
        gt_ids = torch.from_numpy(cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED).astype(np.int64))
        rows.append({"view": view, "image": Path(image_path).name, "psnr": psnr(outputs["rgb"], gt_rgb),
                     "psnr_masked": psnr(outputs["rgb"], gt_rgb, (gt_ids > 0).to(pipeline.device))})
        if mapping:
            preds.append(model.render_instance_ids(camera).cpu())
            gts.append(gt_ids)

    def mean(key: str) -> Optional[float]:
        values = [r[key] for r in rows if r[key] is not None]
        return float(np.mean(values)) if values else None

    result = {"psnr": mean("psnr"), "psnr_masked": mean("psnr_masked"), "miou": None, "iou": None, "per_view": rows}
    if mapping:
        seg = segmentation_scores(torch.stack(preds), torch.stack(gts), mapping)
        result.update(miou=seg["miou"], iou=seg["iou"])
    return result


def true_test_views(scene: Path) -> Tuple[np.ndarray, Dict, List[Path], List[Path]]:
    """The scene's test views: (c2w [V, 4, 4] OpenGL, intrinsics, image paths [V], mask paths [V])."""
    meta = json.loads((Path(scene) / "transforms.json").read_text())
    by_path = {f["file_path"]: f for f in meta["frames"]}
    frames = [by_path[p] for p in meta["test_filenames"]]
    intrinsics = {k: meta[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
    return (np.stack([np.asarray(f["transform_matrix"], dtype=np.float64) for f in frames]), intrinsics,
            [Path(scene) / f["file_path"] for f in frames], [Path(scene) / f["instance_mask_path"] for f in frames])


# ------------------------------------------------------------------ the benchmark
@dataclass
class BenchCaptureConfig:
    """Photos only (ns-process-data / COLMAP poses) against exact poses: ours and 3DGS*, scored on the true test views."""

    preset: str = "office"
    """Synthetic preset."""
    res: str = DemoCommand.res
    """Training size WxH (default: the demo's); the true test views are scored at this size."""
    photo_scale: int = 2
    """The photos are rendered at this multiple of --res (a power of two): COLMAP needs the detail; ns-process-data
    writes the copies at --res that training reads."""
    n_train: int = DemoCommand.n_train
    """Training views (the photos)."""
    n_test: int = DemoCommand.n_test
    """Test views (scored, never given to COLMAP)."""
    base_iterations: int = DemoCommand.base_iterations
    """Base 3DGS* iterations of ours (the baseline gets base + contrastive + finetune)."""
    contrastive_iterations: int = DemoCommand.contrastive_iterations
    """Contrastive-feature iterations of ours."""
    finetune_iterations: int = DemoCommand.finetune_iterations
    """Shared-template fine-tuning iterations of ours."""
    matching: Literal["sequential", "exhaustive"] = "sequential"
    """COLMAP's feature matching in ns-process-data (sequential: each photo with its neighbours along the capture)."""
    camera_type: Literal["perspective", "pinhole"] = "pinhole"
    """COLMAP's camera model in ns-process-data: pinhole (the simulator's photos have no lens distortion) or
    perspective (OPENCV, with distortion: ns-process-data's default for real photos)."""
    exact: bool = True
    """Also train both on the scene with its exact poses (the row the photos-only path is compared with)."""
    json: Optional[Path] = None
    """Where to write the results (default: benchmarks/results/capture_<preset>.json)."""
    data_root: Path = Path("benchmarks/data/capture")
    """Generated scenes and the processed photos are kept here (scenes are reused)."""
    out_dir: Path = Path("benchmarks/runs/capture")
    """Training outputs."""
    sequential: bool = False
    """Train the baseline after ours instead of beside it (beside: each on half of the CPU cores)."""

    def main(self) -> Dict:
        result = run_capture_bench(self)
        print_table(result)
        write_result_json(result, self.json or Path(f"benchmarks/results/capture_{self.preset}.json"))
        return result


def _scene(cfg: BenchCaptureConfig, res: str) -> Path:
    from splatreplace_ns.tools.sim import is_current_scene, make_scene

    data = cfg.data_root / f"{cfg.preset}_{res}_{cfg.n_train}v{cfg.n_test}"
    if not is_current_scene(data):
        make_scene(cfg.preset, data, res=res, seed=0, n_train=cfg.n_train, n_test=cfg.n_test)
    return data


def _train_and_score(cfg: BenchCaptureConfig, data: Path, out: Path, c2w_saved: np.ndarray, truth: Tuple) -> Dict:
    """Ours and the baseline on one dataset (``bench.template.train_ours_and_baseline``), both scored on the true
    test views with :func:`score_true_views`; seconds per stage of ours (``bench.suite.StageClock``)."""
    import gc

    from splatreplace_ns.tools.bench.stage_clock import StageClock
    from splatreplace_ns.tools.bench.template import train_ours_and_baseline

    B, C, F = cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations
    clock = StageClock(B, C, F)
    start = time.perf_counter()
    try:
        pair = train_ours_and_baseline(data, out, B, C, F, parallel=not cfg.sequential, after_step=clock)
    except (ValueError, RuntimeError) as err:  # a refused click or a failed run: the row says why, the others go on
        print(f"[capture] {data.name}: ours stopped: {err}", flush=True)
        return {"error": f"{type(err).__name__}: {err}", "failed_after_s": time.perf_counter() - start,
                "time_s": dict(clock.times)}
    _, intrinsics, images, masks = truth
    pipeline = pair["ours_trainer"].pipeline
    start = time.perf_counter()
    ours = score_true_views(pipeline, data, c2w_saved, intrinsics, images, masks)
    baseline = score_true_views(pair["baseline_pipeline"], data, c2w_saved, intrinsics, images, masks)
    times = pair["times"]
    row = {
        "ours": ours, "baseline": baseline,
        "gain_masked": None if ours["psnr_masked"] is None or baseline["psnr_masked"] is None
        else ours["psnr_masked"] - baseline["psnr_masked"],
        "replaced": bool(pipeline.model.has_templates),
        "registration": {int(k): {"success": v["success"], "message": v["message"]}
                         for k, v in (getattr(pipeline.model, "registration", None) or {}).items()},
        "ns_eval": {"ours": {k: pair["ours"].get(k) for k in ("psnr", "psnr_masked")},
                    "baseline": {k: pair["baseline"].get(k) for k in ("psnr", "psnr_masked")}},
        "time_s": {**clock.stages(times["ours"], times.get("segmentation", 0.0), times.get("registration", 0.0)),
                   "ours": times["ours"], "baseline": times["baseline"], "scoring": time.perf_counter() - start},
        "baseline_beside_ours": pair["parallel"],
    }
    del pair, pipeline
    gc.collect()
    return row


def run_capture_bench(cfg: BenchCaptureConfig) -> Dict:
    from splatreplace_ns.eval.alignment import similarity_fit
    from splatreplace_ns.eval.report import versions

    factor = int(cfg.photo_scale)
    if factor < 1 or factor & (factor - 1):
        raise ValueError(f"--photo-scale must be a power of two (ns-process-data halves the photos), got {factor}")
    w, h = (int(v) for v in cfg.res.lower().split("x"))
    cores = os.cpu_count() or 1
    torch.set_num_threads(max(1, cores if cfg.sequential else cores // 2))
    t0 = time.perf_counter()
    times: Dict[str, float] = {}
    start = time.perf_counter()
    truth_scene = _scene(cfg, cfg.res)
    photo_scene = _scene(cfg, f"{w * factor}x{h * factor}") if factor > 1 else truth_scene
    times["sim"] = time.perf_counter() - start
    work = cfg.data_root / f"{cfg.preset}_{cfg.res}x{factor}_{cfg.n_train}v{cfg.n_test}_{cfg.matching}_{cfg.camera_type}"
    photos, processed = work / "photos", work / "processed"
    training_photos(photo_scene, photos)
    if processed.exists():
        shutil.rmtree(processed)
    print(f"[capture] ns-process-data on {len(list(photos.iterdir()))} photos at {w * factor}x{h * factor} ...", flush=True)
    colmap = ns_process_data(photos, processed, num_downscales=int(math.log2(factor)), matching=cfg.matching,
                             camera_type=cfg.camera_type)
    (work / "ns_process_data.log").write_text(colmap["log"])
    times["ns_process_data"] = colmap["seconds"]
    names = processed_names(photos, processed)
    recovered, true, _ = posed_centres(photo_scene, processed, names)
    errors, _ = centre_errors(recovered, true)
    fit = similarity_fit(true, recovered)  # true frame → the frame of the saved COLMAP poses
    print(f"[capture] COLMAP posed {colmap['posed']} of {colmap['photos']} photos in {colmap['seconds']:.0f} s; camera "
          f"centres after the similarity fit: mean {errors.mean() * 100:.2f} cm, max {errors.max() * 100:.2f} cm", flush=True)
    capture = capture_at_size(processed, factor, work / "capture", capture_clicks(truth_scene, names))
    truth = true_test_views(truth_scene)
    B, C, F = cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations
    runs = cfg.out_dir / f"{work.name}_{B}-{C}-{F}"
    print("[capture] training ours and 3DGS* on the photos' COLMAP poses ...", flush=True)
    rows = {"photos": _train_and_score(cfg, capture, runs / "photos", similarity_pose(truth[0], *fit), truth)}
    if cfg.exact:
        print("[capture] training ours and 3DGS* on the exact poses ...", flush=True)
        rows["exact"] = _train_and_score(cfg, truth_scene, runs / "exact", truth[0], truth)
    return {
        "benchmark": "capture",
        "preset": cfg.preset,
        "parameters": {"res": cfg.res, "photo_res": f"{w * factor}x{h * factor}", "n_train": cfg.n_train,
                       "n_test": cfg.n_test, "base_iterations": B, "contrastive_iterations": C,
                       "finetune_iterations": F, "baseline_iterations": B + C + F, "matching": cfg.matching,
                       "camera_type": cfg.camera_type},
        "colmap": {"posed": colmap["posed"], "photos": colmap["photos"], "seconds": colmap["seconds"],
                   "command": colmap["command"],
                   "centre_error_m": {"mean": float(errors.mean()), "max": float(errors.max())},
                   "similarity_scale": float(fit[0])},
        "rows": rows,
        "time_s": {**times, "total": time.perf_counter() - t0},
        "machine": {"platform": platform.platform(), "cpu_count": cores, "cuda": torch.cuda.is_available()},
        "versions": versions(),
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()},
    }


def print_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    p, colmap = result["parameters"], result["colmap"]
    table = Table(title=f"bench capture: {result['preset']} at {p['res']} ({p['n_train']} photos at {p['photo_res']}, "
                        f"{p['n_test']} true test views), {p['base_iterations']}+{p['contrastive_iterations']}+"
                        f"{p['finetune_iterations']} iterations, 3DGS* {p['baseline_iterations']}")
    for col in ("poses", "posed", "masked PSNR 3DGS*", "masked PSNR ours", "gain", "full PSNR 3DGS* → ours", "mIoU",
                "base s", "contr.+seg. s", "reg. s", "fine-tune s", "ours s", "3DGS* s", "COLMAP s"):
        table.add_column(col)
    for name, row in result["rows"].items():
        t = row["time_s"]
        if "error" in row:
            table.add_row("COLMAP (photos only)" if name == "photos" else "exact",
                          f"{colmap['posed']}/{colmap['photos']}" if name == "photos" else "all",
                          *(["failed"] + [""] * 10), f"{colmap['seconds']:.0f}" if name == "photos" else "-")
            continue
        table.add_row(
            "COLMAP (photos only)" if name == "photos" else "exact",
            f"{colmap['posed']}/{colmap['photos']}" if name == "photos" else "all",
            _fmt(row["baseline"]["psnr_masked"]), _fmt(row["ours"]["psnr_masked"]), _fmt(row["gain_masked"], signed=True),
            f"{_fmt(row['baseline']['psnr'])} → {_fmt(row['ours']['psnr'])}", _fmt(row["ours"]["miou"], 3),
            f"{t['base']:.0f}", f"{t['contrastive'] + t['segmentation']:.0f}", f"{t['registration']:.0f}",
            f"{t['finetune']:.0f}", f"{t['ours']:.0f}", f"{t['baseline']:.0f}",
            f"{colmap['seconds']:.0f}" if name == "photos" else "-",
        )
    Console(width=200).print(table)
    for name, row in result["rows"].items():
        if "error" in row:
            print(f"{name}: {row['error']} (after {row['failed_after_s']:.0f} s)")
    print(f"camera centres after the similarity fit: mean {colmap['centre_error_m']['mean'] * 100:.2f} cm, "
          f"max {colmap['centre_error_m']['max'] * 100:.2f} cm; total {result['time_s']['total'] / 60:.1f} min")
