"""Why a copy left as it was loses: ours' base against 3DGS* per copy, before anything is replaced.

A copy that registration refuses keeps the Gaussians of ours' base stage and is fine-tuned with the scene; its gain
over 3DGS* is then the difference between two 3DGS runs (ours' base: fewer image steps, a contrastive stage; 3DGS*:
the whole budget). This scores, per instance of each scene, ours' checkpoint at the end of segmentation (nothing
replaced yet) and the baseline's final checkpoint on the test views, and sets beside it each copy's gain in suite
runs of the same scene (the defaults, nothing replaced, another training seed: then also how far its 3DGS* lies from
the scored one per copy). Prints the table and writes one JSON.

    splatreplace bench suite --split dev --seeds 5 --res 96x72 --json D.json
    splatreplace bench suite --split dev --seeds 5 --res 96x72 --from-segmentation \
        --overrides pipeline.registration.min_class_copies=100 --json N.json          # nothing replaced
    python benchmarks/bench_left_copies.py --run benchmarks/runs/suite/random_5_96x72_48v8_1500-500-1000 \
        benchmarks/runs/suite/random_7_96x72_48v8_1500-500-1000 --runs defaults=D.json nothing_replaced=N.json \
        --out benchmarks/results/left_copies_dev.json
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import tyro

from splatreplace_ns.tools.bench.output import write_result_json

LOSS_DB = 0.5  # a copy "loses" below -0.5 dB, the bound asked of a copy left as it was


@dataclass
class BenchLeftCopiesConfig:
    run: Tuple[Path, ...]
    """`bench suite` run folders (one per scene) with ours (``ours/``, its checkpoint at the end of segmentation
    kept) and the baseline (``baseline/``)."""
    runs: Tuple[str, ...] = ()
    """LABEL=SUITE_JSON of the same scenes and budget: each copy's gain and what registration did with it."""
    out: Path = Path("benchmarks/results/left_copies_dev.json")
    """Where to write the JSON."""


def copy_status(row: Dict) -> Dict[str, str]:
    """Ground-truth instance id → replaced / template / left (refused, never registered, or the template copy of a
    class none of whose copies was replaced) in one suite row."""
    status: Dict[str, str] = {}
    entries = (row.get("registration") or {}).get("per_instance") or []
    for entry in entries:
        status[str(entry["gt_id"])] = "replaced" if entry.get("success") else "left"
    for entry in entries:  # a template copy is not registered to itself: it is named by its class's entries
        template = str(entry.get("template_gt_id"))
        if entry.get("success"):
            status[template] = "template"
        else:
            status.setdefault(template, "left")
    return status


def summarise(gains: Dict[str, float]) -> Dict:
    """Mean, spread and the copies losing more than ``LOSS_DB`` of a per-copy figure {instance: dB}."""
    values = list(gains.values())
    if not values:
        return {"mean": None, "sd": None, "losing": []}
    return {"mean": statistics.fmean(values), "sd": statistics.pstdev(values),
            "losing": sorted(k for k, v in gains.items() if v < -LOSS_DB)}


def score_checkpoints(run: Path) -> Tuple[Dict[str, float], Dict[str, float], float]:
    """Per-instance masked PSNR of ours at the end of segmentation and of the baseline; seconds spent."""
    from splatreplace_ns.tools.bench.register_scene import load_pipeline
    from splatreplace_ns.tools.bench.template import test_metrics

    start = time.perf_counter()
    ours_config = run / "ours" / "splat-replace" / "run" / "config.yml"
    steps = sorted(int(p.stem.split("-")[1]) for p in (ours_config.parent / "nerfstudio_models").glob("step-*.ckpt"))
    if len(steps) < 2:
        raise FileNotFoundError(f"{ours_config.parent}: no checkpoint from the end of segmentation beside the last")
    ours = test_metrics(load_pipeline(ours_config, steps[0]))["psnr_per_instance"]
    baseline_config = run / "baseline" / "splat-replace" / "run" / "config.yml"
    baseline = test_metrics(load_pipeline(baseline_config))["psnr_per_instance"]
    return ({k: float(v) for k, v in ours.items() if k != "0"}, {k: float(v) for k, v in baseline.items() if k != "0"},
            time.perf_counter() - start)


def scene_figures(run: Path, runs: Tuple[str, ...]) -> Dict:
    """One scene's per-copy figures: ours' base against 3DGS* at the end of segmentation, and each suite run's
    gains (the JSONs' rows of this scene's seed, read from the run folder's name ``random_<seed>_...``)."""
    seed = int(run.name.split("_")[1])
    ours, baseline, seconds = score_checkpoints(run)
    columns: Dict[str, Dict] = {}
    for item in runs:
        label, path = item.split("=", 1)
        result = json.loads(Path(path).read_text())
        row = next((r for r in result["scenes"] if r.get("seed") == seed and "per_instance" in r), None)
        if row is None:
            continue
        columns[label] = {"variant": result.get("variant"), "gain_masked": row["gain_masked"],
                          "ours_s": row["time_s"].get("ours"), "status": copy_status(row),
                          "gain": {k: v["gain"] for k, v in row["per_instance"].items()},
                          # non-zero only for a run with another training seed: how far two 3DGS* runs lie apart
                          "baseline_minus_scored": {k: v["baseline"] - baseline[k]
                                                    for k, v in row["per_instance"].items() if k in baseline}}
    return {"seed": seed, "run": run.name, "scoring_s": seconds, "ours_at_segmentation": ours, "baseline": baseline,
            "base_minus_baseline": {k: ours[k] - baseline[k] for k in ours if k in baseline}, "runs": columns}


def print_scene(scene: Dict) -> None:
    columns = scene["runs"]
    print(f"seed {scene['seed']}\n{'copy':>4} {'base - 3DGS* at segmentation':>30} "
          + " ".join(f"{label:>30}" for label in columns))
    for k in sorted(scene["base_minus_baseline"], key=int):
        cells = []
        for c in columns.values():
            moved = c["baseline_minus_scored"].get(k, 0.0)
            cells.append(f"{c['gain'].get(k, float('nan')):+6.2f} ({c['status'].get(k, 'left')})"
                         + (f" 3DGS* {moved:+.2f}" if abs(moved) > 1e-6 else ""))
        print(f"{k:>4} {scene['base_minus_baseline'][k]:>+30.2f} " + " ".join(f"{cell:>30}" for cell in cells))


def summary_over(scenes: List[Dict]) -> Dict:
    """Every copy of every scene pooled (keys ``seed/copy``): ours' base against 3DGS*, and per suite run all copies,
    the copies it left as they were, where those started from at segmentation, and how far its 3DGS* moved."""
    summary = {"base_minus_baseline": summarise({f"{s['seed']}/{k}": v for s in scenes
                                                  for k, v in s["base_minus_baseline"].items()})}
    for label in sorted({label for s in scenes for label in s["runs"]}):
        gains, left, left_at_segmentation, moved = {}, {}, {}, {}
        for scene in scenes:
            column = scene["runs"].get(label)
            if column is None:
                continue
            for k, gain in column["gain"].items():
                key = f"{scene['seed']}/{k}"
                gains[key] = gain
                if column["status"].get(k, "left") == "left":
                    left[key] = gain
                    if k in scene["base_minus_baseline"]:
                        left_at_segmentation[key] = scene["base_minus_baseline"][k]
                if abs(column["baseline_minus_scored"].get(k, 0.0)) > 1e-6:
                    moved[key] = column["baseline_minus_scored"][k]
        summary[label] = {"seeds": [s["seed"] for s in scenes if label in s["runs"]], "all": summarise(gains),
                          "left": summarise(left), "left_at_segmentation": summarise(left_at_segmentation)}
        if moved:  # another training seed: its own base, not the scored one, is where its left copies started
            summary[label]["baseline_minus_scored"] = summarise(moved)
            del summary[label]["left_at_segmentation"]
    return summary


def main(cfg: BenchLeftCopiesConfig) -> Dict:
    scenes = [scene_figures(run, cfg.runs) for run in cfg.run]
    for scene in scenes:
        print_scene(scene)
    summary = summary_over(scenes)
    for label, s in summary.items():
        print(f"{label}: " + json.dumps(s, default=lambda x: round(x, 3)))
    out = {"benchmark": "left_copies", "loss_db": LOSS_DB, "scenes": scenes, "summary": summary}
    write_result_json(out, cfg.out)
    return out


if __name__ == "__main__":
    main(tyro.cli(BenchLeftCopiesConfig))
