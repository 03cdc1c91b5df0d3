"""The similarity alignment (Umeyama) against transforms known by construction."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splatreplace_ns.eval.alignment import (
    AlignmentError, apply_similarity, centre_errors, invert_similarity, similarity_fit, similarity_pose,
)


def known_transform(seed: int):
    rng = np.random.default_rng(seed)
    return float(rng.uniform(0.2, 5.0)), Rotation.random(random_state=seed).as_matrix(), rng.normal(0.0, 3.0, 3)


@pytest.mark.parametrize("seed", range(5))
def test_recovers_a_known_similarity_exactly(seed):
    scale, rotation, translation = known_transform(seed)
    src = np.random.default_rng(100 + seed).normal(0.0, 2.0, (20, 3))
    dst = scale * src @ rotation.T + translation
    s, r, t = similarity_fit(src, dst)
    assert s == pytest.approx(scale, rel=1e-9)
    assert np.allclose(r, rotation, atol=1e-9) and np.linalg.det(r) == pytest.approx(1.0)
    assert np.allclose(t, translation, atol=1e-8)
    assert np.allclose(apply_similarity(src, s, r, t), dst, atol=1e-8)


def test_three_points_in_a_plane_are_enough():
    scale, rotation, translation = known_transform(7)
    src = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    dst = apply_similarity(src, scale, rotation, translation)
    s, r, t = similarity_fit(src, dst)
    assert s == pytest.approx(scale) and np.allclose(r, rotation, atol=1e-9) and np.allclose(t, translation)


def test_noisy_points_give_the_least_squares_fit():
    """With noise the fit is close to the truth and no other nearby similarity has a smaller residual."""
    scale, rotation, translation = known_transform(3)
    rng = np.random.default_rng(0)
    src = rng.normal(0.0, 2.0, (200, 3))
    dst = apply_similarity(src, scale, rotation, translation) + rng.normal(0.0, 0.05, (200, 3))
    fit = similarity_fit(src, dst)
    assert fit[0] == pytest.approx(scale, rel=0.01)
    assert Rotation.from_matrix(fit[1].T @ rotation).magnitude() < np.radians(0.5)
    residual = ((apply_similarity(src, *fit) - dst) ** 2).sum()
    for k in range(20):
        delta = Rotation.from_rotvec(rng.normal(0.0, 0.01, 3)).as_matrix()
        other = (fit[0] * (1 + rng.normal(0.0, 0.01)), delta @ fit[1], fit[2] + rng.normal(0.0, 0.01, 3))
        assert ((apply_similarity(src, *other) - dst) ** 2).sum() > residual


def test_a_mirrored_point_set_gets_a_rotation_not_a_reflection():
    src = np.random.default_rng(1).normal(0.0, 1.0, (10, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a reflection: no similarity maps one onto the other
    _, r, _ = similarity_fit(src, dst)
    assert np.linalg.det(r) == pytest.approx(1.0) and np.allclose(r @ r.T, np.eye(3), atol=1e-9)


def test_inverse_and_pose_transform_agree_with_the_points():
    scale, rotation, translation = known_transform(11)
    inv = invert_similarity(scale, rotation, translation)
    p = np.random.default_rng(2).normal(0.0, 1.0, (5, 3))
    assert np.allclose(apply_similarity(apply_similarity(p, scale, rotation, translation), *inv), p)
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.random(random_state=4).as_matrix()
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    moved = similarity_pose(c2w, scale, rotation, translation)
    assert np.allclose(moved[:3, 3], apply_similarity(c2w[None, :3, 3], scale, rotation, translation)[0])
    assert np.allclose(moved[:3, :3], rotation @ c2w[:3, :3]) and np.allclose(moved[3], [0, 0, 0, 1])
    # a point seen from the camera is seen at the same direction after both move (depth scales)
    point = np.array([0.5, -0.2, 4.0])
    local = np.linalg.inv(c2w) @ np.r_[point, 1.0]
    local_moved = np.linalg.inv(moved) @ np.r_[apply_similarity(point[None], scale, rotation, translation)[0], 1.0]
    assert np.allclose(local_moved[:3], scale * local[:3])


def test_centre_errors_are_zero_for_an_exact_copy_and_measure_a_displaced_point():
    scale, rotation, translation = known_transform(5)
    dst = np.random.default_rng(6).normal(0.0, 1.0, (30, 3))
    src = apply_similarity(dst, *invert_similarity(scale, rotation, translation))
    errors, fit = centre_errors(src, dst)
    assert errors.max() < 1e-9 and fit[0] == pytest.approx(scale)
    moved = dst.copy()
    moved[0] += np.array([0.0, 0.0, 10.0])  # one outlier: the error is largest there
    errors, _ = centre_errors(src, moved)
    assert int(np.argmax(errors)) == 0 and errors[0] > 5.0


@pytest.mark.parametrize("src, dst, message", [
    (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
    (np.zeros((4, 2)), np.zeros((4, 2)), r"\[N, 3\]"),
    (np.zeros((4, 3)), np.zeros((5, 3)), "same shape"),
    (np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)], np.random.default_rng(0).normal(size=(5, 3)), "one line"),
    (np.ones((5, 3)), np.random.default_rng(0).normal(size=(5, 3)), "coincident"),
    (np.random.default_rng(0).normal(size=(5, 3)), np.ones((5, 3)), "same point"),
    (np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0]]), np.eye(3), "NaN"),
])
def test_degenerate_input_is_a_clear_error(src, dst, message):
    with pytest.raises(AlignmentError, match=message):
        similarity_fit(src, dst)
