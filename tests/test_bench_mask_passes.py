"""``bench mask-passes``: what each variant switches off, and how its runs are summarised."""

from __future__ import annotations

import dataclasses

import pytest

from splatreplace_ns.bench.mask_passes import (
    ALL_POST_PASSES, PASSES, POST_PASSES, BenchMaskPassesConfig, summarise_passes, variant_settings,
)
from splatreplace_ns.masks.clustering import ClusteringConfig


def test_every_variant_changes_real_settings_away_from_the_defaults():
    defaults = ClusteringConfig()
    fields = {f.name for f in dataclasses.fields(ClusteringConfig)}
    for name in (*PASSES, ALL_POST_PASSES):
        settings = variant_settings(name)
        assert settings and set(settings) <= fields, name
        # a variant equal to the defaults would measure nothing
        assert any(getattr(defaults, k) != v for k, v in settings.items()), name
    assert set(POST_PASSES) <= set(PASSES)
    assert variant_settings("defaults") == {}
    assert variant_settings("one_piece+floor_band") == {**PASSES["one_piece"], **PASSES["floor_band"]}
    with pytest.raises(ValueError, match="unknown pass"):
        variant_settings("no_such_rule")
    with pytest.raises(ValueError, match="unknown pass"):
        variant_settings("one_piece+no_such_rule")


def _run(miou, ious):
    return {"scene": "s", "miou": miou, "iou_per_instance": ious, "masks_s": 2.0, "base_s": 10.0, "ceiling_miou": 0.9}


def test_a_rule_pays_only_when_the_mean_drops_by_the_margin_without_it():
    runs = {
        "defaults": {0: _run(0.80, {"1": 0.8, "2": 0.8}), 1: _run(0.60, {"1": 0.6, "2": 0.6})},
        # one instance collapses on scene 0: mean change (-0.2 + 0) / 2 = -0.1
        "floor_band": {0: _run(0.60, {"1": 0.4, "2": 0.8}), 1: _run(0.60, {"1": 0.6, "2": 0.6})},
        # a small loss on one scene and a larger gain on the other: the mean rises, the rule does not pay
        "one_piece": {0: _run(0.79, {"1": 0.79, "2": 0.79}), 1: _run(0.63, {"1": 0.63, "2": 0.63})},
    }
    result = summarise_passes(runs, BenchMaskPassesConfig(seeds=(0, 1), pays_at=0.005))
    rows = {r["variant"]: r for r in result["rows"]}
    assert rows["defaults"]["verdict"] is None
    assert rows["floor_band"]["verdict"] == "pays"
    assert rows["floor_band"]["change"]["mean"] == pytest.approx(-0.1)
    assert rows["floor_band"]["scenes_worse"] == 1 and rows["floor_band"]["scenes_better"] == 0
    assert rows["floor_band"]["instances_moved"] == [{"seed": 0, "instance": "1", "iou_change": pytest.approx(-0.4)}]
    assert rows["one_piece"]["verdict"] == "does not pay"
    assert rows["one_piece"]["scenes_worse"] == 1 and rows["one_piece"]["scenes_better"] == 1
    assert rows["one_piece"]["instances_moved"] == []
