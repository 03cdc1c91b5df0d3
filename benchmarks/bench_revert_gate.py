"""How well does "explains its own training pixels worse after fine-tuning" predict harm in the test views?

Reads finished `splatreplace bench suite` runs of the dev split (any registration variant): for every replaced
instance, the fine-tuned scene's PSNR on its training pixels as replaced and with its own Gaussians (from the
same scene's segmentation checkpoint) put back, beside the instance's masked test-view gain over 3DGS* that
the suite measured. Prints the table and, per margin, which instances the gate would revert; writes one JSON.

    python benchmarks/bench_revert_gate.py --runs benchmarks/runs/suite --out benchmarks/results/revert_gate_dev.json
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import torch
import tyro

from splatreplace_ns.tools.bench.register_scene import load_pipeline
from splatreplace_ns.template.revert import RevertGateConfig, score_replaced_instances

SEGMENTATION_STEP = 1999  # end of the contrastive stage with the quick budget (1500 + 500)


@dataclass
class BenchRevertGateConfig:
    runs: Path = Path("benchmarks/runs/suite")
    """Folder of the suite's runs (one folder per scene and variant, each with result.json)."""
    out: Path = Path("benchmarks/results/revert_gate_dev.json")
    margins: Tuple[float, ...] = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0)
    """Margins (dB) whose decisions are tabulated."""


def own_gaussians(seg_pipeline) -> Tuple[Dict[int, Dict[str, torch.Tensor]], torch.Tensor]:
    model = seg_pipeline.model
    labels = model.instance_labels.to(model.means.device)
    sh = torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1).detach()
    out = {}
    for i in sorted(set(labels.unique().tolist()) - {0}):
        sel = labels == i
        out[int(i)] = {"means": model.means.detach()[sel], "quats": model.quats.detach()[sel],
                       "log_scales": model.scales.detach()[sel], "logit_opacities": model.opacities.detach()[sel],
                       "sh": sh[sel]}
    return out, labels


def score_run(run: Path) -> List[Dict]:
    result = json.loads((run / "result.json").read_text())["row"]
    base_run = Path(str(run).split("_reg-")[0])
    seg_pipeline = load_pipeline(base_run / "ours/splat-replace/run/config.yml", SEGMENTATION_STEP)
    own, _ = own_gaussians(seg_pipeline)
    config = run / "ours/splat-replace/run/config.yml"
    last = max(int(p.stem.split("-")[1]) for p in (config.parent / "nerfstudio_models").glob("step-*.ckpt"))
    pipeline = load_pipeline(config, last)  # a run resumed from segmentation names that step in its config
    model = pipeline.model
    if not model.has_templates:
        return []
    scene_c = model.composed_scene()
    scene = {"means": scene_c.means, "quats": scene_c.quats, "log_scales": scene_c.log_scales,
             "logit_opacities": scene_c.logit_opacities, "sh": scene_c.sh}
    cameras = pipeline.datamanager.train_dataset.cameras
    images = [d["image"] for d in pipeline.datamanager.cached_train]

    def render(view, gaussians, extra):
        return model.render_gaussian_set(cameras[view : view + 1], gaussians, extra)

    # how much the whole training views improved from segmentation to the end (the own Gaussians missed that)
    seg = seg_pipeline.model
    seg_scene = {"means": seg.means, "quats": seg.quats, "log_scales": seg.scales, "logit_opacities": seg.opacities,
                 "sh": torch.cat((seg.features_dc[:, None], seg.features_rest), 1)}
    with torch.no_grad():
        err_seg, err_fin = [], []
        for v in range(len(images)):
            target = images[v][..., :3].float()
            target = target / 255.0 if images[v].dtype == torch.uint8 else target
            a, _ = render(v, seg_scene, torch.zeros(len(seg_scene["means"]), 1))
            b, _ = render(v, scene, torch.zeros(len(scene["means"]), 1))
            err_seg.append((a - target).pow(2).mean())
            err_fin.append((b - target).pow(2).mean())
    train_gain = float(10 * torch.log10(torch.stack(err_seg).mean() / torch.stack(err_fin).mean()))
    start = time.perf_counter()
    with torch.no_grad():
        scores = score_replaced_instances(scene, scene_c.instance_id.detach(), own, images, render, RevertGateConfig())
    seconds = time.perf_counter() - start
    reg = {int(r["instance"]): r for r in result["registration"]["per_instance"]}
    templates = {int(v["template"]) for v in model.registration.values()}
    rows = []
    for iid, s in scores.items():
        r = reg.get(iid, {})
        gt = r.get("gt_id") if r else next((x["template_gt_id"] for x in reg.values() if x.get("template") == iid), None)
        gain = result["per_instance"].get(str(gt), {}).get("gain") if gt is not None else None
        rows.append({"run": run.name, "seed": result["seed"], "instance": iid, "template": iid in templates,
                     "rotation_error_deg": r.get("rotation_error_deg"), "test_gain_db": gain,
                     **{k: v for k, v in s.as_dict().items() if k not in ("revert", "reason")},
                     "scene_time_s": seconds, "scene_train_gain_db": train_gain})
    return rows


def main(cfg: BenchRevertGateConfig) -> None:
    runs = sorted(p for p in cfg.runs.iterdir() if p.name.startswith("random_") and (p / "result.json").exists())
    rows: List[Dict] = []
    for run in runs:
        got = score_run(run)
        rows.extend(got)
        for r in got:
            print(f"{r['run']:<60} inst {r['instance']:>2} {'T' if r['template'] else ' '} "
                  f"rot {r['rotation_error_deg'] if r['rotation_error_deg'] is None else round(r['rotation_error_deg'], 1)!s:>6} "
                  f"test {r['test_gain_db'] if r['test_gain_db'] is None else round(r['test_gain_db'], 2)!s:>6} "
                  f"train loss {r['loss_db'] if r['loss_db'] is None else round(r['loss_db'], 2)!s:>6} "
                  f"scene train gain {r['scene_train_gain_db']:.2f}", flush=True)
    by_margin = {}
    for m in cfg.margins:
        reverted = [r for r in rows if r["loss_db"] is not None and r["loss_db"] > m]
        kept = [r for r in rows if r not in reverted]
        by_margin[str(m)] = {
            "reverted": len(reverted),
            "reverted_harmful": sum(1 for r in reverted if (r["test_gain_db"] or 0) < -1),
            "reverted_helpful": sum(1 for r in reverted if (r["test_gain_db"] or 0) > 0),
            "kept_harmful": sum(1 for r in kept if (r["test_gain_db"] or 0) < -1),
        }
        print(f"margin {m:>4} dB: {by_margin[str(m)]}")
    cfg.out.parent.mkdir(parents=True, exist_ok=True)
    cfg.out.write_text(json.dumps({"benchmark": "revert_gate", "rows": rows, "by_margin": by_margin}, indent=1))


if __name__ == "__main__":
    main(tyro.cli(BenchRevertGateConfig))
