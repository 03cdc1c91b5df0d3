"""``splatreplace bench template``: the shared template against the 3DGS* baseline (paper Table 1 and its ablation).

On one synthetic preset, with the same total number of iterations for both:

* ``ours`` — base → contrastive → segmentation (clicks.json) → registration → shared templates → fine-tuning;
* ``baseline`` — 3DGS* only (``base + contrastive + finetune`` base iterations);
* ablations, each resumed from ours' checkpoint at the end of segmentation (so they share base, features and
  segmentation and differ only after it): ``shared_only`` (λ = 1, no offsets), ``offsets_only`` (λ = 0, no
  shared colour), ``no_pose_refinement`` (instance poses frozen at the registration result); and on request
  the oracles ``gt_poses`` (registration replaced by the scene's ground-truth poses) and ``gt_instances``
  (segmentation too: the Gaussians labelled from the ground-truth masks), which show how much of the gap
  to the best-seen copy the earlier stages leave.

Test-view PSNR/SSIM on full images and on the masked repeated regions (union of the ground-truth instance
masks), wall time of every run, and the export sizes of ours.
"""

from __future__ import annotations

import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import torch

from splatreplace_ns.tools.bench.output import write_result_json
from splatreplace_ns.tools.bench.scenes import cached_scene

ABLATIONS = ("shared_only", "offsets_only", "no_pose_refinement")
# oracles (asked for by name, not run by default): the stages before the template made exact
ORACLE_ABLATIONS = ("gt_poses", "gt_instances")
METRICS = ("psnr", "psnr_masked", "ssim", "ssim_masked")


@dataclass
class BenchTemplateConfig:
    """Masked and full-image PSNR/SSIM of the replaced scene vs the 3DGS* baseline, with ablations."""

    preset: str = "office"
    """Synthetic preset (office, temple, chess, ...)."""
    json: Optional[Path] = None
    """Where to write the results as JSON."""
    res: str = "160x120"
    """Scene resolution WxH."""
    n_train: int = 60
    """Training views."""
    n_test: int = 12
    """Test views."""
    base_iterations: int = 3000
    """Base 3DGS* iterations of ours (the baseline gets base + contrastive + finetune)."""
    contrastive_iterations: int = 1000
    """Contrastive iterations (paper: 1k is nearly as good as 5k)."""
    finetune_iterations: int = 2000
    """Shared-template fine-tuning iterations."""
    ablations: Tuple[str, ...] = ABLATIONS
    """Ablations to run (each costs one fine-tuning run): shared_only, offsets_only, no_pose_refinement; the
    oracles gt_poses (ground-truth registration) and gt_instances (ground-truth segmentation and registration)
    run only when named."""
    data_root: Path = Path("benchmarks/data")
    """Generated scenes are kept here and reused."""
    out_dir: Path = Path("benchmarks/runs")
    """Training outputs."""
    threads: int = 2
    """torch CPU threads."""
    light: Literal["preset", "overhead"] = "preset"
    """preset: the scene lit as its preset draws it. overhead: every directional light straight overhead, so that
    copies turned differently are lit alike (what the shared template gains without per-instance lighting)."""

    def main(self) -> Dict:
        result = run_template_bench(self)
        print_table(result)
        write_result_json(result, self.json)
        return result


def test_metrics(pipeline) -> Dict[str, float]:
    """Average test-view metrics (what ``ns-eval`` reports), restricted to the table's figures, plus the
    per-instance PSNR when the dataset has instance masks, the PSNR on own / shared / unseen pixels
    (``coverage``: {"own", "shared", "unseen", "pixels", "sharp"}) when it has the ground truth for them, and each view's
    figures (``per_view``)."""
    from splatreplace_ns.eval.coverage_scores import coverage_figures

    pipeline.eval()
    metrics = pipeline.get_average_eval_image_metrics()
    out = {k: (float(metrics[k]) if metrics.get(k) is not None else None) for k in METRICS}
    if "psnr_per_instance" in metrics:  # ground-truth instance id → PSNR over its pixels in the test views
        out["psnr_per_instance"] = metrics["psnr_per_instance"]
    figures = coverage_figures(metrics)  # PSNR over the test pixels seen on their own copy, only on another, or never
    if figures:
        out["coverage"] = figures
    out["instance_masks"] = metrics.get("instance_masks")  # "ground truth", "made from the clicks ...", or None
    if "per_view" in metrics:
        out["per_view"] = [{k: row.get(k) for k in ("view", "image") + METRICS} for row in metrics["per_view"]]
    return out


def gain_by_baseline_quality(baseline: List[Dict], ours: List[Dict], key: str = "psnr_masked") -> Optional[Dict]:
    """The gain on the test views the baseline renders worst, and on the others.

    The average over all test views mixes views the capture covered (both methods render the instances about
    equally well) with views it did not (where the shared templates are meant to help). The views are ranked
    by the baseline's ``key``; the worse half (rounded up) and the rest are averaged apart.

    Args:
        baseline, ours: per-view rows (``view`` index and ``key``), the same views in the same order.
    Returns:
        {"key", "worst_half": {"views", "baseline", "ours", "gain"}, "rest": {same}} or None when fewer than
        two views have ``key``.
    """
    pairs = [(b["view"], b[key], o[key]) for b, o in zip(baseline, ours)
             if b.get(key) is not None and o.get(key) is not None and b["view"] == o["view"]]
    if len(pairs) < 2:
        return None
    pairs.sort(key=lambda p: p[1])
    half = (len(pairs) + 1) // 2

    def summary(part):
        base = sum(p[1] for p in part) / len(part)
        mine = sum(p[2] for p in part) / len(part)
        return {"views": [p[0] for p in part], "baseline": base, "ours": mine, "gain": mine - base}

    return {"key": key, "worst_half": summary(pairs[:half]), "rest": summary(pairs[half:])}


def _run(config, before_train=None, after_step=None) -> Tuple[object, float]:
    from splatreplace_ns.method.train import run_training

    start = time.perf_counter()
    trainer = run_training(config, after_step=after_step, before_train=before_train)
    return trainer, time.perf_counter() - start


def reseed(config, seed: Optional[int]) -> None:
    """Sets a run's training seed: torch's, numpy's and random's (``machine.seed``) and the order the training
    views are drawn in (the datamanager's own seed). None keeps nerfstudio's (42 for both)."""
    if seed is not None:
        config.machine.seed = seed
        config.pipeline.datamanager.train_cameras_sampling_seed = seed


def _baseline_worker(data: str, out: str, iterations: int, threads: int, log_path: str, queue, seed=None) -> None:
    """Trains and scores the 3DGS* baseline in a process of its own (its console output goes to ``log_path``)."""
    from splatreplace_ns.method.train import make_trainer_config

    with open(log_path, "w") as log:  # the descriptors 1 and 2 keep the file open after this block
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
    torch.set_num_threads(threads)
    config = make_trainer_config(Path(data), Path(out), iterations, experiment_name="baseline", progress=True)
    reseed(config, seed)
    trainer, seconds = _run(config)
    queue.put({"metrics": test_metrics(trainer.pipeline), "time_s": seconds, "gaussians": trainer.pipeline.model.num_points,
               "config": str(config.get_base_dir() / "config.yml")})


def _wait_for(process, queue) -> Dict:
    """The worker's result; a clear error when it died without one."""
    import queue as queue_module

    while True:
        try:
            return queue.get(timeout=5.0)
        except queue_module.Empty:
            if not process.is_alive():
                raise RuntimeError(f"the baseline's training process ended without a result (exit code {process.exitcode})")


def train_ours_and_baseline(
    data: Path, out: Path, B: int, C: int, F: int, resumable: bool = False, parallel: bool = False, after_step=None,
    configure=None, seed: Optional[int] = None,
) -> Dict:
    """Trains the whole method and the 3DGS* baseline with the same total iterations and scores both.

    Args:
        data: dataset folder; out: runs folder; B, C, F: base, contrastive and fine-tuning iterations of ours
            (the baseline trains B + C + F base iterations).
        resumable: also keep ours' checkpoint at the end of segmentation (for ablations to resume from).
        parallel: on a CPU with at least two cores, train the baseline in a second process at the same time,
            the cores split between the two (on two cores one torch thread scales to about 1.2x from two, so
            two runs side by side finish much sooner than one after the other). Its log goes to
            ``out/baseline.log``.
        after_step: ``after_step(trainer, step)`` after every step of ours (see ``method.train.run_training``).
        configure: ``configure(trainer_config)`` changes ours' settings before it trains (not the baseline's).
        seed: the training seed of both runs (:func:`reseed`; default: nerfstudio's 42).
    Returns:
        {"ours", "baseline": metrics, "ours_trainer", "baseline_pipeline", "ours_config", "times", "sizes",
         "registration"}.
    """
    import multiprocessing

    from splatreplace_ns.method.train import make_trainer_config
    from splatreplace_ns.template.export import instanced_arrays, ply_bytes, save_instanced

    times: Dict[str, float] = {}
    cores = os.cpu_count() or 1
    parallel = parallel and cores >= 2 and not torch.cuda.is_available()
    worker = None
    if parallel:
        threads = max(1, cores // 2)
        torch.set_num_threads(threads)
        out.mkdir(parents=True, exist_ok=True)
        context = multiprocessing.get_context("spawn")
        queue = context.Queue()
        worker = context.Process(target=_baseline_worker, daemon=True,
                                 args=(str(data), str(out), B + C + F, threads, str(out / "baseline.log"), queue, seed))
        worker.start()
    try:
        ours_cfg = make_trainer_config(data, out, B, C, F, experiment_name="ours",
                                       steps_per_save=B + C - 1 if resumable else None, progress=True)
        ours_cfg.save_only_latest_checkpoint = not resumable
        reseed(ours_cfg, seed)
        if configure is not None:
            configure(ours_cfg)
        ours_trainer, times["ours"] = _run(ours_cfg, after_step=after_step)
    except BaseException:
        if worker is not None:
            worker.terminate()
        raise
    pipeline = ours_trainer.pipeline
    ours = test_metrics(pipeline)
    model = pipeline.model
    times["segmentation"] = float(pipeline.segmentation_report.get("time_s", float("nan")))
    times["registration"] = float(pipeline.registration_report.get("time_s", float("nan")))
    sh_coeffs = model.features_rest.shape[1] + 1
    sizes: Dict[str, object] = {}
    if model.has_templates:
        instanced = ours_cfg.get_base_dir() / "export" / "instanced.npz"
        sizes["instanced_bytes"] = save_instanced(instanced, instanced_arrays(model))
        sizes["instanced_path"] = str(instanced)
        composed = len(model.composed_scene().means)
        sizes.update(ours_ply_bytes=ply_bytes(composed, sh_coeffs), ours_gaussians_rendered=composed,
                     ours_gaussians_stored=model.num_points)
        if model.base_gaussians:  # ours' own scene before the templates replaced its copies (what export compares)
            sizes.update(base_scene_gaussians=int(model.base_gaussians),
                         base_scene_ply_bytes=ply_bytes(int(model.base_gaussians), sh_coeffs))
    registration = {int(k): {"success": v["success"], "message": v["message"]} for k, v in model.registration.items()}

    if worker is not None:
        from splatreplace_ns.tools.bench.register_scene import load_pipeline

        if worker.is_alive():
            print(f"ours is done; waiting for the baseline's run beside it (progress in {out / 'baseline.log'})", flush=True)
        done = _wait_for(worker, queue)
        worker.join()
        baseline, times["baseline"], n_base = done["metrics"], done["time_s"], done["gaussians"]
        baseline_pipeline = load_pipeline(Path(done["config"]))
    else:
        baseline_cfg = make_trainer_config(data, out, B + C + F, experiment_name="baseline", progress=True)
        reseed(baseline_cfg, seed)
        baseline_trainer, times["baseline"] = _run(baseline_cfg)
        baseline = test_metrics(baseline_trainer.pipeline)
        baseline_pipeline = baseline_trainer.pipeline
        n_base = baseline_pipeline.model.num_points
    sizes.update(baseline_ply_bytes=ply_bytes(n_base, sh_coeffs), baseline_gaussians=n_base)
    return {"ours": ours, "baseline": baseline, "ours_trainer": ours_trainer, "baseline_pipeline": baseline_pipeline,
            "ours_config": ours_cfg, "times": times, "sizes": sizes, "registration": registration,
            "parallel": parallel}


def run_ablation(name: str, data: Path, out: Path, B: int, C: int, F: int, checkpoint_dir: Path) -> Dict:
    """One ablation, resumed from ours' checkpoint at the end of segmentation (step B + C − 1) and fine-tuned
    to the same total. → test metrics and ``time_s``."""
    from splatreplace_ns.method.train import make_trainer_config

    ab_cfg = make_trainer_config(data, out, B, C, F, experiment_name=f"ablation_{name}", progress=True,
                                 resume_from=(checkpoint_dir, B + C - 1))
    before = None
    if name == "shared_only":
        ab_cfg.pipeline.model.template_mix = 1.0
    elif name == "offsets_only":
        ab_cfg.pipeline.model.template_mix = 0.0
    elif name == "no_pose_refinement":
        ab_cfg.optimizers["instance_poses"]["optimizer"].lr = 0.0
    elif name in ORACLE_ABLATIONS:
        from splatreplace_ns.tools.bench.oracle import use_ground_truth

        def before(trainer):
            use_ground_truth(trainer.pipeline, instances_too=name == "gt_instances")

    elif name != "ours":  # "ours": the full method resumed, the reference the ablations differ from
        raise ValueError(f"unknown ablation {name!r}; known: {', '.join(ABLATIONS + ORACLE_ABLATIONS)}")
    trainer, seconds = _run(ab_cfg, before)
    result = {**test_metrics(trainer.pipeline), "time_s": seconds}
    registration = trainer.pipeline.model.registration
    result["replaced"] = sorted(int(k) for k, v in registration.items() if v["success"])
    result["registration"] = {int(k): v["message"] for k, v in registration.items()}
    result["instances"] = [{k: i[k] for k in ("id", "class", "source") if k in i} for i in trainer.pipeline.model.instances]
    del trainer
    return result


def run_folder_name(cfg: BenchTemplateConfig) -> str:
    """The folder under ``out_dir`` that holds one configuration's runs: named by everything that changes what
    they train (preset, light, resolution, views, iterations), so that a run of another configuration does not
    overwrite the checkpoints (which ``--seg-step`` of ``bench register`` and the ablations resume from) of this
    one. E.g. ``template_office_128x96_48v8_1500-500-1000`` or ``template_office_160x120_60v12_3000-1000-2000_overhead``."""
    name = (f"template_{cfg.preset}_{cfg.res}_{cfg.n_train}v{cfg.n_test}_"
            f"{cfg.base_iterations}-{cfg.contrastive_iterations}-{cfg.finetune_iterations}")
    return name + ("" if cfg.light == "preset" else f"_{cfg.light}")


def run_template_bench(cfg: BenchTemplateConfig) -> Dict:
    unknown = sorted(set(cfg.ablations) - set(ABLATIONS) - set(ORACLE_ABLATIONS))
    if unknown:
        raise ValueError(f"unknown ablation(s) {unknown}; known: {', '.join(ABLATIONS + ORACLE_ABLATIONS)}")
    torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
    t0 = time.perf_counter()
    data = cached_scene(cfg.preset, cfg.res, cfg.n_train, cfg.n_test, cfg.data_root, cfg.light)
    out = cfg.out_dir / run_folder_name(cfg)
    B, C, F = cfg.base_iterations, cfg.contrastive_iterations, cfg.finetune_iterations
    sim_s = time.perf_counter() - t0
    pair = train_ours_and_baseline(data, out, B, C, F, resumable=bool(cfg.ablations))
    ours, baseline, sizes, registration = pair["ours"], pair["baseline"], pair["sizes"], pair["registration"]
    times = {"sim": sim_s, **pair["times"]}
    checkpoint_dir = pair["ours_config"].get_checkpoint_dir()
    del pair

    ablations: Dict[str, Dict] = {}
    for name in cfg.ablations:
        ablations[name] = run_ablation(name, data, out, B, C, F, checkpoint_dir)

    return {
        "benchmark": "template",
        "preset": cfg.preset,
        "baseline": baseline,
        "ours": ours,
        "gain": {k: (ours[k] - baseline[k]) if ours[k] is not None and baseline[k] is not None else None for k in METRICS},
        "gain_by_baseline_quality": gain_by_baseline_quality(baseline.get("per_view", []), ours.get("per_view", [])),
        "ablations": ablations,
        "sizes": sizes,
        "registration": registration,
        "time_s": {**times, "total": time.perf_counter() - t0},
        "parameters": {"res": cfg.res, "light": cfg.light, "n_train": cfg.n_train, "n_test": cfg.n_test, "base_iterations": B,
                       "contrastive_iterations": C, "finetune_iterations": F, "baseline_iterations": B + C + F},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
                    "threads": torch.get_num_threads()},
    }


def print_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"shared template on '{result['preset']}' (test views, same total iterations)")
    for col in ("run", "PSNR", "PSNR masked", "SSIM", "SSIM masked", "time (s)"):
        table.add_column(col)

    def fmt(v, digits):
        return "n/a" if v is None else f"{v:.{digits}f}"

    rows: List = [("baseline 3DGS*", result["baseline"], result["time_s"]["baseline"]),
                  ("ours", result["ours"], result["time_s"]["ours"])]
    rows += [(f"ablation: {k}", v, v["time_s"]) for k, v in result["ablations"].items()]
    for name, m, seconds in rows:
        table.add_row(name, fmt(m["psnr"], 2), fmt(m["psnr_masked"], 2), fmt(m["ssim"], 4), fmt(m["ssim_masked"], 4),
                      f"{seconds:.0f}")
    Console().print(table)
    split = result.get("gain_by_baseline_quality")
    if split:
        worst, rest = split["worst_half"], split["rest"]
        Console().print(
            f"masked PSNR on the {len(worst['views'])} test views the baseline renders worst: baseline "
            f"{worst['baseline']:.2f}, ours {worst['ours']:.2f} ({worst['gain']:+.2f} dB); on the other "
            f"{len(rest['views'])}: {rest['baseline']:.2f} → {rest['ours']:.2f} ({rest['gain']:+.2f} dB)"
        )
    sizes = result["sizes"]
    if "instanced_bytes" in sizes:
        Console().print(
            f"sizes: baseline PLY {sizes['baseline_ply_bytes'] / 1e6:.2f} MB ({sizes['baseline_gaussians']} Gaussians), "
            f"ours PLY {sizes['ours_ply_bytes'] / 1e6:.2f} MB, instanced {sizes['instanced_bytes'] / 1e6:.2f} MB "
            f"({sizes['ours_gaussians_stored']} stored Gaussians)"
            + (f"; ours before replacement {sizes['base_scene_ply_bytes'] / 1e6:.2f} MB as PLY "
               f"({sizes['base_scene_gaussians']} Gaussians)" if "base_scene_ply_bytes" in sizes else "")
        )
