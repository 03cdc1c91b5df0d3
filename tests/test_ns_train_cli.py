"""`ns-train splat-replace --data DIR` on a `sim` scene, through nerfstudio's own CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import torch

from splatreplace_ns.datamanager.datamanager import SplatReplaceDataManagerConfig
from splatreplace_ns.tools.sim import make_scene


def test_sim_scene_loads_through_our_datamanager(tmp_path):
    make_scene("tiny", tmp_path / "tiny")
    config = SplatReplaceDataManagerConfig()
    config.data = tmp_path / "tiny"
    dm = config.setup(device="cpu", test_mode="test")
    camera, batch = dm.next_train(0)
    assert batch["image"].shape == (48, 64, 3)
    ids = set(torch.unique(batch["instance_mask"]).tolist())
    listed = {inst["id"] for inst in dm.train_dataparser_outputs.metadata["instances"]}
    assert ids - {0} <= listed and len(listed) == 3
    assert batch["depth"].shape == (48, 64, 1) and (batch["depth"] > 0).any()
    assert dm.train_dataparser_outputs.metadata["points3D_xyz"].shape[0] > 100


def test_ns_train_runs_on_cpu(tmp_path):
    make_scene("tiny", tmp_path / "tiny")
    ns_train = Path(sys.executable).parent / "ns-train"
    result = subprocess.run(
        [str(ns_train), "splat-replace", "--data", str(tmp_path / "tiny"), "--output-dir", str(tmp_path / "out"),
         "--max-num-iterations", "30", "--vis", "tensorboard", "--timestamp", "t"],
        capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    run = tmp_path / "out" / "tiny" / "splat-replace" / "t"
    assert (run / "config.yml").exists()
    assert list((run / "nerfstudio_models").glob("step-*.ckpt"))
