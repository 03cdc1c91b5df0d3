"""``bench mask-passes``: what each variant switches off, and how its runs are summarised."""

from __future__ import annotations

import dataclasses

import pytest

from splatreplace_ns.tools.bench.mask_passes import (
    PASSES, BenchMaskPassesConfig, summarise_passes, variant_settings,
)
from splatreplace_ns.instances.geometric_config import ClusteringConfig


def test_every_variant_changes_real_settings_away_from_the_defaults(monkeypatch):
    defaults = ClusteringConfig()
    fields = {f.name for f in dataclasses.fields(ClusteringConfig)}
    for name in PASSES:
        settings = variant_settings(name)
        assert settings and set(settings) <= fields, name
        # a variant equal to the defaults would measure nothing
        assert any(getattr(defaults, k) != v for k, v in settings.items()), name
    assert variant_settings("defaults") == {}
    monkeypatch.setitem(PASSES, "lower_win", {"split_min_probability": 0.3})
    assert variant_settings("colour_reclaim+lower_win") == {**PASSES["colour_reclaim"], "split_min_probability": 0.3}
    with pytest.raises(ValueError, match="unknown pass"):
        variant_settings("no_such_rule")
    with pytest.raises(ValueError, match="unknown pass"):
        variant_settings("colour_reclaim+no_such_rule")


def _run(miou, ious):
    return {"scene": "s", "miou": miou, "iou_per_instance": ious, "masks_s": 2.0, "base_s": 10.0, "ceiling_miou": 0.9}


def test_a_rule_pays_only_when_the_mean_drops_by_the_margin_without_it(monkeypatch):
    monkeypatch.setitem(PASSES, "lower_win", {"split_min_probability": 0.3})
    runs = {
        "defaults": {0: _run(0.80, {"1": 0.8, "2": 0.8}), 1: _run(0.60, {"1": 0.6, "2": 0.6})},
        # one instance collapses on scene 0: mean change (-0.2 + 0) / 2 = -0.1
        "lower_win": {0: _run(0.60, {"1": 0.4, "2": 0.8}), 1: _run(0.60, {"1": 0.6, "2": 0.6})},
        # a small loss on one scene and a larger gain on the other: the mean rises, the rule does not pay
        "colour_reclaim": {0: _run(0.79, {"1": 0.79, "2": 0.79}), 1: _run(0.63, {"1": 0.63, "2": 0.63})},
    }
    result = summarise_passes(runs, BenchMaskPassesConfig(seeds=(0, 1), pays_at=0.005))
    rows = {r["variant"]: r for r in result["rows"]}
    assert rows["defaults"]["verdict"] is None
    assert rows["lower_win"]["verdict"] == "pays"
    assert rows["lower_win"]["change"]["mean"] == pytest.approx(-0.1)
    assert rows["lower_win"]["scenes_worse"] == 1 and rows["lower_win"]["scenes_better"] == 0
    assert rows["lower_win"]["instances_moved"] == [{"seed": 0, "instance": "1", "iou_change": pytest.approx(-0.4)}]
    assert rows["colour_reclaim"]["verdict"] == "does not pay"
    assert rows["colour_reclaim"]["scenes_worse"] == 1 and rows["colour_reclaim"]["scenes_better"] == 1
    assert rows["colour_reclaim"]["instances_moved"] == []


def test_the_report_split_is_refused(tmp_path):
    from splatreplace_ns.tools.bench.mask_passes import run_mask_passes

    with pytest.raises(ValueError, match="not in the dev split"):
        run_mask_passes(BenchMaskPassesConfig(seeds=(0, 10000), out_dir=tmp_path))
