"""Ground-truth stand-ins of the oracle ablations (bench template): the implied registration is exact."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splatreplace_ns.tools.bench.oracle import ground_truth_registration, ground_truth_transform


def _similarity(rotvec, t, scale):
    P = np.eye(4)
    P[:3, :3] = scale * Rotation.from_rotvec(rotvec).as_matrix()
    P[:3, 3] = t
    return P


def test_ground_truth_transform_maps_every_source_point_onto_the_template():
    rng = np.random.default_rng(0)
    scale = 0.37  # the dataparser's normalisation: one scale shared by every pose
    P_src = _similarity(rng.normal(size=3), rng.normal(size=3), scale)
    P_tpl = _similarity(rng.normal(size=3), rng.normal(size=3), scale)
    T = ground_truth_transform(P_tpl, P_src)
    # rigid, and the same object point lands on the same object point
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    obj = np.c_[rng.normal(size=(50, 3)), np.ones(50)]
    np.testing.assert_allclose((T @ P_src @ obj.T).T, (P_tpl @ obj.T).T, atol=1e-12)


def test_ground_truth_registration_picks_the_stage_template_and_reports_missing_poses():
    rng = np.random.default_rng(1)
    poses = {i: _similarity(rng.normal(size=3), rng.normal(size=3), 1.0) for i in (1, 2, 3, 4)}
    instances = {i: SimpleNamespace(num_gaussians=n) for i, n in {1: 50, 2: 80, 3: 10, 4: 30, 5: 99}.items()}
    classes = {1: "chair", 2: "chair", 3: "chair", 4: "table", 5: "table"}
    results = ground_truth_registration(instances, classes, poses)
    assert {i: r.template_id for i, r in results.items()} == {1: 2, 2: 2, 3: 2, 4: 5, 5: 5}
    for iid in (1, 2, 3):
        assert results[iid].success
        np.testing.assert_allclose(results[iid].transform, poses[2] @ np.linalg.inv(poses[iid]), atol=1e-12)
    np.testing.assert_allclose(results[2].transform, np.eye(4), atol=1e-12)
    # table 5 (the template: most Gaussians) has no pose, so neither table can be placed
    assert not results[4].success and not results[5].success
    assert "no ground-truth pose" in results[4].message
