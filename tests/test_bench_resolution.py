"""benchmarks/bench_resolution.py: one point per run folder, its size and regime read from the suite's result.json."""

from __future__ import annotations

import json

from benchmark_scripts import load_benchmark


def _run(folder, res, oracle, masked):
    folder.mkdir(parents=True)
    row = {"seed": 8, "variant": "defaults", "gain_masked": masked, "gain_full": 0.5,
           "coverage": {"sharp": {"shared": {"gain": 2.0}}}, "registration": {"failures": [3, 4], "wrong": [2]},
           "time_s": {"ours": 100.0, "baseline": 120.0, "finetune": 40.0}}
    configuration = {"res": res, "base_iterations": 1500, "contrastive_iterations": 500, "finetune_iterations": 1000,
                     "oracle": oracle}
    (folder / "result.json").write_text(json.dumps({"configuration": configuration, "row": row}))
    return folder


def test_points_carry_size_regime_and_figures(tmp_path, capsys):
    bench = load_benchmark("bench_resolution")
    runs = (_run(tmp_path / "a", "192x144", None, 1.3), _run(tmp_path / "b", "96x72", "gt_instances", 4.7))
    result = bench.main(bench.BenchResolutionConfig(runs=runs, out=tmp_path / "out.json"))
    big, small = result["points"]
    assert (big["res"], big["pixels"], big["regime"]) == ("192x144", 192 * 144, "defaults")
    assert (small["regime"], small["gain_masked"], small["not_accepted"], small["wrong"]) == ("exact stages", 4.7, 2, 1)
    assert big["budget"] == "1500+500+1000" and big["gain_shared_sharp"] == 2.0
    table = capsys.readouterr().out
    assert table.index("96x72") < table.index("192x144")  # sorted by size
    assert json.loads((tmp_path / "out.json").read_text())["points"][0]["res"] == "192x144"


def test_keep_adds_only_points_not_measured_again(tmp_path, capsys):
    bench = load_benchmark("bench_resolution")
    earlier = bench.main(bench.BenchResolutionConfig(
        runs=(_run(tmp_path / "a", "192x144", None, 1.3), _run(tmp_path / "b", "96x72", None, 0.9)),
        out=tmp_path / "earlier.json"))
    assert len(earlier["points"]) == 2
    result = bench.main(bench.BenchResolutionConfig(runs=(_run(tmp_path / "c", "96x72", None, 1.7),),
                                                    out=tmp_path / "now.json", keep=tmp_path / "earlier.json"))
    by_res = {p["res"]: p for p in result["points"]}
    assert set(by_res) == {"96x72", "192x144"}
    assert by_res["96x72"]["gain_masked"] == 1.7 and "kept_from" not in by_res["96x72"]  # measured again wins
    assert by_res["192x144"]["gain_masked"] == 1.3 and by_res["192x144"]["kept_from"] == "earlier.json"
    assert "defaults (kept)" in capsys.readouterr().out
