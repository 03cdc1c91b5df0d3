"""The template stage against its ceiling: one change at a time under exact stages.

Reads `splatreplace bench suite` JSONs run with `--from-segmentation --oracle gt_instances` (exact poses and
instances, from the defaults' segmentation of each scene), one JSON per scene and variant; the variant is the run's
`--overrides` (none: the reference). Every variant fine-tunes against the same baseline, so per scene its masked gain
minus the reference's is what the change does to the representation. Also the gain on the test pixels that only
other copies saw well (`shared`, sharp classes of `splatreplace_ns.eval.coverage`; the baseline's figures come from
the defaults' run of the scene, where it recorded them) and the fine-tuning time. Prints the table, writes one JSON.

    splatreplace bench suite --split dev --seeds S --res 96x72 --json D_S.json     # the defaults, per scene S
    splatreplace bench suite --split dev --seeds S --res 96x72 --from-segmentation --oracle gt_instances \
        [--overrides PATH=VALUE] --json V_S.json
    python benchmarks/bench_template_variants.py V_*.json
    python benchmarks/bench_template_variants.py benchmarks/runs/suite/*oracle-gt_instances/result.json   # or the runs
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import tyro

from splatreplace_ns.tools.bench.output import write_result_json

REFERENCE = "exact stages"


@dataclass
class BenchTemplateVariantsConfig:
    runs: Tuple[Path, ...]
    """Suite JSONs run with --from-segmentation --oracle gt_instances (any scenes, any --overrides), or the
    result.json the suite keeps in each such run's folder."""
    runs_dir: Path = Path("benchmarks/runs/suite")
    """Where the suite kept each scene's runs (the defaults' result.json holds the baseline's coverage figures)."""
    out: Path = Path("benchmarks/results/template_variants_dev.json")
    """Where to write the JSON."""


def variant_name(result: Dict) -> str:
    overrides = result["parameters"].get("overrides") or []
    return " ".join(overrides) if overrides else REFERENCE


def baseline_shared(row: Dict, runs_dir: Path, parameters: Dict) -> Optional[float]:
    """The baseline's PSNR on the pixels only other copies saw well, from the defaults' run of the scene."""
    name = f"random_{row['seed']}_{parameters['res']}_{parameters['n_train']}v{parameters['n_test']}"
    budget = f"{parameters['base_iterations']}-{parameters['contrastive_iterations']}-{parameters['finetune_iterations']}"
    saved = runs_dir / f"{name}_{budget}" / "result.json"
    if not saved.exists():
        return None
    coverage = (json.loads(saved.read_text())["row"].get("coverage") or {}).get("sharp") or {}
    return (coverage.get("shared") or {}).get("baseline")


def collect(cfg: BenchTemplateVariantsConfig) -> Dict:
    cells: Dict[str, Dict[int, Dict]] = {}
    for path in cfg.runs:
        result = json.loads(Path(path).read_text())
        if "configuration" in result:  # one scene's result.json in its run folder
            result = {"parameters": result["configuration"], "scenes": [result["row"]]}
        if result["parameters"].get("oracle") != "gt_instances":
            raise ValueError(f"{path}: not run with --oracle gt_instances")
        for row in result["scenes"]:
            sharp = ((row.get("coverage") or {}).get("sharp") or {})
            ours_shared = (sharp.get("shared") or {}).get("ours")
            base_shared = baseline_shared(row, cfg.runs_dir, result["parameters"])
            cells.setdefault(variant_name(result), {})[row["seed"]] = {
                "gain_masked": row["gain_masked"], "gain_full": row["gain_full"],
                "gain_shared_sharp": None if ours_shared is None or base_shared is None else ours_shared - base_shared,
                "shared_sharp_share": (sharp.get("pixel_share") or {}).get("shared"),
                "losing_over_1db": sum(1 for v in row["per_instance"].values() if v["gain"] < -1.0),
                "finetune_s": row["time_s"].get("finetune"),
                "effects": row["effects"],
            }
    if REFERENCE not in cells:
        raise ValueError("no reference run (--oracle gt_instances without --overrides) among the JSONs")
    reference = cells[REFERENCE]
    summary = {}
    for name, by_seed in cells.items():
        seeds = sorted(set(by_seed) & set(reference))
        delta = [by_seed[s]["gain_masked"] - reference[s]["gain_masked"] for s in seeds]
        summary[name] = {"seeds": seeds, "mean_gain": statistics.fmean(by_seed[s]["gain_masked"] for s in seeds),
                         "mean_delta": statistics.fmean(delta), "worst_delta": min(delta)}
    return {"benchmark": "template_variants", "reference": REFERENCE, "variants": cells, "summary": summary}


def print_table(result: Dict) -> None:
    seeds = sorted({s for cells in result["variants"].values() for s in cells})
    print("masked gain over 3DGS* (dB) under exact stages; in brackets the change against the reference; "
          "shared = gain on the pixels only other copies saw well")
    print("| variant | " + " | ".join(f"seed {s}" for s in seeds) + " | mean change |")
    print("|---|" + "---|" * (len(seeds) + 1))
    reference = result["variants"][REFERENCE]
    for name in sorted(result["variants"], key=lambda n: (n != REFERENCE, n)):
        cells = result["variants"][name]
        parts = []
        for s in seeds:
            c = cells.get(s)
            if c is None:
                parts.append("")
                continue
            text = f"{c['gain_masked']:+.2f}"
            if name != REFERENCE and s in reference:
                text += f" ({c['gain_masked'] - reference[s]['gain_masked']:+.2f})"
            if c["gain_shared_sharp"] is not None:
                text += f", shared {c['gain_shared_sharp']:+.2f}"
            parts.append(text)
        st = result["summary"][name]
        print(f"| {name} | " + " | ".join(parts) + f" | {st['mean_delta']:+.2f} (worst {st['worst_delta']:+.2f}) |")


def main(cfg: BenchTemplateVariantsConfig) -> Dict:
    result = collect(cfg)
    print_table(result)
    write_result_json(result, cfg.out)
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchTemplateVariantsConfig))
