"""`splatreplace bench segment`: the leftover count against a mesh oracle, and a whole tiny run's JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import torch

from splatreplace_ns.tools.bench.segment import BenchSegmentConfig, count_leftovers, leftovers_by_instance, run_segment_bench
from splatreplace_ns.tools.sim import class_mesh


def test_leftovers_are_background_gaussians_inside_or_next_to_an_instance():
    mesh = class_mesh("crate")
    low, high = np.asarray(mesh.get_min_bound()), np.asarray(mesh.get_max_bound())
    centre, diagonal = (low + high) / 2, float(np.linalg.norm(high - low))
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([2.0, -1.0, 0.5])  # object → world
    world = lambda p: torch.tensor(p, dtype=torch.float64) + pose[:3, 3]
    on_surface = np.asarray(mesh.vertices)[0]
    means = torch.stack([
        world(on_surface),                                       # on the crate's surface: a leftover
        world(centre + [0.0, 0.0, high[2] - centre[2] + 0.005 * diagonal]),  # just above the lid (0.5 % < 1 %)
        world(centre + [0.0, 0.0, high[2] - centre[2] + 0.05 * diagonal]),   # 5 % above: not near
        world(centre + [10.0, 0.0, 0.0]),                        # far away
        world(on_surface),                                       # the same, but labelled as the instance
    ]).float()
    labels = torch.tensor([0, 0, 0, 0, 1])
    instances = [{"id": 1, "class": "crate", "transform_matrix": pose}]
    assert count_leftovers(means, labels, instances) == 2
    assert count_leftovers(means, torch.ones(5, dtype=torch.long), instances) == 0
    assert count_leftovers(means[:0], labels[:0], instances) == 0


def test_leftovers_are_told_apart_by_the_instance_they_sit_in():
    mesh = class_mesh("crate")
    on_surface = torch.tensor(np.asarray(mesh.vertices)[0], dtype=torch.float64)
    another_vertex = torch.tensor(np.asarray(mesh.vertices)[len(mesh.vertices) // 2], dtype=torch.float64)
    poses = []
    for shift in ([0.0, 0.0, 0.0], [5.0, 0.0, 0.0]):
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, 3] = torch.tensor(shift)
        poses.append(pose)
    instances = [{"id": 3, "class": "crate", "transform_matrix": poses[0]},
                 {"id": 7, "class": "crate", "transform_matrix": poses[1]}]
    means = torch.stack([
        on_surface + poses[0][:3, 3],                    # background on crate 3
        on_surface + poses[1][:3, 3],                    # background on crate 7
        on_surface + poses[1][:3, 3],                    # again on crate 7, but labelled as it
        another_vertex + poses[1][:3, 3],                # background elsewhere on crate 7
        torch.tensor([2.5, 10.0, 0.0], dtype=torch.float64),  # between them, near neither
    ]).float()
    labels = torch.tensor([0, 0, 7, 0, 0])
    by_instance = leftovers_by_instance(means, labels, instances)
    assert {k: v.tolist() for k, v in by_instance.items()} == {
        3: [True, False, False, False], 7: [False, True, True, False]}
    assert count_leftovers(means, labels, instances) == 3
    assert {k: v.numel() for k, v in leftovers_by_instance(means, torch.full((5,), 3), instances).items()} == {3: 0, 7: 0}


def test_tiny_run_writes_the_interface(tmp_path):
    cfg = BenchSegmentConfig(
        preset="tiny", res="64x48", n_train=12, n_test=4, base_iterations=150, contrastive_iterations=200,
        early_contrastive_iterations=100, data_root=tmp_path / "data", out_dir=tmp_path / "runs",
        json=tmp_path / "segment.json", threads=1,
    )
    result = cfg.main()
    written = json.loads((tmp_path / "segment.json").read_text())
    for key in ("preset", "miou", "macc", "miou_1k", "miou_5k", "leftover", "time_s"):
        assert key in written, key
    assert written["preset"] == "tiny" and written["miou_5k"] == result["miou"]
    # the tiny run segments its three crates: mIoU 0.770 and mAcc 0.900 with the default machine.seed, 0.75-0.78 and
    # 0.89-0.91 with machine.seeds 1-4; the early score (after 100 contrastive steps) is real but lower, 0.41 and
    # 0.16-0.43. Empty masks give mIoU 0 and mAcc 0.25 (the background's accuracy alone)
    assert 0.6 < written["miou"] <= 1.0 and 0.8 < written["macc"] <= 1.0, (written["miou"], written["macc"])
    assert 0.0 < written["miou_1k"] < written["miou"], written["miou_1k"]
    leftover = written["leftover"]
    assert all(isinstance(leftover[k], int) and leftover[k] >= 0 for k in ("none", "reg", "reg_carve"))
    # carving only removes background Gaussians near instances, never adds them
    assert leftover["reg_carve"] <= leftover["reg"]
    # the breakdown names every instance, and each leftover sits in at least one of them
    by_instance = leftover["reg_carve_by_instance"]
    assert set(by_instance) == {"1", "2", "3"} and sum(by_instance.values()) >= leftover["reg_carve"]
    assert all(math.isfinite(v) and v >= 0 for v in written["time_s"].values())
    assert {"base", "contrastive", "segmentation", "total"} <= set(written["time_s"])
