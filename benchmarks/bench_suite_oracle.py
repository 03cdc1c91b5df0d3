"""Where the scene suite's gain is lost: the defaults against the same scenes with exact stages.

Reads up to three `splatreplace bench suite` JSONs of the same split, budget and scenes: the defaults, and the
oracles resumed from the defaults' segmentation (`--from-segmentation --oracle gt_poses`, `--oracle gt_instances`).
The oracles fine-tune against the same baseline, so per scene the differences split the masked gain's distance from
what the representation reaches with exact stages (gt_instances, the ceiling at this budget):

    registration's cost  = gain(gt_poses) - gain(defaults)       (same segmentation, exact poses)
    segmentation's cost  = gain(gt_instances) - gain(gt_poses)   (exact poses, exact Gaussians per instance)
    the stages' cost     = gain(gt_instances) - gain(defaults)   (both; the only one without a gt_poses run)

Per instance: the baseline's PSNR over its test-view pixels and its gain under each run. Per scene and run, where
the suite measured it: the gain on the instance pixels of each sharp class (own: the copy's own training views saw
that point as sharply as the test view; shared: only other copies' did; unseen: none did;
``splatreplace_ns.eval.coverage``), which says whether the gap to a target lies in pixels sharing can reach.
Prints the tables and writes one JSON.

    splatreplace bench suite --split dev --seeds 0 1 2 3 4 5 --res 96x72 --json D.json
    splatreplace bench suite --split dev --seeds 0 1 2 3 4 5 --res 96x72 --from-segmentation --oracle gt_poses --json P.json
    splatreplace bench suite --split dev --seeds 0 1 2 3 4 5 --res 96x72 --from-segmentation --oracle gt_instances --json I.json
    python benchmarks/bench_suite_oracle.py --defaults D.json --gt-poses P.json --gt-instances I.json

Without ``--gt-instances`` only registration's cost is split off (and the tables leave the ceiling out); without
``--gt-poses`` only the stages' cost together.
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import tyro

from splatreplace_ns.eval.coverage import CLASS_NAMES
from splatreplace_ns.eval.coverage_scores import mean_coverage_gains
from splatreplace_ns.eval.metrics import mse_to_psnr
from splatreplace_ns.tools.bench.output import write_result_json

RUNS = ("defaults", "gt_poses", "gt_instances")
SHARP_CLASSES = tuple(CLASS_NAMES.values())  # own, shared, unseen
WRONG_POSE_DEG = 5.0
"""As the suite counts a wrong pose (``splatreplace_ns.tools.bench.suite.WRONG_POSE_DEG``)."""


@dataclass
class BenchSuiteOracleConfig:
    defaults: Tuple[Path, ...]
    """Suite JSONs with the defaults (several when the scenes ran in parts)."""
    gt_poses: Tuple[Path, ...] = ()
    """Suite JSONs of the same scenes with --from-segmentation --oracle gt_poses (none: registration's and
    segmentation's costs are not told apart)."""
    gt_instances: Tuple[Path, ...] = ()
    """Suite JSONs of the same scenes with --from-segmentation --oracle gt_instances (none: segmentation's cost is
    not measured)."""
    out: Path = Path("benchmarks/results/suite_dev_oracle.json")
    """Where to write the JSON."""


IGNORED = ("oracle", "from_segmentation", "registration", "overrides")  # how a run was made, not its scenes or budget


def rows_by_seed(paths: Tuple[Path, ...], oracle: Optional[str]) -> Tuple[Dict, Dict[int, Dict]]:
    """The parameters the JSONs share and every scene's row by seed.

    Raises:
        ValueError: when a JSON was run with another oracle than ``oracle`` or with other parameters.
    """
    results = [json.loads(Path(p).read_text()) for p in paths]
    for result, path in zip(results, paths):
        if result["parameters"].get("oracle") != oracle:
            raise ValueError(f"{path}: run with oracle {result['parameters'].get('oracle')!r}, expected {oracle!r}")
        if comparable(result) != comparable(results[0]):
            raise ValueError(f"{path} was run with other parameters than {paths[0]}")
    return comparable(results[0]), {int(r["seed"]): r for result in results for r in result["scenes"]}


def comparable(result: Dict) -> Dict:
    return {"split": result["split"], **{k: v for k, v in result["parameters"].items() if k not in IGNORED}}


def decompose(rows: Dict[str, Dict[int, Dict]]) -> Dict[str, List[Dict]]:
    """Per scene (seeds every run has): the masked and full gains of each run and the two costs; per instance: the
    baseline's PSNR, the gain under each run and how the defaults treated it."""
    scenes, instances = [], []
    runs = tuple(rows)
    for seed in sorted(set.intersection(*(set(r) for r in rows.values()))):
        by = {k: rows[k][seed] for k in runs}
        masked = {k: by[k]["gain_masked"] for k in runs}
        scenes.append({
            "seed": seed,
            "effects": by["defaults"]["effects"],
            "classes": [f"{g['count']} {g['cls']}" for g in by["defaults"]["scene"].get("groups", [])],
            "baseline_masked": by["defaults"]["baseline"]["psnr_masked"],
            "gain_masked": masked,
            "gain_full": {k: by[k]["gain_full"] for k in runs},
            "registration_cost": cost(masked, "gt_poses", "defaults"),
            "segmentation_cost": cost(masked, "gt_instances", "gt_poses"),
            "stages_cost": cost(masked, "gt_instances", "defaults"),
            "sharp_classes": {k: sharp_classes(by[k]) for k in runs},
            "not_accepted": len(by["defaults"]["registration"]["failures"]),
            "losing_over_1db": {k: sum(v["gain"] < -1.0 for v in by[k]["per_instance"].values()) for k in runs},
        })
        registered = {int(r["gt_id"]): r for r in by["defaults"]["registration"].get("per_instance", [])
                      if r.get("gt_id") is not None}
        for key in sorted(set.intersection(*(set(by[k]["per_instance"]) for k in runs)), key=int):
            entry = registered.get(int(key))
            instances.append({"seed": seed, "instance": int(key),
                              "baseline": by["defaults"]["per_instance"][key]["baseline"],
                              "gain": {k: by[k]["per_instance"][key]["gain"] for k in runs},
                              "defaults": instance_status(entry),
                              "rotation_error_deg": None if entry is None else entry.get(
                                  "rotation_error_deg" if entry["success"] else "proposed_rotation_error_deg")})
    return {"scenes": scenes, "instances": instances}


def cost(masked: Dict[str, float], better: str, worse: str) -> Optional[float]:
    """gain(better) - gain(worse) where both ran, else None."""
    return masked[better] - masked[worse] if better in masked and worse in masked else None


def sharp_classes(row: Dict) -> Optional[Dict]:
    """A suite row's masked gain on each sharp class's pixels and the classes' share of the instance pixels (None
    where the suite did not class them: no ground truth to class by)."""
    sharp = (row.get("coverage") or {}).get("sharp")
    if not sharp:
        return None
    return {**{c: {m: sharp[c][m] for m in ("baseline", "ours", "gain")} for c in SHARP_CLASSES},
            "pixels": {c: sharp["pixels"][c] for c in SHARP_CLASSES},
            "pixel_share": {c: sharp["pixel_share"][c] for c in SHARP_CLASSES}}


def pooled_gain(classed: List[Dict], cls: str) -> Optional[float]:
    """The gain on one class's pixels of all scenes pooled: each method's PSNR over the union of the pixels (the
    per-scene mean squared errors weighted by pixel count), so a scene with a few dozen pixels of the class weighs
    that much. None where no scene has pixels of the class."""
    rows = [c for c in classed if c["pixels"][cls] and c[cls]["baseline"] is not None]
    if not rows:
        return None
    n = sum(c["pixels"][cls] for c in rows)

    def pooled_psnr(method: str) -> float:
        return mse_to_psnr(sum(c["pixels"][cls] * 10.0 ** (-c[cls][method] / 10.0) for c in rows) / n)

    return pooled_psnr("ours") - pooled_psnr("baseline")


def sharp_summary(scenes: List[Dict], run: str) -> Optional[Dict]:
    """Over the scenes whose run classed its pixels: the mean gain on each class (over the scenes with pixels of
    that class), the gain on the class's pixels pooled over the scenes, and the mean share of shared pixels."""
    classed = [s["sharp_classes"][run] for s in scenes if s["sharp_classes"].get(run)]
    if not classed:
        return None
    out = {"scenes": len(classed), "shared_pixel_share_mean": statistics.fmean(c["pixel_share"]["shared"]
                                                                                for c in classed)}
    means = mean_coverage_gains(classed)
    for c in SHARP_CLASSES:
        out[f"{c}_gain_mean"] = means[c]
        out[f"{c}_gain_pooled"] = pooled_gain(classed, c)
    return out


def instance_status(entry: Optional[Dict]) -> str:
    """How the defaults treated an instance: its class's template (no registration entry), replaced under a pose
    within or beyond WRONG_POSE_DEG of the truth, or not replaced."""
    if entry is None:
        return "template"
    if not entry["success"]:
        return "not replaced"
    error = entry.get("rotation_error_deg")
    return "replaced" if error is None or error <= WRONG_POSE_DEG else "replaced, wrong"


def by_status(instances: List[Dict]) -> Dict[str, Dict]:
    """Per status of the defaults: how many instances, and their mean gain under the defaults and with exact poses
    (the registration's cost where it lies: refusals, or poses accepted but off)."""
    out = {}
    for status in ("template", "replaced", "replaced, wrong", "not replaced"):
        rows = [i for i in instances if i["defaults"] == status]
        if rows:
            out[status] = {"count": len(rows),
                           **{f"gain_{k}": statistics.fmean(i["gain"][k] for i in rows) for k in rows[0]["gain"]}}
    return out


def summarise(diff: Dict[str, List[Dict]]) -> Dict:
    """Mean, worst and standard deviation of each run's masked gain, the mean costs, and the same means over the
    scenes with and without coverage imbalance (the effect that makes some copies badly seen)."""

    def stats(scenes: List[Dict]) -> Optional[Dict]:
        if not scenes:
            return None
        out = {"scenes": len(scenes)}
        for k in scenes[0]["gain_masked"]:
            g = [s["gain_masked"][k] for s in scenes]
            out[k] = {"mean": statistics.fmean(g), "worst": min(g), "sd": statistics.pstdev(g),
                      "full_mean": statistics.fmean(s["gain_full"][k] for s in scenes),
                      "full_worst": min(s["gain_full"][k] for s in scenes),
                      "losing_over_1db": sum(s["losing_over_1db"][k] for s in scenes),
                      "sharp_classes": sharp_summary(scenes, k)}
        for name in ("registration_cost", "segmentation_cost", "stages_cost"):
            out[f"{name}_mean"] = (None if scenes[0][name] is None
                                   else statistics.fmean(s[name] for s in scenes))
        return out

    scenes = diff["scenes"]
    return {"all": stats(scenes), "instances_by_status": by_status(diff["instances"]),
            "coverage_imbalance": stats([s for s in scenes if "coverage_imbalance" in s["effects"]]),
            "no_coverage_imbalance": stats([s for s in scenes if "coverage_imbalance" not in s["effects"]])}


def print_table(result: Dict) -> None:
    runs = tuple(result["runs"])
    def signed(x: Optional[float]) -> str:
        return "" if x is None else f"{x:+.2f}"

    print(f"{'seed':>5} {'classes':<28} {'3DGS* masked':>12} " + " ".join(f"{k[:9]:>9}" for k in runs)
          + f" {'reg. cost':>9} {'seg. cost':>9} {'stages':>7} {'full, each run':>22} {'lose>1dB':>10}")
    for s in result["scenes"]:
        g, f, n = s["gain_masked"], s["gain_full"], s["losing_over_1db"]
        print(f"{s['seed']:>5} {', '.join(s['classes']):<28} {s['baseline_masked']:>12.2f} "
              + " ".join(f"{g[k]:>+9.2f}" for k in runs)
              + f" {signed(s['registration_cost']):>9} {signed(s['segmentation_cost']):>9}"
              + f" {signed(s['stages_cost']):>7} "
              + f"{' / '.join(f'{f[k]:+.2f}' for k in runs):>22} {' / '.join(str(n[k]) for k in runs):>10}")
    print("masked gain per sharp class (own / shared / unseen) and the share of shared pixels:")
    for s in result["scenes"]:
        cells = []
        for k in runs:
            c = s["sharp_classes"].get(k)
            cells.append(f"{k}: " + ("not classed" if c is None else " / ".join(
                signed(c[x]["gain"]) or "-" for x in SHARP_CLASSES)))
        share = next((c["pixel_share"]["shared"] for c in s["sharp_classes"].values() if c), None)
        print(f"{s['seed']:>5} shared {'-' if share is None else f'{100 * share:.0f} %':>5}  " + "; ".join(cells))
    for status, st in result["summary"]["instances_by_status"].items():
        print(f"instances {status} by the defaults: {st['count']}, mean gain " + ", ".join(
            f"{k} {st[f'gain_{k}']:+.2f}" for k in runs))
    for name, st in result["summary"].items():
        if st is None or name == "instances_by_status":
            continue
        reg, seg, both = (st[f"{c}_cost_mean"] for c in ("registration", "segmentation", "stages"))
        costs = ([] if reg is None else [f"registration costs {reg:+.2f} dB"]) + (
            [] if seg is None else [f"segmentation {seg:+.2f} dB"]) + (
            [f"the stages together {both:+.2f} dB"] if reg is None and both is not None else [])
        print(f"{name} ({st['scenes']} scenes): masked gain mean " + ", ".join(
            f"{k} {st[k]['mean']:+.2f} (worst {st[k]['worst']:+.2f}, sd {st[k]['sd']:.2f})" for k in runs)
            + ("; " + ", ".join(costs) if costs else ""))
        for k in runs:
            sharp = st[k]["sharp_classes"]
            if sharp:
                print(f"  {k}: own {signed(sharp['own_gain_mean'])}, shared {signed(sharp['shared_gain_mean'])} dB"
                      f" ({100 * sharp['shared_pixel_share_mean']:.0f} % of the pixels shared); pooled over the"
                      f" scenes' pixels own {signed(sharp['own_gain_pooled'])}, shared"
                      f" {signed(sharp['shared_gain_pooled'])} dB")


def main(cfg: BenchSuiteOracleConfig) -> Dict:
    given = {k: paths for k, paths in zip(RUNS, (cfg.defaults, cfg.gt_poses, cfg.gt_instances)) if paths}
    if "defaults" not in given or len(given) < 2:
        raise ValueError("give the defaults' JSONs and at least one oracle's (--gt-poses, --gt-instances)")
    loaded = {k: rows_by_seed(paths, None if k == "defaults" else k) for k, paths in given.items()}
    parameters = loaded["defaults"][0]
    for k in list(loaded)[1:]:
        if loaded[k][0] != parameters:
            raise ValueError(f"the {k} runs differ from the defaults in more than the oracle: {loaded[k][0]} "
                             f"against {parameters}")
    diff = decompose({k: rows for k, (_, rows) in loaded.items()})
    if not diff["scenes"]:
        raise ValueError(f"no scene was run by all {len(loaded)}")
    result = {"benchmark": "suite_oracle", "parameters": parameters,
              "runs": {k: [Path(p).name for p in paths] for k, paths in given.items()},
              "time_s": {k: sum(r["time_s"]["ours"] for r in rows.values()) for k, (_, rows) in loaded.items()},
              "summary": summarise(diff), **diff}
    print_table(result)
    write_result_json(result, cfg.out)
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchSuiteOracleConfig))
