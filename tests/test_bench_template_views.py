"""``bench template`` splits the test views by how well the baseline renders them."""

import pytest

from splatreplace_ns.tools.bench.template import gain_by_baseline_quality


def rows(values):
    return [{"view": i, "psnr_masked": v} for i, v in enumerate(values)]


def test_worst_half_is_ranked_by_the_baseline_and_averaged_apart():
    baseline = rows([25.0, 15.0, 26.0, 17.0, 16.0])
    ours = rows([24.0, 19.0, 26.5, 20.0, 18.0])
    split = gain_by_baseline_quality(baseline, ours)
    worst, rest = split["worst_half"], split["rest"]
    assert worst["views"] == [1, 4, 3] and rest["views"] == [0, 2]  # five views: the worse three
    assert worst["baseline"] == pytest.approx(16.0) and worst["ours"] == pytest.approx(19.0)
    assert worst["gain"] == pytest.approx(3.0)
    assert rest["gain"] == pytest.approx((24.0 + 26.5) / 2 - 25.5)
    # the two halves together give the overall average gain
    overall = sum(o["psnr_masked"] - b["psnr_masked"] for b, o in zip(baseline, ours)) / 5
    assert (3 * worst["gain"] + 2 * rest["gain"]) / 5 == pytest.approx(overall)


def test_views_without_the_metric_are_left_out_and_too_few_give_none():
    baseline = rows([20.0, None, 22.0])
    ours = rows([21.0, 30.0, None])
    assert gain_by_baseline_quality(baseline, ours) is None  # only view 0 has both
    split = gain_by_baseline_quality(rows([20.0, None, 22.0]), rows([21.0, 25.0, 22.5]))
    assert split["worst_half"]["views"] == [0] and split["rest"]["views"] == [2]
    assert gain_by_baseline_quality([], []) is None


def test_each_configuration_gets_its_own_run_folder():
    from dataclasses import replace

    from splatreplace_ns.tools.bench.template import BenchTemplateConfig, run_folder_name

    demo = BenchTemplateConfig(preset="office", res="128x96", n_train=48, n_test=8, base_iterations=1500,
                               contrastive_iterations=500, finetune_iterations=1000)
    assert run_folder_name(demo) == "template_office_128x96_48v8_1500-500-1000"
    variants = [
        replace(demo, res="160x120"), replace(demo, n_train=60), replace(demo, n_test=12),
        replace(demo, base_iterations=3000), replace(demo, contrastive_iterations=1000),
        replace(demo, finetune_iterations=2000), replace(demo, light="overhead"), replace(demo, preset="temple"),
    ]
    names = {run_folder_name(c) for c in variants}
    assert len(names) == len(variants) and run_folder_name(demo) not in names
    # what does not change the training (ablations, threads, where the JSON goes) keeps the folder
    same = replace(demo, ablations=("shared_only",), threads=1, json=None)
    assert run_folder_name(same) == run_folder_name(demo)
