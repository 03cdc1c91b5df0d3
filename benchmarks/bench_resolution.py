"""Does the gain grow with the image? One scene's runs at several image sizes, the defaults and exact stages.

Reads the result.json that `splatreplace bench suite` keeps in each run's folder (any sizes, the defaults' runs and
their `--from-segmentation --oracle gt_instances` runs) and prints, per size and regime, the masked and full gain
over 3DGS*, the gain on the pixels only other copies saw well, the poses not accepted, and the wall time of ours
and of 3DGS* (trained beside each other on the defaults' run; the oracle fine-tunes alone). Writes one JSON.

    splatreplace bench suite --split dev --seeds 8 --res 192x144                          # the defaults, per size
    splatreplace bench suite --split dev --seeds 8 --res 192x144 --from-segmentation --oracle gt_instances
    python benchmarks/bench_resolution.py --runs benchmarks/runs/suite/random_8_192x144_48v8_1500-500-1000 ...

With ``--keep`` an earlier JSON's points that no given run folder measures again (same seed, size and regime) stay
in the table, marked ``kept_from`` (they were measured at the code of that JSON's run, not this one).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import tyro

from splatreplace_ns.tools.bench.output import write_result_json


@dataclass
class BenchResolutionConfig:
    runs: Tuple[Path, ...]
    """Run folders of `splatreplace bench suite` (each holding its result.json)."""
    out: Path = Path("benchmarks/results/resolution_dev.json")
    """Where to write the JSON."""
    keep: Optional[Path] = None
    """An earlier JSON of this script whose points not measured again by ``runs`` are kept (marked ``kept_from``)."""


def point(folder: Path) -> Dict:
    """One run folder → its size, regime and figures."""
    saved = json.loads((Path(folder) / "result.json").read_text())
    configuration, row = saved["configuration"], saved["row"]
    shared = (((row.get("coverage") or {}).get("sharp") or {}).get("shared") or {}).get("gain")
    w, h = (int(x) for x in configuration["res"].split("x"))
    return {"seed": row["seed"], "res": configuration["res"], "pixels": w * h,
            "regime": "exact stages" if configuration.get("oracle") == "gt_instances" else "defaults",
            "variant": row.get("variant"),
            "budget": f"{configuration['base_iterations']}+{configuration['contrastive_iterations']}+"
                      f"{configuration['finetune_iterations']}",
            "gain_masked": row["gain_masked"], "gain_full": row["gain_full"], "gain_shared_sharp": shared,
            "not_accepted": len(row["registration"]["failures"]), "wrong": len(row["registration"]["wrong"]),
            "ours_s": row["time_s"]["ours"], "baseline_s": row["time_s"]["baseline"],
            "finetune_s": row["time_s"].get("finetune")}


def key(p: Dict) -> Tuple:
    """What makes two points the same point of the curve."""
    return p["seed"], p["res"], p["regime"]


def kept_points(earlier: Path, measured: List[Dict]) -> List[Dict]:
    """The points of an earlier JSON that ``measured`` does not measure again, each marked with where it came from."""
    again = {key(p) for p in measured}
    return [{**p, "kept_from": p.get("kept_from") or earlier.name}
            for p in json.loads(Path(earlier).read_text())["points"] if key(p) not in again]


def table(points: List[Dict]) -> None:
    print("| seed | size | regime | masked gain | full gain | shared pixels | not accepted / wrong | ours, s | 3DGS*, s |")
    print("| ---: | --- | --- | ---: | ---: | ---: | --- | ---: | ---: |")
    for p in sorted(points, key=lambda p: (p["seed"], p["pixels"], p["regime"])):
        regime = p["regime"] + (" (kept)" if p.get("kept_from") else "")
        shared = "–" if p["gain_shared_sharp"] is None else f"{p['gain_shared_sharp']:+.2f}"
        print(f"| {p['seed']} | {p['res']} | {regime} | {p['gain_masked']:+.2f} | {p['gain_full']:+.2f} | {shared} | "
              f"{p['not_accepted']} / {p['wrong']} | {p['ours_s']:.0f} | {p['baseline_s']:.0f} |")


def main(cfg: BenchResolutionConfig) -> Dict:
    points = [point(folder) for folder in cfg.runs]
    if cfg.keep is not None:
        points += kept_points(cfg.keep, points)
    table(points)
    result = {"benchmark": "resolution", "points": points}
    write_result_json(result, cfg.out)
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchResolutionConfig))
