"""benchmarks/bench_suite_oracle.py: the suite's gain split into what registration and segmentation cost."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_suite_oracle")


def suite_json(path: Path, oracle, gains, instance_gains, effects=("far_test_views",), res="96x72",
               sharp=None) -> Path:
    """A suite result with one scene per seed: ``gains`` {seed: masked gain}; ``instance_gains`` {seed: [gain]};
    ``sharp`` {seed: (own gain, shared gain, shared pixel share)}: the sharp classes of those seeds."""
    parameters = {"res": res, "n_train": 48, "base_iterations": 1500, "registration": "ours", "overrides": [],
                  "from_segmentation": oracle is not None, **({"oracle": oracle} if oracle else {})}
    scenes = [{
        "seed": seed, "effects": list(effects), "scene": {"groups": [{"cls": "crate", "count": 3}]},
        "baseline": {"psnr_masked": 20.0}, "gain_masked": gain, "gain_full": gain / 2,
        "per_instance": {str(i + 1): {"baseline": 20.0, "gain": g} for i, g in enumerate(instance_gains[seed])},
        "registration": {"failures": [2] if oracle is None else [], "per_instance": [
            {"gt_id": 1, "success": True, "rotation_error_deg": 2.0 if seed == 0 else 30.0},
            {"gt_id": 2, "success": False, "rotation_error_deg": 0.0, "proposed_rotation_error_deg": 1.0},
        ] if oracle is None else []}, "time_s": {"ours": 60.0},
        **({"coverage": sharp_coverage(*sharp[seed])} if sharp and seed in sharp else {}),
    } for seed, gain in gains.items()]
    path.write_text(json.dumps({"split": "dev", "parameters": parameters, "scenes": scenes}))
    return path


def sharp_coverage(own: float, shared: float, shared_share: float, pixels: int = 1000) -> dict:
    """The suite's coverage entry with only its sharp classes filled in (no unseen pixels; the baseline at 20 dB)."""
    classes = {"own": {"gain": own, "baseline": 20.0, "ours": 20.0 + own},
               "shared": {"gain": shared, "baseline": 20.0, "ours": 20.0 + shared},
               "unseen": {"gain": None, "baseline": None, "ours": None}}
    share = {"own": 1.0 - shared_share, "shared": shared_share, "unseen": 0.0}
    counts = {"own": round(pixels * (1.0 - shared_share)), "shared": round(pixels * shared_share), "unseen": 0}
    return {"sharp": {**classes, "pixels": counts, "pixel_share": share}}


def test_costs_are_the_differences_between_the_runs(bench, tmp_path, capsys):
    d = suite_json(tmp_path / "d.json", None, {0: 0.5, 1: 2.0}, {0: [-1.5, 0.2], 1: [2.0, 1.0]})
    p = suite_json(tmp_path / "p.json", "gt_poses", {0: 1.0, 1: 2.2}, {0: [0.5, 0.2], 1: [2.0, 1.5]})
    i = suite_json(tmp_path / "i.json", "gt_instances", {0: 1.5, 1: 2.1}, {0: [0.6, 0.3], 1: [2.2, 1.4]})
    result = bench.main(bench.BenchSuiteOracleConfig(defaults=(d,), gt_poses=(p,), gt_instances=(i,),
                                                     out=tmp_path / "out.json"))
    first, second = result["scenes"]
    assert first["registration_cost"] == pytest.approx(0.5) and first["segmentation_cost"] == pytest.approx(0.5)
    assert second["registration_cost"] == pytest.approx(0.2) and second["segmentation_cost"] == pytest.approx(-0.1)
    assert first["losing_over_1db"] == {"defaults": 1, "gt_poses": 0, "gt_instances": 0}
    assert first["not_accepted"] == 1
    summary = result["summary"]["all"]
    assert summary["gt_instances"]["mean"] == pytest.approx(1.8) and summary["defaults"]["worst"] == pytest.approx(0.5)
    assert summary["registration_cost_mean"] == pytest.approx(0.35)
    assert result["summary"]["coverage_imbalance"] is None and result["summary"]["no_coverage_imbalance"]["scenes"] == 2
    assert len(result["instances"]) == 4 and result["instances"][0]["gain"]["gt_poses"] == pytest.approx(0.5)
    assert [i["defaults"] for i in result["instances"]] == ["replaced", "not replaced", "replaced, wrong", "not replaced"]
    assert result["instances"][1]["rotation_error_deg"] == 1.0  # a refused instance: the pose it refused
    refused = result["summary"]["instances_by_status"]["not replaced"]
    assert refused["count"] == 2 and refused["gain_gt_poses"] == pytest.approx((0.2 + 1.5) / 2)
    assert json.loads((tmp_path / "out.json").read_text())["summary"] == result["summary"]
    assert "registration costs +0.35" in capsys.readouterr().out


def test_without_exact_instances_only_registrations_cost_is_split_off(bench, tmp_path, capsys):
    d = suite_json(tmp_path / "d.json", None, {0: 0.5, 1: 2.0}, {0: [-1.5, 0.2], 1: [2.0, 1.0]})
    p = suite_json(tmp_path / "p.json", "gt_poses", {0: 1.0, 1: 2.2}, {0: [0.5, 0.2], 1: [2.0, 1.5]})
    result = bench.main(bench.BenchSuiteOracleConfig(defaults=(d,), gt_poses=(p,), out=tmp_path / "out.json"))
    assert [s["registration_cost"] for s in result["scenes"]] == pytest.approx([0.5, 0.2])
    assert [s["segmentation_cost"] for s in result["scenes"]] == [None, None]
    assert set(result["runs"]) == {"defaults", "gt_poses"}
    summary = result["summary"]["all"]
    assert summary["segmentation_cost_mean"] is None and "gt_instances" not in summary
    assert result["summary"]["instances_by_status"]["not replaced"]["gain_gt_poses"] == pytest.approx((0.2 + 1.5) / 2)
    out = capsys.readouterr().out
    assert "registration costs +0.35 dB" in out and "segmentation" not in out


def test_runs_of_other_scenes_or_oracles_are_refused(bench, tmp_path):
    d = suite_json(tmp_path / "d.json", None, {0: 0.5}, {0: [0.1]})
    p = suite_json(tmp_path / "p.json", "gt_poses", {0: 1.0}, {0: [0.2]})
    i = suite_json(tmp_path / "i.json", "gt_instances", {0: 1.5}, {0: [0.3]})
    other_res = suite_json(tmp_path / "r.json", "gt_instances", {0: 1.5}, {0: [0.3]}, res="128x96")
    out = tmp_path / "out.json"
    with pytest.raises(ValueError, match="expected 'gt_poses'"):
        bench.main(bench.BenchSuiteOracleConfig(defaults=(d,), gt_poses=(i,), gt_instances=(i,), out=out))
    with pytest.raises(ValueError, match="differ from the defaults in more than the oracle"):
        bench.main(bench.BenchSuiteOracleConfig(defaults=(d,), gt_poses=(p,), gt_instances=(other_res,), out=out))
    elsewhere = suite_json(tmp_path / "e.json", "gt_instances", {5: 1.5}, {5: [0.3]})
    with pytest.raises(ValueError, match="no scene was run by all 3"):
        bench.main(bench.BenchSuiteOracleConfig(defaults=(d,), gt_poses=(p,), gt_instances=(elsewhere,), out=out))
    assert not out.exists()


def test_without_exact_poses_the_stages_cost_together_and_sharp_classes_are_kept(bench, tmp_path, capsys):
    d = suite_json(tmp_path / "d.json", None, {0: 0.5, 1: 2.0}, {0: [-1.5, 0.2], 1: [2.0, 1.0]},
                   sharp={0: (0.4, 1.0, 0.1), 1: (1.5, 3.0, 0.4)})
    i = suite_json(tmp_path / "i.json", "gt_instances", {0: 1.5, 1: 4.0}, {0: [0.6, 0.3], 1: [2.2, 1.4]},
                   sharp={0: (1.2, 4.0, 0.1)}, effects=("coverage_imbalance",))
    result = bench.main(bench.BenchSuiteOracleConfig(defaults=(d,), gt_instances=(i,), out=tmp_path / "out.json"))
    first, second = result["scenes"]
    assert first["stages_cost"] == pytest.approx(1.0) and second["stages_cost"] == pytest.approx(2.0)
    assert first["registration_cost"] is None and first["segmentation_cost"] is None
    assert {c: first["sharp_classes"]["gt_instances"][c]["gain"] for c in ("own", "shared", "unseen")} == {
        "own": 1.2, "shared": 4.0, "unseen": None}
    assert second["sharp_classes"]["gt_instances"] is None  # that run did not class its pixels
    summary = result["summary"]["all"]
    assert summary["stages_cost_mean"] == pytest.approx(1.5) and summary["registration_cost_mean"] is None
    defaults = summary["defaults"]["sharp_classes"]
    assert defaults["scenes"] == 2 and defaults["shared_gain_mean"] == pytest.approx(2.0)
    assert defaults["own_gain_mean"] == pytest.approx(0.95) and defaults["unseen_gain_mean"] is None
    assert defaults["shared_pixel_share_mean"] == pytest.approx(0.25)
    # pooled: 100 shared pixels at +1 dB and 400 at +3 dB, both against a 20 dB baseline
    pooled = -10 * math.log10((100 * 10 ** -2.1 + 400 * 10 ** -2.3) / 500) - 20.0
    assert defaults["shared_gain_pooled"] == pytest.approx(pooled) and 1.0 < pooled < 3.0
    assert defaults["unseen_gain_pooled"] is None
    assert summary["gt_instances"]["sharp_classes"]["scenes"] == 1
    out = capsys.readouterr().out
    assert "the stages together +1.50 dB" in out and "registration costs" not in out
    assert "shared +4.00 dB" in out  # the oracle's summary line


def test_the_defaults_alone_are_refused(bench, tmp_path):
    d = suite_json(tmp_path / "d.json", None, {0: 0.5}, {0: [0.1]})
    with pytest.raises(ValueError, match="at least one oracle"):
        bench.main(bench.BenchSuiteOracleConfig(defaults=(d,), out=tmp_path / "out.json"))
