"""The instanced file's sparse per-instance offsets: round trip, colour bound, old files still load."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from splatreplace_ns.render.sh import spherical_harmonics
from splatreplace_ns.template.export import (
    InstancedScene,
    offset_epsilon,
    pack_offsets,
    sh_basis_abs_bound,
    unpack_offsets,
)


def _l1_like_offsets(n=500, K=16, seed=0):
    """Offsets as an L1 penalty leaves them: most entries tiny, some large."""
    rng = np.random.default_rng(seed)
    small = rng.normal(0.0, 1e-3, (n, K, 3))
    large = rng.normal(0.0, 0.3, (n, K, 3)) * (rng.random((n, K, 3)) < 0.2)
    return (small + large).astype(np.float32)


def test_pack_round_trip_keeps_the_large_entries_and_zeroes_the_rest():
    offsets = _l1_like_offsets()
    eps = 2e-3
    bits, values = pack_offsets(offsets, eps)
    back = unpack_offsets(bits, values, offsets.shape)
    big = np.abs(offsets) > eps
    assert values.dtype == np.float16 and bits.dtype == np.uint8
    assert np.all(back[~big] == 0.0)
    np.testing.assert_allclose(back[big], offsets[big], rtol=1e-3, atol=1e-6)  # float16
    assert bits.nbytes + values.nbytes < 0.5 * offsets.astype(np.float16).nbytes  # the point of it
    with pytest.raises(ValueError, match="keeps"):
        unpack_offsets(bits, values[:-1], offsets.shape)


def test_dropped_offsets_change_no_colour_by_more_than_the_tolerance():
    """Worst case: every coefficient just under ε with the sign of its basis value in some direction."""
    K, lam, tol = 16, 0.8, 0.5 / 255
    eps = offset_epsilon(lam, K, tol)
    gen = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(4000, 3, generator=gen, dtype=torch.float64), dim=-1)
    # the basis as the renderer applies it: the colour of coefficient j alone
    one_hot = torch.eye(K, dtype=torch.float64)[:, :, None].expand(K, K, 3)
    basis = torch.stack([spherical_harmonics(3, dirs, one_hot[j].expand(len(dirs), K, 3))[:, 0] for j in range(K)], 1)
    adversarial = 0.999 * eps * torch.sign(basis)  # [dirs, K]: dropped entirely by pack_offsets
    offsets = adversarial[:, :, None].expand(-1, K, 3).numpy().astype(np.float32)
    bits, values = pack_offsets(offsets, eps)
    assert len(values) == 0
    change = (1.0 - lam) * (basis * adversarial).sum(dim=1).abs()  # colour change in each adversary's direction
    assert float(change.max()) <= tol
    assert float(change.max()) > 0.5 * tol  # and the bound is not loose by orders of magnitude
    assert sh_basis_abs_bound(1) == pytest.approx(1.05 * 0.28209479, rel=1e-6)


def test_epsilon_edge_cases():
    assert offset_epsilon(1.0, 16) == float("inf")  # λ = 1: offsets never reach the colour
    assert offset_epsilon(0.8, 16, 0.0) == 0.0  # tolerance 0: keep every non-zero offset
    assert offset_epsilon(0.0, 16) < offset_epsilon(0.8, 16)


def _tiny_instanced(offsets_entry):
    n, K = 4, 4
    arrays = {
        "means": np.zeros((n, 3), np.float32), "quats": np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
        "scales": np.full((n, 3), -3.0, np.float32), "opacities": np.zeros((n, 1), np.float32),
        "sh": np.zeros((n, K, 3), np.float32), "gauss_class": np.array([0, 1, 1, 1], np.int16),
        "instance_ids": np.array([7]), "instance_class": np.array([1]), "instance_slot": np.array([0]),
        "pose_q": np.array([[1, 0, 0, 0]], np.float32), "pose_t": np.array([[0, 0, 1]], np.float32),
        "lam": np.float32(0.0),
    }
    arrays.update(offsets_entry)
    return InstancedScene(arrays)


def test_v1_dense_and_v2_sparse_offsets_compose_alike():
    offsets = np.random.default_rng(1).normal(0.0, 0.5, (3, 4, 3)).astype(np.float32)
    dense = _tiny_instanced({"offsets_7": offsets.astype(np.float16)}).compose()
    bits, values = pack_offsets(offsets, 0.0)
    sparse = _tiny_instanced({"offsets_bits_7": bits, "offsets_values_7": values}).compose()
    assert torch.equal(dense.sh, sparse.sh)
    # λ = 0: the instance's colour is its offsets (background Gaussian first, then the instance's three)
    assert torch.allclose(sparse.sh[-3:], torch.from_numpy(offsets), atol=2e-3)


def test_offset_counts_report_kept_of_all():
    from splatreplace_ns.template.export import offset_counts

    offsets = np.zeros((3, 4, 3), np.float32)
    offsets[0, 0, 0], offsets[2, 3, 1] = 0.5, -0.25
    bits, values = pack_offsets(offsets, 1e-3)
    scene = _tiny_instanced({"offsets_bits_7": bits, "offsets_values_7": values})
    assert offset_counts(scene.arrays) == (2, 36)


def test_a_stored_colour_gain_is_applied_when_composing():
    from splatreplace_ns.template.compose import apply_colour_gain

    offsets = np.random.default_rng(2).normal(0.5, 0.2, (3, 4, 3)).astype(np.float32)
    bits, values = pack_offsets(offsets, 0.0)
    entry = {"offsets_bits_7": bits, "offsets_values_7": values}
    plain = _tiny_instanced(dict(entry)).compose()
    gain = np.array([[0.3, -0.2, 0.0]], np.float32)
    gained = _tiny_instanced({**entry, "colour_gain": gain}).compose()
    assert torch.equal(gained.sh[:1], plain.sh[:1])  # the background Gaussian
    assert torch.allclose(gained.sh[1:], apply_colour_gain(plain.sh[1:], torch.from_numpy(gain).expand(3, 3)), atol=1e-6)
    assert not torch.allclose(gained.sh[1:], plain.sh[1:])
