"""Where the shape's veto lies: each pose the image choice accepted, its fitness and its size against its template,
beside the truth (``poses.decision.leave_doubtful_instances``: a pose is refused below ``min_shape_fitness`` or
beyond ``max_size_ratio``).

Reads `bench suite` run folders (the final checkpoint's registration entries, with each instance's size against its
template as registration recorded it, or for a run from before the veto measured again from the checkpoint at the end
of segmentation; ``result.json`` for each pose's error and each copy's gain), prints
one row per accepted pose and a summary (the range right poses span, which poses each check refuses), and writes one
JSON. Choose the thresholds on the dev split's runs only.

    splatreplace bench suite --split dev --seeds 0 1 2 3 4 5 6 7 8 --res 96x72 --inputs user
    python benchmarks/bench_shape_evidence.py --runs benchmarks/runs/suite/random_{0,1,2,3,4,5,6,7,8}_96x72_48v8{,_user}_1500-500-1000 \
        --out benchmarks/results/shape_evidence_dev.json
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
import tyro

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.decision import size_ratio
from splatreplace_ns.poses.instance import InstanceGaussians
from splatreplace_ns.tools.bench.output import write_result_json

WRONG_DEG = 5.0  # a pose more than 5° from the truth is wrong (the suite's count)


@dataclass
class BenchShapeEvidenceConfig:
    runs: Tuple[Path, ...]
    """`bench suite` run folders of the defaults (one per scene and regime), each with ``result.json`` and ours'
    checkpoints (``ours/splat-replace/run/nerfstudio_models``)."""
    out: Path = Path("benchmarks/results/shape_evidence_dev.json")
    """Where to write the JSON."""


def _states(run: Path) -> List[Dict]:
    paths = sorted((run / "ours" / "splat-replace" / "run" / "nerfstudio_models").glob("step-*.ckpt"))
    return [torch.load(p, map_location="cpu", weights_only=False)["pipeline"] for p in paths]


def _segmented(run: Path, states: List[Dict]) -> Dict:
    """The state of ours' checkpoint at the end of segmentation among ``states`` (``run``'s). A variant resumed from
    the defaults' segmentation (``--from-segmentation``) has none of its own: the defaults' folder (its name up to
    the budget) has it."""
    segmented = [s for s in states if s["_model._extra_state"]["stage"] == "segmented"]
    if not segmented:
        defaults = re.match(r"^(.*_\d+-\d+-\d+)_", run.name)
        if defaults is None:
            raise FileNotFoundError(f"{run}: no checkpoint at the end of segmentation")
        segmented = [s for s in _states(run.parent / defaults.group(1))
                     if s["_model._extra_state"]["stage"] == "segmented"]
    return segmented[0]


def accepted_poses(run: Path, cfg: RegistrationConfig) -> List[Dict]:
    """One row per instance whose pose the image choice accepted in ``run``: error against the truth, gain, the
    fitness under its pose and its size against its template (solid centres, as registration takes them)."""
    row = json.loads((run / "result.json").read_text())["row"]
    states = _states(run)
    registration = states[-1]["_model._extra_state"]["registration"]
    recorded = all("size_ratio" in entry for entry in registration.values())
    if not recorded:  # a run from before the veto: measured again from the checkpoint at the end of segmentation
        segmented = _segmented(run, states)
        means = segmented["_model.gauss_params.means"].numpy()
        labels = segmented["_model._extra_state"]["instance_labels"].numpy()
        opacities = 1.0 / (1.0 + np.exp(-segmented["_model.gauss_params.opacities"].numpy().reshape(-1)))

    def solid(iid: int) -> np.ndarray:  # as registration takes an instance's centres
        mine = labels == iid
        inst = InstanceGaussians(means[mine], None, None, opacities[mine], None)
        return inst.centres()[inst.solid(cfg.min_opacity, cfg.min_solid_points)]

    truth = {int(p["instance"]): p for p in row["registration"]["per_instance"]}
    rows = []
    for iid, entry in registration.items():
        iid, template = int(iid), int(entry["template"])
        choice = entry.get("image_choice") or {}
        if iid == template or not choice.get("accepted"):
            continue
        t = truth.get(iid, {})
        gain = (row["per_instance"].get(str(t.get("gt_id"))) or {}).get("gain")
        error = t.get("proposed_rotation_error_deg")
        start = time.perf_counter()
        ratio = entry["size_ratio"] if recorded else size_ratio(solid(iid), solid(template))
        rows.append({"scene": run.name, "seed": row["seed"], "inputs": row.get("inputs", "exact"), "instance": iid,
                     "rotation_error_deg": error, "wrong": None if error is None else error > WRONG_DEG,
                     "gain_db": gain, "fitness": float(entry["fitness"]), "size_ratio": ratio,
                     "size_ratio_s": time.perf_counter() - start})
    return rows


def vetoes(r: Dict, cfg: RegistrationConfig) -> List[str]:
    """Which checks refuse pose row ``r`` under ``cfg``."""
    out = []
    if r["fitness"] < cfg.min_shape_fitness:
        out.append("fitness")
    ratio = r["size_ratio"]
    if ratio is not None and max(ratio, 1.0 / ratio) > cfg.max_size_ratio:
        out.append("size")
    return out


def summarise(rows: List[Dict], cfg: RegistrationConfig) -> Dict:
    right = [r for r in rows if r["wrong"] is False]
    wrong = [r for r in rows if r["wrong"]]
    sizes = [r["size_ratio"] for r in right if r["size_ratio"] is not None]
    refused = [r for r in rows if r["vetoed_by"]]
    return {
        "accepted": len(rows), "right": len(right), "wrong": len(wrong),
        "right_min_fitness": min((r["fitness"] for r in right), default=None),
        "right_size_ratio_range": [min(sizes), max(sizes)] if sizes else None,
        "refused_right": sum(1 for r in refused if r["wrong"] is False),
        "refused_wrong": sum(1 for r in refused if r["wrong"]),
        "refused_gain_db": [r["gain_db"] for r in refused],
        "by_fitness": sum(1 for r in refused if "fitness" in r["vetoed_by"]),
        "by_size": sum(1 for r in refused if "size" in r["vetoed_by"]),
        "min_shape_fitness": cfg.min_shape_fitness, "max_size_ratio": cfg.max_size_ratio,
    }


def _fmt(v: Optional[float], spec: str) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def main(cfg: BenchShapeEvidenceConfig) -> Dict:
    start = time.perf_counter()
    reg = RegistrationConfig()
    rows = [r for run in cfg.runs for r in accepted_poses(Path(run), reg)]
    for r in rows:
        r["vetoed_by"] = vetoes(r, reg)
    by_regime = {regime: summarise([r for r in rows if r["inputs"] == regime], reg)
                 for regime in sorted({r["inputs"] for r in rows})}
    print(f"{'scene':<46} {'inst':>4} {'error °':>8} {'gain dB':>8} {'fitness':>8} {'size':>6}  refused by")
    for r in rows:
        print(f"{r['scene']:<46} {r['instance']:>4} {_fmt(r['rotation_error_deg'], '8.1f')} "
              f"{_fmt(r['gain_db'], '+8.2f')} {r['fitness']:8.2f} {_fmt(r['size_ratio'], '6.2f')}  "
              f"{', '.join(r['vetoed_by']) or '-'}")
    for regime, s in by_regime.items():
        print(f"{regime}: {s['accepted']} accepted ({s['right']} right, {s['wrong']} wrong); right poses: fitness >= "
              f"{_fmt(s['right_min_fitness'], '.2f')}, size {s['right_size_ratio_range']}; refused "
              f"{s['refused_wrong']} wrong, {s['refused_right']} right (by fitness {s['by_fitness']}, by size "
              f"{s['by_size']})")
    checks_s = [r["size_ratio_s"] for r in rows]
    result = {
        "benchmark": "shape_evidence", "runs": [Path(run).name for run in cfg.runs], "rows": rows,
        "summary": by_regime, "size_ratio_s_max": max(checks_s, default=0.0),
        "wall_s": time.perf_counter() - start,
    }
    print(f"{result['wall_s']:.1f} s; the size check itself at most {1e3 * result['size_ratio_s_max']:.1f} ms per instance")
    write_result_json(result, cfg.out)
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchShapeEvidenceConfig))
