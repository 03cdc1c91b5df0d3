"""``splatreplace bench scale``: what every stage after the base training costs as the scene grows.

One preset's base model (trained once, reused) is grown to each number of Gaussians by splitting its Gaussians
(``scale_stages.split_gaussians``); each stage then runs the method's own code in a fresh process, which reports
its wall time, its peak resident memory (the whole process, and the growth during the stage) and the count its
cost grows with. Three sweeps: the number of Gaussians (at ``--views`` views of ``--size``), the number of views
and the image size (at ``--fixed-gaussians``), the latter two for the stages that render views. Per stage a
power law is fitted to time against its count over the Gaussian sweep; the table names the worst exponent.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from splatreplace_ns.tools.bench.output import publish
from splatreplace_ns.tools.bench.scale_stages import COUNT_OF, RUNNERS, STAGES, checked_size, power_law_exponent

_RESULT_MARK = "BENCH_SCALE_RESULT "
_REPO_ROOT = Path(__file__).resolve().parents[3]
VIEW_STAGES = ("mask_rendering", "carving", "render")
"""The stages whose cost also grows with the views rendered and their size."""


@dataclass
class BenchScaleConfig:
    """Wall time and peak memory of every stage after the base training, from 50k to 1M Gaussians."""

    preset: str = "office"
    """Synthetic preset whose base model is grown."""
    res: str = "160x120"
    """Resolution of the preset's capture (the base model trains on it)."""
    n_train: int = 48
    """Training views of the capture."""
    n_test: int = 8
    """Test views of the capture (part of the cached scene's key)."""
    base_iterations: int = 1500
    """Base 3DGS* iterations of the model that is grown."""
    gaussians: Tuple[int, ...] = (50_000, 100_000, 200_000, 500_000, 1_000_000)
    """Gaussian counts of the main sweep."""
    views: int = 48
    """Views the view stages render in the Gaussian sweep (the training cameras, cycled when there are fewer)."""
    size: str = "320x240"
    """Image size of the view stages in the Gaussian sweep."""
    fixed_gaussians: int = 200_000
    """Gaussians in the views and image-size sweeps."""
    view_counts: Tuple[int, ...] = (48, 100, 200)
    """Views of the views sweep (empty: no views sweep)."""
    sizes: Tuple[str, ...] = ("160x120", "320x240", "640x480", "1280x960")
    """Image sizes of the image-size sweep (empty: no size sweep)."""
    stages: Tuple[str, ...] = STAGES
    """Stages to time: clustering, mask_rendering, carving, registration, templates, export, render."""
    threads: int = 2
    """torch threads per measurement."""
    timeout_s: float = 3600.0
    """A measurement still running after this many seconds is stopped and reported as such."""
    data_root: Path = Path("benchmarks/data")
    """Generated scenes are kept here and reused."""
    out_dir: Path = Path("benchmarks/runs")
    """The base model's training output (reused when finished)."""
    json: Optional[Path] = None
    """Where to write the results as JSON."""
    plot: Optional[Path] = None
    """Log-log plot per stage (default: beside --json, else benchmarks/runs/scale.png)."""

    def main(self) -> Dict:
        result = run_scale_bench(self)
        return publish(result, print_scale, self.json, self.plot, self.out_dir / "scale.png", write_scale_plot)


# ----------------------------------------------------------------------------- one measurement (own process)


def _register_config(cfg: Dict[str, Any]):
    from splatreplace_ns.tools.bench.register import BenchRegisterConfig

    return BenchRegisterConfig(preset=cfg["preset"], res=cfg["res"], n_train=cfg["n_train"], n_test=cfg["n_test"],
                               base_iterations=cfg["base_iterations"], data_root=Path(cfg["data_root"]),
                               out_dir=Path(cfg["out_dir"]), threads=cfg["threads"])


def prepare_base(cfg: BenchScaleConfig) -> Dict[str, Any]:
    """Trains (or reuses) the base model and labels its Gaussians from the ground-truth masks, once; the labels
    are saved beside the run for the measurements. → what the measurements need to find them."""
    import torch

    from splatreplace_ns.tools.bench.gt_labels import label_gaussians_from_ground_truth
    from splatreplace_ns.tools.bench.register_scene import scene_folder, shown_path, train_or_load_base

    spec = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}
    reg = _register_config(spec)
    started = time.perf_counter()
    pipeline, config_path, _, reused = train_or_load_base(reg, scene_folder(reg))
    labels_path = config_path.parent / "gt_labels.pt"
    if not labels_path.exists():
        torch.save(label_gaussians_from_ground_truth(pipeline, reg.depth_tolerance).cpu(), labels_path)
    return {"config": str(config_path), "labels": str(labels_path), "base_gaussians": int(pipeline.model.num_points),
            "reused": reused, "prepare_s": time.perf_counter() - started, "run": shown_path(config_path.parent)}


def measure(spec: Dict[str, Any]) -> Dict[str, Any]:
    """One stage at one size in this process: loads the base, grows it, times the stage. → its figures."""
    import torch

    from splatreplace_ns.tools.bench.register_scene import load_pipeline
    from splatreplace_ns.tools.bench.render import peak_tracker, proc_status_mb
    from splatreplace_ns.tools.bench.scale_stages import grow_model

    torch.set_num_threads(spec["threads"])
    pipeline = load_pipeline(Path(spec["config"]))
    labels = grow_model(pipeline, torch.load(spec["labels"]), spec["gaussians"])
    size = checked_size(spec["size"])
    growth = peak_tracker()
    started = time.perf_counter()
    figures = RUNNERS[spec["stage"]](pipeline, labels, spec["views"], size)
    seconds = time.perf_counter() - started
    return {**{k: spec[k] for k in ("stage", "sweep", "gaussians", "views", "size")}, **figures,
            "seconds": seconds, "peak_growth_mb": growth(), "peak_rss_mb": proc_status_mb("VmHWM")}


def measure_isolated(spec: Dict[str, Any], timeout_s: float) -> Dict[str, Any]:
    """:func:`measure` in a fresh process (its own peak memory); a failure or a timeout is reported, not raised."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(_REPO_ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    env.setdefault("OMP_NUM_THREADS", str(spec["threads"]))
    keys = {k: spec[k] for k in ("stage", "sweep", "gaussians", "views", "size")}
    started = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-m", "splatreplace_ns.tools.bench.scale", "--worker", json.dumps(spec)],
                              capture_output=True, text=True, env=env, cwd=str(_REPO_ROOT), timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {**keys, "error": f"stopped after {timeout_s:.0f} s"}
    for line in proc.stdout.splitlines():
        if line.startswith(_RESULT_MARK):
            return {**json.loads(line[len(_RESULT_MARK):]), "process_s": time.perf_counter() - started}
    tail = (proc.stderr or proc.stdout)[-600:].strip().splitlines()
    return {**keys, "error": f"exit {proc.returncode}: {tail[-1] if tail else ''}"}


# ----------------------------------------------------------------------------- sweeps and summary


def measurement_specs(cfg: BenchScaleConfig, base: Dict[str, Any]) -> List[Dict[str, Any]]:
    """Every (stage, sweep, size) to measure, in the order they run (smallest first in each sweep)."""
    unknown = set(cfg.stages) - set(STAGES)
    if unknown:
        raise ValueError(f"unknown stages {sorted(unknown)}; known: {', '.join(STAGES)}")
    for text in (cfg.size, *cfg.sizes):
        checked_size(text)
    common = {"config": base["config"], "labels": base["labels"], "threads": cfg.threads}
    specs = [{**common, "stage": s, "sweep": "gaussians", "gaussians": n, "views": cfg.views, "size": cfg.size}
             for s in cfg.stages for n in sorted(cfg.gaussians)]
    for s in (s for s in cfg.stages if s in VIEW_STAGES):
        if s != "render":
            specs += [{**common, "stage": s, "sweep": "views", "gaussians": cfg.fixed_gaussians, "views": v,
                       "size": cfg.size} for v in sorted(cfg.view_counts)]
        specs += [{**common, "stage": s, "sweep": "size", "gaussians": cfg.fixed_gaussians,
                   "views": cfg.views if s != "render" else 1, "size": z}
                  for z in sorted(cfg.sizes, key=lambda t: checked_size(t)[0] * checked_size(t)[1])]
    return specs


def seconds_per(row: Dict[str, Any]) -> float:
    """A measurement's time, per instance for registration (the target is per instance)."""
    return row["seconds"] / row["instances"] if row["stage"] == "registration" else row["seconds"]


def summarise(rows: List[Dict[str, Any]]) -> Dict[str, Any]:
    """Per stage: the fitted exponent of time against its count over the Gaussian sweep, the largest run's time
    and peak memory; and the stage that grows worst."""
    out: Dict[str, Any] = {"stages": {}}
    for stage in dict.fromkeys(r["stage"] for r in rows):
        done = [r for r in rows if r["stage"] == stage and r["sweep"] == "gaussians" and "error" not in r]
        entry: Dict[str, Any] = {"count": COUNT_OF[stage], "measured": len(done)}
        if len({r["count"] for r in done}) >= 2:
            per = [seconds_per(r) for r in done]
            entry["exponent"], entry["r2"] = power_law_exponent([r["count"] for r in done], per)
        if done:
            largest = max(done, key=lambda r: r["gaussians"])
            entry.update(largest_gaussians=largest["gaussians"], seconds=largest["seconds"],
                         seconds_per_instance=seconds_per(largest),
                         peak_rss_mb=largest["peak_rss_mb"], peak_growth_mb=largest["peak_growth_mb"])
        entry["failed"] = [f"{r['gaussians']} G: {r['error']}" for r in rows
                           if r["stage"] == stage and r["sweep"] == "gaussians" and "error" in r]
        out["stages"][stage] = entry
    fitted = {s: e["exponent"] for s, e in out["stages"].items() if "exponent" in e}
    out["worst_stage"] = max(fitted, key=fitted.get) if fitted else None
    return out


def run_scale_bench(cfg: BenchScaleConfig) -> Dict[str, Any]:
    import platform

    import torch

    torch.set_num_threads(cfg.threads)
    started = time.perf_counter()
    base = prepare_base(cfg)
    rows = []
    specs = measurement_specs(cfg, base)
    for i, spec in enumerate(specs, 1):
        print(f"[scale] {i}/{len(specs)} {spec['stage']}: {spec['gaussians']:,d} Gaussians, {spec['views']} views of "
              f"{spec['size']}", flush=True)
        rows.append(measure_isolated(spec, cfg.timeout_s))
        row = rows[-1]
        said = row["error"] if "error" in row else f"{row['seconds']:.1f} s, peak {row['peak_rss_mb'] or 0:.0f} MB"
        print(f"[scale]   {said}", flush=True)
    return {
        "benchmark": "scale", "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
        "base": {k: v for k, v in base.items() if k not in ("config", "labels")}, "rows": rows, "summary": summarise(rows), "wall_s": time.perf_counter() - started,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "threads": cfg.threads,
                    "torch": torch.__version__},
        "how_grown": "every Gaussian of the trained base model split into children drawn from it (centres from its "
                     "Gaussian, scales / k^(1/3)), the instances' labels inherited",
    }


# ----------------------------------------------------------------------------- output


def print_scale(result: Dict[str, Any]) -> None:
    rows = result["rows"]
    print(f"\nbench scale: {result['config']['preset']} base model of {result['base']['base_gaussians']:,d} Gaussians "
          f"grown by splitting; {result['machine']['threads']} threads")
    print(f"{'stage':<15} {'sweep':<10} {'Gaussians':>10} {'views':>6} {'size':>9} {'count':>14} {'s':>9} "
          f"{'peak MB':>8} {'grew MB':>8}")
    for r in rows:
        if "error" in r:
            print(f"{r['stage']:<15} {r['sweep']:<10} {r['gaussians']:>10,d} {r['views']:>6} {r['size']:>9}  {r['error']}")
            continue
        print(f"{r['stage']:<15} {r['sweep']:<10} {r['gaussians']:>10,d} {r['views']:>6} {r['size']:>9} "
              f"{r['count']:>14,d} {r['seconds']:>9.2f} {r['peak_rss_mb'] or 0:>8.0f} {r['peak_growth_mb'] or 0:>8.0f}")
    print(f"\n{'stage':<15} {'grows with':<28} {'exponent':>8} {'R²':>5} {'s at largest':>12} {'peak MB':>8}")
    for stage, e in result["summary"]["stages"].items():
        exponent = f"{e['exponent']:.2f}" if "exponent" in e else "n/a"
        r2 = f"{e['r2']:.2f}" if "r2" in e else ""
        seconds = f"{e['seconds_per_instance']:.1f}" if "seconds" in e else "n/a"
        print(f"{stage:<15} {e['count']:<28} {exponent:>8} {r2:>5} {seconds:>12} {e.get('peak_rss_mb') or 0:>8.0f}")
    print(f"worst-growing stage: {result['summary']['worst_stage']}")


def write_scale_plot(result: Dict[str, Any], path: Path) -> None:
    """One log-log panel per stage: time against its count over the Gaussian sweep, the fitted exponent."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    stages = list(result["summary"]["stages"])
    cols = min(4, max(1, len(stages)))
    rows_n = -(-len(stages) // cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(3.4 * cols, 2.9 * rows_n), dpi=110, squeeze=False)
    for ax, stage in zip(axes.flat, stages):
        done = [r for r in result["rows"] if r["stage"] == stage and r["sweep"] == "gaussians" and "error" not in r]
        xs = [r["count"] for r in done]
        ys = [seconds_per(r) for r in done]
        ax.loglog(xs, ys, "o-", color="#2980b9")
        e = result["summary"]["stages"][stage]
        ax.set_title(f"{stage}: ~count^{e['exponent']:.2f}" if "exponent" in e else stage, fontsize=9)
        ax.set_xlabel(e["count"], fontsize=8)
        ax.set_ylabel("s per instance" if stage == "registration" else "s", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    for ax in list(axes.flat)[len(stages):]:
        ax.axis("off")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "--worker":
    import warnings

    warnings.filterwarnings("ignore")
    print(_RESULT_MARK + json.dumps(measure(json.loads(sys.argv[2]))), flush=True)
