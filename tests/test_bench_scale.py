"""``bench scale``: growing a model by splitting keeps its Gaussians' distribution, the exponent fit reads a power law,
and every stage runs on a grown tiny model (in this process and in a worker process)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splatreplace_ns.render.projection import quat_to_rotmat
from splatreplace_ns.tools.bench.scale import BenchScaleConfig, measure, measure_isolated, measurement_specs, prepare_base, summarise
from splatreplace_ns.tools.bench.scale_stages import STAGES, checked_size, power_law_exponent, split_counts, split_gaussians


def parent_set(n: int = 7, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g) * 3.0,
        "scales": torch.log(torch.rand(n, 3, generator=g) * 0.3 + 0.05),
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        "opacities": torch.randn(n, 1, generator=g),
        "features_dc": torch.rand(n, 3, generator=g),
        "features_rest": torch.rand(n, 15, 3, generator=g),
    }


def test_split_counts_sum_to_the_target_and_differ_by_at_most_one():
    counts = split_counts(7, 100)
    assert int(counts.sum()) == 100 and int(counts.max() - counts.min()) <= 1
    assert split_counts(3, 0).tolist() == [0, 0, 0]
    with pytest.raises(ValueError):
        split_counts(0, 5)


def test_children_are_drawn_from_their_parent_and_fill_its_volume():
    parents = parent_set()
    grown, parent = split_gaussians(parents, 7 * 4000, torch.Generator().manual_seed(1))
    assert grown["means"].shape == (28000, 3) and torch.equal(torch.bincount(parent), torch.full((7,), 4000))
    for key in ("quats", "opacities", "features_dc", "features_rest"):
        assert torch.equal(grown[key], parents[key][parent])
    # each parent's children: centres with the parent's mean and covariance R S² Rᵀ, scales / 4000^(1/3)
    for p in range(7):
        kids = grown["means"][parent == p].double()
        R = quat_to_rotmat(parents["quats"][p : p + 1]).double()[0]
        S = torch.exp(parents["scales"][p]).double()
        cov = R @ torch.diag(S**2) @ R.T
        assert torch.allclose(kids.mean(0), parents["means"][p].double(), atol=4 * float(S.max()) / math.sqrt(4000))
        assert torch.allclose(torch.cov(kids.T), cov, atol=0.1 * float(S.max()) ** 2)
        assert torch.allclose(torch.exp(grown["scales"][parent == p]), (S / 4000 ** (1 / 3)).float().expand(4000, 3),
                              rtol=1e-5)


def test_fewer_gaussians_than_the_parents_is_a_subset():
    parents = parent_set(50)
    grown, parent = split_gaussians(parents, 20, torch.Generator().manual_seed(0))
    assert len(set(parent.tolist())) == 20
    for key, value in parents.items():
        assert torch.equal(grown[key], value[parent])


def test_power_law_exponent_reads_the_exponent_of_a_power_law():
    counts = [1e4, 1e5, 1e6]
    slope, r2 = power_law_exponent(counts, [3e-6 * c**1.5 for c in counts])
    assert slope == pytest.approx(1.5) and r2 == pytest.approx(1.0)
    n_log_n = [1e-7 * c * math.log(c) for c in counts]
    assert 1.0 < power_law_exponent(counts, n_log_n)[0] < 1.15  # N log N reads as just above linear
    with pytest.raises(ValueError):
        power_law_exponent([5, 5], [1.0, 2.0])


def test_sizes_are_checked():
    assert checked_size("320x240") == (320, 240)
    for bad in ("320", "0x10", "axb"):
        with pytest.raises(ValueError):
            checked_size(bad)


def test_summary_names_the_worst_stage_and_keeps_failures():
    rows = [
        {"stage": "a", "sweep": "gaussians", "gaussians": n, "count": n, "seconds": 1e-6 * n, "peak_rss_mb": 1.0,
         "peak_growth_mb": 0.5} for n in (1000, 10000)
    ] + [
        {"stage": "registration", "sweep": "gaussians", "gaussians": n, "count": n, "seconds": 1e-9 * n**2,
         "peak_rss_mb": 2.0, "peak_growth_mb": 1.0, "instances": 2} for n in (1000, 10000)
    ] + [{"stage": "registration", "sweep": "gaussians", "gaussians": 10**6, "error": "stopped after 5 s"}]
    import splatreplace_ns.tools.bench.scale as scale

    scale.COUNT_OF.update(a="x")
    try:
        summary = summarise(rows)
    finally:
        scale.COUNT_OF.pop("a")
    b = summary["stages"]["registration"]
    assert summary["stages"]["a"]["exponent"] == pytest.approx(1.0) and b["exponent"] == pytest.approx(2.0)
    assert summary["worst_stage"] == "registration" and b["failed"] == ["1000000 G: stopped after 5 s"]
    assert b["seconds_per_instance"] == pytest.approx(1e-9 * 1e8 / 2)  # registration's target is per instance
    assert summary["stages"]["a"]["seconds_per_instance"] == pytest.approx(1e-2)


@pytest.fixture(scope="module")
def tiny_base(tmp_path_factory):
    root = tmp_path_factory.mktemp("scale")
    cfg = BenchScaleConfig(preset="tiny", res="64x48", n_train=8, n_test=2, base_iterations=60, gaussians=(3000, 6000),
                           views=2, size="32x24", fixed_gaussians=3000, view_counts=(2, 3), sizes=("32x24", "64x48"),
                           data_root=root / "data", out_dir=root / "runs", threads=1)
    return cfg, prepare_base(cfg)


def test_every_stage_runs_on_a_grown_model(tiny_base):
    cfg, base = tiny_base
    specs = measurement_specs(cfg, base)
    assert {s["stage"] for s in specs} == set(STAGES)
    assert {(s["sweep"], s["stage"]) for s in specs if s["sweep"] != "gaussians"} == {
        (sweep, stage) for stage in ("mask_rendering", "carving") for sweep in ("views", "size")} | {("size", "render")}
    for spec in (s for s in specs if s["sweep"] == "gaussians" and s["gaussians"] == 6000):
        row = measure(spec)
        assert row["seconds"] >= 0 and row["count"] > 0, row
        assert row["peak_rss_mb"] is None or row["peak_rss_mb"] > 0
        if spec["stage"] == "clustering":
            assert row["count"] == 6000
        if spec["stage"] == "mask_rendering":
            assert row["count"] == 6000 * 2 * 32 * 24 and row["instance_pixels"] > 0
        if spec["stage"] == "registration":
            assert row["instances"] >= 2 and row["registered"] >= 1
        if spec["stage"] == "templates":
            assert row["instances"] >= 2 and row["stored"] < 6000  # the copies share one template
        if spec["stage"] == "export":
            assert row["ply_bytes"] > 0 and row["instanced_bytes"] > 0 and row["count"] > 0


def test_a_measurement_runs_in_its_own_process(tiny_base):
    cfg, base = tiny_base
    spec = next(s for s in measurement_specs(cfg, base) if s["stage"] == "clustering")
    row = measure_isolated(spec, timeout_s=600)
    assert "error" not in row, row
    assert row["count"] == spec["gaussians"] and row["process_s"] >= row["seconds"]
    stopped = measure_isolated(spec, timeout_s=0.01)
    assert stopped["error"].startswith("stopped after")
