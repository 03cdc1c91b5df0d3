"""The demo's baseline trained in a second process beside ours (CPU, two or more cores)."""

from __future__ import annotations

import math
import multiprocessing
import os
import sys

import pytest
import torch

from splatreplace_ns.tools.bench.template import _wait_for, test_metrics as scored, train_ours_and_baseline
from splatreplace_ns.tools.sim import make_scene


@pytest.mark.skipif((os.cpu_count() or 1) < 2 or torch.cuda.is_available(), reason="needs a CPU with two cores")
def test_baseline_beside_ours_reports_what_its_checkpoint_gives(tmp_path):
    data = tmp_path / "tiny"
    make_scene("tiny", data, n_train=12)
    threads = torch.get_num_threads()
    try:
        # 200 contrastive steps: after 80, most seeds left some clicks matching no Gaussian's feature
        pair = train_ours_and_baseline(data, tmp_path / "runs", 150, 200, 60, parallel=True)
    finally:
        torch.set_num_threads(threads)
    assert pair["parallel"]
    assert (tmp_path / "runs" / "baseline.log").stat().st_size > 0
    baseline = pair["baseline"]
    assert all(math.isfinite(baseline[k]) for k in ("psnr", "psnr_masked", "ssim", "ssim_masked"))
    assert pair["times"]["baseline"] > 0 and pair["sizes"]["baseline_gaussians"] == pair["baseline_pipeline"].model.num_points
    # the figures the worker sent are those of the checkpoint it left: re-scored here, they agree
    again = scored(pair["baseline_pipeline"])
    for k in ("psnr", "psnr_masked", "ssim", "ssim_masked"):
        assert abs(again[k] - baseline[k]) < 1e-3, (k, again[k], baseline[k])
    # each test view on its own, in the eval dataset's order
    assert [row["view"] for row in baseline["per_view"]] == list(range(len(pair["baseline_pipeline"].datamanager.eval_dataset)))
    model = pair["ours_trainer"].pipeline.model
    if model.has_templates:  # ours' own scene before replacement, the size the instanced file is compared with
        from splatreplace_ns.template.export import ply_bytes

        assert pair["sizes"]["base_scene_gaussians"] == model.base_gaussians > 0
        assert pair["sizes"]["base_scene_ply_bytes"] == ply_bytes(model.base_gaussians, model.features_rest.shape[1] + 1)
    steps = sorted((tmp_path / "runs" / "baseline").glob("*/run/nerfstudio_models/step-*.ckpt"))
    assert steps and steps[-1].name == f"step-{150 + 200 + 60 - 1:09d}.ckpt"


def test_a_worker_that_dies_without_a_result_is_a_clear_error():
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    worker = context.Process(target=sys.exit, args=(3,))
    worker.start()
    with pytest.raises(RuntimeError, match="exit code 3"):
        _wait_for(worker, queue)
