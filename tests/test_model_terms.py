"""Pure functions of the base 3DGS* stage against hand-computed values."""

from __future__ import annotations

import math

import torch

from splatreplace_ns.method.losses import apply_exposure, base_regularisers, inverse_depth_l1, nearest_downscale


def test_base_regularisers_are_means_of_activated_values():
    opacities = torch.tensor([[0.0], [math.log(3.0)]])  # sigmoid -> 0.5, 0.75
    scales = torch.log(torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]))
    opacity_l1, scale_l1 = base_regularisers(opacities, scales)
    assert torch.isclose(opacity_l1, torch.tensor(0.625))
    assert torch.isclose(scale_l1, torch.tensor(3.5))


def test_exposure_identity_and_affine():
    rgb = torch.rand(4, 5, 3)
    assert torch.allclose(apply_exposure(rgb, torch.eye(3, 4)), rgb)
    affine = torch.tensor([[2.0, 0, 0, 0.1], [0, 1.0, 0, 0], [0, 0, 0.5, -0.1]])
    expected = torch.stack([2 * rgb[..., 0] + 0.1, rgb[..., 1], 0.5 * rgb[..., 2] - 0.1], -1)
    assert torch.allclose(apply_exposure(rgb, affine), expected)


def test_inverse_depth_l1_ignores_invalid_and_has_finite_grad():
    pred = torch.tensor([[[2.0], [0.0]], [[4.0], [1.0]]], requires_grad=True)
    target = torch.tensor([[[1.0], [0.0]], [[4.0], [0.0]]])
    loss = inverse_depth_l1(pred, target)
    assert torch.isclose(loss, torch.tensor((0.5 + 0.0) / 2))
    loss.backward()
    assert torch.isfinite(pred.grad).all()
    empty = inverse_depth_l1(pred, torch.zeros_like(target))
    assert empty.item() == 0.0


def test_inverse_depth_l1_pushes_the_sky_away():
    """A target of +inf (no surface) asks for inverse depth 0: the loss falls as the rendered depth recedes,
    its gradient pushes the depth out, and nothing is infinite or NaN, even for a rendered depth of 0."""
    target = torch.tensor([[[2.0], [float("inf")]]])
    losses = []
    for far in (0.0, 1.0, 4.0, 100.0):
        pred = torch.tensor([[[2.0], [far]]], requires_grad=True)
        loss = inverse_depth_l1(pred, target)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()
        if far > 0.001:
            assert pred.grad[0, 1, 0] < 0  # descending the loss moves the sky farther
        losses.append(loss.item())
    assert losses == sorted(losses, reverse=True) and losses[-1] < 0.01
    assert torch.isclose(inverse_depth_l1(torch.tensor([[[2.0], [4.0]]]), target), torch.tensor(0.25 / 2))


def test_nearest_downscale_keeps_zeros():
    depth = torch.arange(48.0).reshape(6, 8, 1)
    out = nearest_downscale(depth, 2, 3, 4)
    assert out.shape == (3, 4, 1)
    assert torch.equal(out, depth[1::2, 1::2])
