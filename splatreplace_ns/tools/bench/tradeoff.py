"""``splatreplace bench tradeoff``: what accuracy costs in time.

One reference run of the whole method on a synthetic preset, then one knob changed at a time. Every point
reports the wall time of the stage it changes and of the whole run, and the accuracy it buys: masked
test-view PSNR, test-view segmentation mIoU and mean registration rotation error (all from the same
evaluation ``ns-eval`` runs). Sweeps and how each point is trained:

* ``baseline``: the 3DGS* baseline with the reference's total iterations (what the method must beat);
* ``base`` (base 3DGS* iterations) and ``res`` (image resolution): whole runs from scratch (the base
  learning-rate schedule depends on its length, and another resolution is another scene);
* ``contrastive`` (paper: 1k vs 5k): resumed from the reference's checkpoint at the end of the base stage;
* ``finetune`` (paper: 4k vs 7k): resumed from the reference's checkpoint at the end of segmentation;
* ``virtual_views`` (9 / 25 / 49) and ``matcher``: registration alone, on the reference's segmented
  checkpoint; their whole-run time is the reference's with its registration time replaced (marked
  ``"whole_time": "reference with this stage's time"``), and their masked PSNR is only measured with
  ``--finetune-registration-points`` (one fine-tuning run each).

The default budgets are the paper's scaled down so that the sweep runs in well under an hour on two CPU
cores (contrastive 1:5 and fine-tuning 4:7 as in the paper); every figure is labelled with the iterations
that produced it. Outputs: a table, JSON, and a Pareto plot PNG (masked PSNR against whole-run time;
rotation error against registration time).
"""

from __future__ import annotations

import os
import platform
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import torch

from splatreplace_ns.tools.bench.output import publish
from splatreplace_ns.tools.bench.scenes import cached_scene

SWEEPS = ("baseline", "base", "contrastive", "finetune", "virtual_views", "matcher", "res")
VIEW_GRIDS = {9: (3, 3), 25: (5, 5), 49: (7, 7)}
"""Virtual views per instance → (azimuths, elevations)."""


@dataclass
class BenchTradeoffConfig:
    """Accuracy (masked PSNR, mIoU, rotation error) against wall time, one budget changed at a time."""

    preset: str = "office"
    """Synthetic preset (office, temple, chess, ...)."""
    json: Optional[Path] = None
    """Where to write the results as JSON."""
    plot: Optional[Path] = None
    """Pareto plot PNG (default: beside --json, else benchmarks/results/tradeoff_PRESET.png)."""
    res: str = "96x72"
    """Resolution of the reference run (WxH)."""
    n_train: int = 40
    """Training views."""
    n_test: int = 6
    """Test views."""
    base_iterations: int = 1000
    """Base iterations of the reference run."""
    contrastive_iterations: int = 500
    """Contrastive iterations of the reference run (the paper's "1k"; 200 left the features too weak to
    segment at 96×72)."""
    finetune_iterations: int = 800
    """Fine-tuning iterations of the reference run (the paper's "7k")."""
    sweeps: Tuple[str, ...] = SWEEPS
    """Which knobs to sweep: baseline (3DGS* with the same total iterations), base, contrastive, finetune,
    virtual_views, matcher, res."""
    base_values: Tuple[int, ...] = (500, 2000)
    """Other base iteration counts."""
    contrastive_values: Tuple[int, ...] = (2500,)
    """Other contrastive iteration counts (2500 = 5 × the reference: the paper's "5k")."""
    finetune_values: Tuple[int, ...] = (457,)
    """Other fine-tuning iteration counts (457 = 4/7 of the reference: the paper's "4k")."""
    virtual_views: Tuple[int, ...] = (9, 49)
    """Other virtual view counts per instance (the reference uses 25): 9, 25 or 49."""
    matchers: Tuple[str, ...] = ("sift", "orb", "xfeat-lighterglue")
    """Other robust matchers (the reference uses xfeat); unavailable ones are reported and skipped."""
    res_values: Tuple[str, ...] = ("64x48", "128x96")
    """Other resolutions (whole runs on scenes generated at that resolution)."""
    finetune_registration_points: bool = False
    """Also fine-tune after each virtual-view / matcher point, to measure its masked PSNR (costs one
    fine-tuning run each)."""
    data_root: Path = Path("benchmarks/data")
    """Generated scenes are kept here and reused."""
    out_dir: Path = Path("benchmarks/runs")
    """Training outputs."""
    threads: int = 2
    """torch CPU threads."""
    split: Optional[Literal["dev", "report"]] = None
    """Sweep the whole run's budget on these scenes of the scene suite instead of one preset's knobs: each point
    is ``bench suite`` at --budget-scales × the demo's budget (ours against 3DGS* with the same total
    iterations), reusing the suite's runs of the same configuration; --preset, --sweeps and the per-knob values
    are then not used, the scenes have the suite's 48 + 8 views at --res."""
    seeds: Tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    """Scenes of --split (its seeds) for the budget sweep."""
    budget_scales: Tuple[float, ...] = (0.5, 1.0)
    """Budgets of the sweep, as multiples of the demo's 1500 + 500 + 1000 iterations."""
    training_seed: Optional[int] = None
    """Training seed of the sweep's runs (``bench suite --training-seed``; default: nerfstudio's 42)."""

    def main(self) -> Dict:
        if self.split is not None:
            from splatreplace_ns.tools.bench.budget_sweep import print_budget_table, run_budget_sweep, write_budget_plot

            return publish(run_budget_sweep(self), print_budget_table, self.json, self.plot,
                           Path(f"benchmarks/results/tradeoff_{self.split}.png"), write_budget_plot)
        return publish(run_tradeoff_bench(self), print_table, self.json, self.plot,
                       Path(f"benchmarks/results/tradeoff_{self.preset}.png"), write_pareto_plot)


# ----------------------------------------------------------------------------- pure helpers


def pareto_front(times: Sequence[float], scores: Sequence[float], higher_is_better: bool = True) -> List[int]:
    """Indices of the points no other point beats in both time (lower) and score, sorted by time.

    Args:
        times: [P] costs; scores: [P] accuracies (None/NaN points are never on the front).
    """
    sign = 1.0 if higher_is_better else -1.0
    points = [(t, sign * s, i) for i, (t, s) in enumerate(zip(times, scores))
              if t is not None and s is not None and np.isfinite(t) and np.isfinite(s)]
    front, best = [], -np.inf
    for t, s, i in sorted(points, key=lambda p: (p[0], -p[1])):
        if s > best:
            front.append(i)
            best = s
    return front


def stage_times(marks: Dict[str, float]) -> Dict[str, float]:
    """Stage wall times from the clock marks of one run.

    Args:
        marks: perf_counter values at "start" and "end", and when the run covers them "base" (end of the
            base stage) and "segmented" (end of contrastive training and segmentation). A run resumed at a
            stage boundary marks that boundary at its start.
    Returns:
        "total" and each of "base", "contrastive" (includes segmentation), "finetune" (includes registration)
        whose both ends are marked.
    """
    out: Dict[str, float] = {}
    for name, begin, end in (("base", "start", "base"), ("contrastive", "base", "segmented"), ("finetune", "segmented", "end")):
        if begin in marks and end in marks:
            out[name] = marks[end] - marks[begin]
    out["total"] = marks["end"] - marks["start"]
    return out


def gain_per_minute(point: Dict, reference: Dict) -> Dict[str, Optional[float]]:
    """What each extra minute of whole-run time buys over the reference (negative: what a saved minute costs).

    Returns:
        {"psnr_masked_db", "miou", "rot_err_deg"} per minute (rotation error: its decrease), None where a
        figure is missing or the times are equal.
    """
    minutes = (point["whole_time_s"] - reference["whole_time_s"]) / 60.0
    out: Dict[str, Optional[float]] = {}
    for key, name, sign in (("psnr_masked", "psnr_masked_db", 1.0), ("miou", "miou", 1.0), ("rot_err_deg_mean", "rot_err_deg", -1.0)):
        a, b = point.get(key), reference.get(key)
        out[name] = None if a is None or b is None or abs(minutes) < 1e-9 else sign * (a - b) / minutes
    return out


# ----------------------------------------------------------------------------- runs


def _accuracy(pipeline) -> Dict[str, Optional[float]]:
    """Test-view masked PSNR (and full PSNR), segmentation mIoU and registration rotation error (ns-eval's)."""
    pipeline.eval()
    metrics = pipeline.get_average_eval_image_metrics()
    seg, reg = metrics.get("segmentation") or {}, metrics.get("registration") or {}
    return {
        "psnr": metrics.get("psnr"),
        "psnr_masked": metrics.get("psnr_masked"),
        "miou": seg.get("miou"),
        "rot_err_deg_mean": reg.get("rotation_error_deg_mean"),
        "registered": reg.get("num_success"),
        "registration_attempts": reg.get("num_registered"),
    }


def _train(config, marks_at: Dict[int, str], save_at: Sequence[int] = ()):
    """Trains with clock marks at the given steps (after the pipeline's callbacks) and extra checkpoints."""
    from splatreplace_ns.method.train import run_training

    marks = {"start": time.perf_counter()}

    def after_step(trainer, step: int) -> None:
        if step in marks_at:
            marks[marks_at[step]] = time.perf_counter()
        if step in save_at:
            trainer.save_checkpoint(step)

    trainer = run_training(config, after_step)
    marks["end"] = time.perf_counter()
    return trainer, marks


def _registration_only(cfg_of_run, reg_config) -> Tuple[Dict, float]:
    """Loads a segmented checkpoint, registers with ``reg_config``; returns (accuracy, registration seconds)."""
    config = cfg_of_run
    config.pipeline.registration = reg_config
    config.set_timestamp()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()  # loads the checkpoint
    pipeline = trainer.pipeline
    start = time.perf_counter()
    pipeline.run_registration()
    seconds = time.perf_counter() - start
    accuracy = _accuracy(pipeline)
    accuracy["psnr"] = accuracy["psnr_masked"] = None  # the scene was not fine-tuned after this registration
    return accuracy, seconds


def run_tradeoff_bench(cfg: BenchTradeoffConfig) -> Dict:
    from splatreplace_ns.method.train import make_trainer_config
    from splatreplace_ns.poses.matching import MATCHERS

    unknown = sorted(set(cfg.sweeps) - set(SWEEPS))
    if unknown:
        raise ValueError(f"unknown sweep(s) {unknown}; known: {', '.join(SWEEPS)}")
    bad_views = sorted(set(cfg.virtual_views) - set(VIEW_GRIDS))
    if bad_views:
        raise ValueError(f"--virtual-views must be among {sorted(VIEW_GRIDS)}, got {bad_views}")
    torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
    t0 = time.perf_counter()
    B, C, F = cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations
    out = cfg.out_dir / f"tradeoff_{cfg.preset}"
    points: List[Dict] = []

    def whole_run(name: str, sweep: str, value, res: str, b: int) -> Tuple[object, Dict, object]:
        data = cached_scene(cfg.preset, res, cfg.n_train, cfg.n_test, cfg.data_root)
        config = make_trainer_config(data, out, b, C, F, experiment_name=name, progress=True)
        config.save_only_latest_checkpoint = name != "reference"  # the other points resume from its stage ends
        trainer, marks = _train(config, {b - 1: "base", b + C - 1: "segmented"},
                                save_at=(b - 1, b + C - 1) if name == "reference" else ())
        times = stage_times(marks)
        pipeline = trainer.pipeline
        times["registration"] = float(pipeline.registration_report.get("time_s", float("nan")))
        point = {"sweep": sweep, "value": value, "iterations": {"base": b, "contrastive": C, "finetune": F},
                 "res": res, "stage_time_s": times["base"] if sweep == "base" else times["total"],
                 "whole_time_s": times["total"], "times": times, **_accuracy(pipeline)}
        return trainer, point, config

    # -- the reference: every other point changes one thing from it
    reference_trainer, reference, ref_config = whole_run("reference", "reference", None, cfg.res, B)
    checkpoints = ref_config.get_checkpoint_dir()
    ref_times = reference["times"]
    reference["stage_time_s"] = ref_times["total"]
    points.append(reference)
    data = Path(reference_trainer.pipeline.datamanager.get_datapath())
    n_sources = max(1, int(reference.get("registration_attempts") or 0))
    del reference_trainer

    if "baseline" in cfg.sweeps:
        config = make_trainer_config(data, out, B + C + F, experiment_name="baseline", progress=True)
        trainer, marks = _train(config, {})
        seconds = marks["end"] - marks["start"]
        accuracy = _accuracy(trainer.pipeline)
        points.append({"sweep": "baseline", "value": B + C + F, "iterations": {"base": B + C + F, "contrastive": 0, "finetune": 0},
                       "res": cfg.res, "stage_time_s": seconds, "whole_time_s": seconds, "times": {"base": seconds},
                       **accuracy})
        del trainer

    if "base" in cfg.sweeps:
        for b in cfg.base_values:
            trainer, point, _ = whole_run(f"base_{b}", "base", b, cfg.res, b)
            points.append(point)
            del trainer

    if "contrastive" in cfg.sweeps:
        for c in cfg.contrastive_values:
            config = make_trainer_config(data, out, B, c, F, experiment_name=f"contrastive_{c}", progress=True,
                                         resume_from=(checkpoints, B - 1))
            trainer, marks = _train(config, {B + c - 1: "segmented"})
            marks["base"] = marks["start"]
            times = stage_times(marks)
            whole = ref_times["base"] + times["contrastive"] + times["finetune"]
            points.append({"sweep": "contrastive", "value": c, "iterations": {"base": B, "contrastive": c, "finetune": F},
                           "res": cfg.res, "stage_time_s": times["contrastive"], "whole_time_s": whole,
                           "times": times, **_accuracy(trainer.pipeline)})
            del trainer

    if "finetune" in cfg.sweeps:
        for f in cfg.finetune_values:
            config = make_trainer_config(data, out, B, C, f, experiment_name=f"finetune_{f}", progress=True,
                                         resume_from=(checkpoints, B + C - 1))
            trainer, marks = _train(config, {})
            seconds = stage_times({**marks, "segmented": marks["start"]})["finetune"]
            points.append({"sweep": "finetune", "value": f, "iterations": {"base": B, "contrastive": C, "finetune": f},
                           "res": cfg.res, "stage_time_s": seconds,
                           "whole_time_s": ref_times["base"] + ref_times["contrastive"] + seconds,
                           "times": {"finetune": seconds}, **_accuracy(trainer.pipeline)})
            del trainer

    registration_points: List[Tuple[str, object, Callable]] = []
    if "virtual_views" in cfg.sweeps:
        for v in cfg.virtual_views:
            az, el = VIEW_GRIDS[v]
            registration_points.append(("virtual_views", v, lambda r, az=az, el=el: replace(r, n_azimuth=az, n_elevation=el)))
    skipped: List[Dict] = []
    if "matcher" in cfg.sweeps:
        for m in cfg.matchers:
            if m not in MATCHERS or m == "onnx":
                skipped.append({"sweep": "matcher", "value": m, "reason": "not a matcher that runs without a user model"})
                continue
            registration_points.append(("matcher", m, lambda r, m=m: replace(r, robust_matcher=m)))
    for sweep, value, change in registration_points:
        config = make_trainer_config(data, out, B, C, F, experiment_name=f"{sweep}_{value}", progress=True,
                                     resume_from=(checkpoints, B + C - 1))
        reg = change(config.pipeline.registration)
        try:
            if cfg.finetune_registration_points:
                config.pipeline.registration = reg
                trainer, marks = _train(config, {})
                accuracy = _accuracy(trainer.pipeline)
                seconds = float(trainer.pipeline.registration_report.get("time_s", float("nan")))
                whole = ref_times["base"] + ref_times["contrastive"] + marks["end"] - marks["start"]
                whole_kind = "measured"
                del trainer
            else:
                accuracy, seconds = _registration_only(config, reg)
                whole = ref_times["total"] - ref_times["registration"] + seconds
                whole_kind = "reference with this stage's time"
        except Exception as err:  # a matcher whose weights are missing must not end the sweep
            skipped.append({"sweep": sweep, "value": value, "reason": f"{type(err).__name__}: {err}"})
            continue
        points.append({"sweep": sweep, "value": value, "iterations": {"base": B, "contrastive": C, "finetune": F},
                       "res": cfg.res, "stage_time_s": seconds, "stage_time_s_per_instance": seconds / n_sources,
                       "whole_time_s": whole, "whole_time": whole_kind, "times": {"registration": seconds}, **accuracy})
    reference["stage_time_s_per_instance"] = ref_times["registration"] / n_sources

    if "res" in cfg.sweeps:
        for res in cfg.res_values:
            trainer, point, _ = whole_run(f"res_{res}", "res", res, res, B)
            points.append(point)
            del trainer

    for point in points:
        if point is not reference:
            point["gain_per_minute"] = gain_per_minute(point, reference)
    from splatreplace_ns.eval.report import versions

    return {
        "benchmark": "tradeoff",
        "preset": cfg.preset,
        "reference": {"res": cfg.res, "n_train": cfg.n_train, "n_test": cfg.n_test, "base_iterations": B,
                      "contrastive_iterations": C, "finetune_iterations": F, "virtual_views": 25, "matcher": "xfeat"},
        "points": points,
        "skipped": skipped,
        "pareto_psnr_masked": [points[i]["sweep"] + f":{points[i]['value']}" for i in pareto_front(
            [p["whole_time_s"] for p in points], [p["psnr_masked"] for p in points])],
        "time_s": {"total": time.perf_counter() - t0},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
                    "threads": torch.get_num_threads()},
        "versions": versions(),
    }


# ----------------------------------------------------------------------------- output


def _label(point: Dict) -> str:
    return "reference" if point["sweep"] == "reference" else f"{point['sweep']}={point['value']}"


def print_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    ref = result["reference"]
    table = Table(title=f"accuracy vs time on '{result['preset']}' (reference: {ref['res']}, {ref['base_iterations']} base + "
                        f"{ref['contrastive_iterations']} contrastive + {ref['finetune_iterations']} fine-tuning iterations, "
                        f"25 virtual views, xfeat)")
    for col in ("point", "stage time (s)", "whole run (s)", "PSNR masked", "PSNR", "mIoU", "rot. err (°)", "registered",
                "dB / extra min"):
        table.add_column(col)

    def fmt(v, digits):
        return "n/a" if v is None else f"{v:.{digits}f}"

    for p in result["points"]:
        whole = fmt(p["whole_time_s"], 0) + ("*" if p.get("whole_time") not in (None, "measured") else "")
        registered = "n/a" if p.get("registration_attempts") is None else f"{p['registered']}/{p['registration_attempts']}"
        table.add_row(_label(p), fmt(p["stage_time_s"], 1), whole, fmt(p["psnr_masked"], 2), fmt(p["psnr"], 2),
                      fmt(p["miou"], 3), fmt(p["rot_err_deg_mean"], 2), registered,
                      fmt((p.get("gain_per_minute") or {}).get("psnr_masked_db"), 2))
    Console().print(table)
    Console().print("* reference run with this point's registration time (registration-only point); "
                    "n/a masked PSNR: not fine-tuned after this registration (see --finetune-registration-points)")
    for s in result["skipped"]:
        Console().print(f"skipped {s['sweep']}={s['value']}: {s['reason']}")


def write_pareto_plot(result: Dict, path: Path, size: Tuple[int, int] = (1200, 520)) -> None:
    """Two panels: masked PSNR vs whole-run time, and rotation error vs registration time per instance;
    each point labelled, the Pareto front drawn as a line. Drawn with OpenCV (no plotting dependency)."""
    import cv2

    W, H = size
    canvas = np.full((H, W, 3), 255, np.uint8)
    colours = {"reference": (0, 0, 0), "baseline": (60, 60, 200), "base": (180, 80, 0), "contrastive": (0, 140, 0), "finetune": (0, 0, 200),
               "virtual_views": (160, 0, 160), "matcher": (0, 140, 200), "res": (120, 120, 0)}
    panels = [
        ("masked PSNR (dB) vs whole-run time (s)", "whole_time_s", "psnr_masked", True),
        ("rotation error (deg) vs registration time per instance (s)", "stage_time_s_per_instance", "rot_err_deg_mean", False),
    ]
    for k, (title, x_key, y_key, higher) in enumerate(panels):
        x0, y0, pw, ph = 70 + k * (W // 2), 40, W // 2 - 110, H - 110
        pts = [(p.get(x_key), p.get(y_key), p) for p in result["points"]]
        pts = [(x, y, p) for x, y, p in pts if x is not None and y is not None and np.isfinite(x) and np.isfinite(y)]
        cv2.putText(canvas, title, (x0, y0 - 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.rectangle(canvas, (x0, y0), (x0 + pw, y0 + ph), (0, 0, 0), 1)
        if not pts:
            cv2.putText(canvas, "no points", (x0 + 10, y0 + 30), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
            continue
        xs, ys = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
        xlo, xhi = xs.min(), xs.max()
        ylo, yhi = ys.min(), ys.max()
        xpad, ypad = max((xhi - xlo) * 0.08, 1e-3), max((yhi - ylo) * 0.1, 1e-3)
        xlo, xhi, ylo, yhi = xlo - xpad, xhi + xpad, ylo - ypad, yhi + ypad

        def to_px(x, y):
            return (int(x0 + (x - xlo) / (xhi - xlo) * pw), int(y0 + ph - (y - ylo) / (yhi - ylo) * ph))

        for frac in (0.0, 0.5, 1.0):
            xv, yv = xlo + frac * (xhi - xlo), ylo + frac * (yhi - ylo)
            cv2.putText(canvas, f"{xv:.3g}", (to_px(xv, ylo)[0] - 15, y0 + ph + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
            cv2.putText(canvas, f"{yv:.3g}", (x0 - 55, to_px(xlo, yv)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        front = pareto_front(list(xs), list(ys), higher_is_better=higher)
        for a, b in zip(front, front[1:]):
            cv2.line(canvas, to_px(xs[a], ys[a]), to_px(xs[b], ys[b]), (150, 150, 150), 2, cv2.LINE_AA)
        for x, y, p in pts:
            colour = colours.get(p["sweep"], (0, 0, 0))
            centre = to_px(x, y)
            cv2.circle(canvas, centre, 5, colour, -1, cv2.LINE_AA)
            label = _label(p)
            width = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)[0][0]
            x = centre[0] + 6 if centre[0] + 6 + width < x0 + pw else centre[0] - 6 - width  # keep it inside
            cv2.putText(canvas, label, (x, centre[1] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA)
    cv2.putText(canvas, f"splatreplace bench tradeoff --preset {result['preset']} (grey: Pareto front)", (10, H - 12),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), canvas)
