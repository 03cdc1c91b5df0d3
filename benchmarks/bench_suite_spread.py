"""The scene suite's run-to-run spread: the same scenes, code and budget trained with two training seeds.

Reads two `splatreplace bench suite` JSONs of the same split, budget and scenes, one of them run with
`--training-seed` (torch's seed and the order the training views are drawn in, for ours and the baseline).
Per scene: each run's masked and full gain over 3DGS*, and how far the two runs' gains, ours' PSNR and the
baseline's PSNR lie apart; per instance: how far its gain moved. Prints the table and writes one JSON.

    splatreplace bench suite --split dev --seeds 0 1 2 3 4 5 --res 96x72 --json A.json
    splatreplace bench suite --split dev --seeds 0 1 2 3 4 5 --res 96x72 --training-seed 1 --json B.json
    python benchmarks/bench_suite_spread.py --runs-a A.json --runs-b B.json --out benchmarks/results/suite_dev_spread.json
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import tyro


@dataclass
class BenchSuiteSpreadConfig:
    runs_a: Tuple[Path, ...]
    """Suite JSONs of one training seed (several when its scenes ran in parts)."""
    runs_b: Tuple[Path, ...]
    """Suite JSONs of the same scenes and budget with another training seed."""
    out: Path = Path("benchmarks/results/suite_dev_spread.json")
    """Where to write the JSON."""


IGNORED = ("training_seed", "overrides", "reuse_baseline")  # how a run was made, not what it trained


def rows_by_seed(paths: Tuple[Path, ...]) -> Tuple[Dict, Dict[int, Dict]]:
    """The first JSON's header and every scene's row; the JSONs must share split and parameters."""
    results = [json.loads(Path(p).read_text()) for p in paths]
    first = results[0]
    for other, path in zip(results[1:], paths[1:]):
        if (other["split"], comparable(other)) != (first["split"], comparable(first)):
            raise ValueError(f"{path} was run with other parameters than {paths[0]}")
    return first, {int(r["seed"]): r for result in results for r in result["scenes"]}


def comparable(result: Dict) -> Dict:
    return {k: v for k, v in result["parameters"].items() if k not in IGNORED}


def compare(a: Dict[int, Dict], b: Dict[int, Dict]) -> Dict:
    """Per-scene and per-instance differences between two runs of the same scenes (b minus a)."""
    scenes, instances = [], []
    for seed in sorted(set(a) & set(b)):
        ra, rb = a[seed], b[seed]
        scenes.append({
            "seed": seed,
            "gain_masked": [ra["gain_masked"], rb["gain_masked"]],
            "gain_full": [ra["gain_full"], rb["gain_full"]],
            "d_gain_masked": rb["gain_masked"] - ra["gain_masked"],
            "d_gain_full": rb["gain_full"] - ra["gain_full"],
            "d_ours_masked": rb["ours"]["psnr_masked"] - ra["ours"]["psnr_masked"],
            "d_baseline_masked": rb["baseline"]["psnr_masked"] - ra["baseline"]["psnr_masked"],
            "miou": [ra.get("segmentation_miou"), rb.get("segmentation_miou")],
        })
        for key in sorted(set(ra["per_instance"]) & set(rb["per_instance"]), key=int):
            ga, gb = ra["per_instance"][key]["gain"], rb["per_instance"][key]["gain"]
            instances.append({"seed": seed, "instance": int(key), "gain": [ga, gb], "d_gain": gb - ga})
    return {"scenes": scenes, "instances": instances}


def summary(diff: Dict) -> Dict:
    """Standard deviation of one run's figure implied by the two runs' differences (|d| / sqrt(2) on average:
    d = x_b - x_a of two independent draws has twice the variance of one), and the largest differences."""

    def one_run_sd(values: List[float]) -> float:
        return (statistics.fmean(v * v for v in values) / 2) ** 0.5

    out = {}
    for key in ("d_gain_masked", "d_gain_full", "d_ours_masked", "d_baseline_masked"):
        values = [s[key] for s in diff["scenes"]]
        out[key] = {"one_run_sd": one_run_sd(values), "max_abs": max(abs(v) for v in values)}
    d = [i["d_gain"] for i in diff["instances"]]
    mean_a = statistics.fmean(s["gain_masked"][0] for s in diff["scenes"])
    mean_b = statistics.fmean(s["gain_masked"][1] for s in diff["scenes"])
    out["instances"] = {"count": len(d), "one_run_sd": one_run_sd(d), "moved_over_1db": sum(abs(v) > 1 for v in d),
                        "losing_over_1db": [sum(i["gain"][k] < -1 for i in diff["instances"]) for k in (0, 1)]}
    out["mean_gain_masked"] = [mean_a, mean_b]
    return out


def main(cfg: BenchSuiteSpreadConfig) -> Dict:
    (result_a, a), (result_b, b) = rows_by_seed(cfg.runs_a), rows_by_seed(cfg.runs_b)
    if (result_a["split"], comparable(result_a)) != (result_b["split"], comparable(result_b)):
        raise ValueError(f"the two sides differ in more than the training seed: {comparable(result_a)} against "
                         f"{comparable(result_b)}")
    diff = compare(a, b)
    result = {"benchmark": "suite_spread", "runs": [[Path(p).name for p in cfg.runs_a], [Path(p).name for p in cfg.runs_b]],
              "training_seeds": [result_a["parameters"].get("training_seed", 42), result_b["parameters"].get("training_seed", 42)],
              "split": result_a["split"], "parameters": result_a["parameters"], "summary": summary(diff), **diff}
    print(f"{'seed':>5} {'masked gain a → b':>20} {'full gain a → b':>18} {'Δ ours masked':>14} {'Δ 3DGS* masked':>15} {'mIoU a / b':>12}")
    for s in diff["scenes"]:
        miou = " / ".join("n/a" if m is None else f"{m:.2f}" for m in s["miou"])
        print(f"{s['seed']:>5} {s['gain_masked'][0]:+8.2f} → {s['gain_masked'][1]:+7.2f} "
              f"{s['gain_full'][0]:+7.2f} → {s['gain_full'][1]:+7.2f} {s['d_ours_masked']:+14.2f} "
              f"{s['d_baseline_masked']:+15.2f} {miou:>12}")
    sm = result["summary"]
    print(f"one run's standard deviation (from the differences): masked gain {sm['d_gain_masked']['one_run_sd']:.2f} dB, "
          f"full gain {sm['d_gain_full']['one_run_sd']:.2f}, ours masked {sm['d_ours_masked']['one_run_sd']:.2f}, "
          f"3DGS* masked {sm['d_baseline_masked']['one_run_sd']:.2f}; per instance gain {sm['instances']['one_run_sd']:.2f} dB "
          f"({sm['instances']['moved_over_1db']} of {sm['instances']['count']} moved more than 1 dB)")
    cfg.out.parent.mkdir(parents=True, exist_ok=True)
    cfg.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {cfg.out}")
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchSuiteSpreadConfig))
