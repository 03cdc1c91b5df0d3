"""The learned sky background: ray directions, the sky colour over elevation, the opacity term, the model's use."""

from __future__ import annotations

import math

import pytest
import torch

from splatreplace_ns.method.sky import legendre_basis, pixel_directions, sky_colour, sky_opacity_l1


def _rotation(axis: str, degrees: float) -> torch.Tensor:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    if axis == "x":
        return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float32)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float32)


def test_pixel_directions_reproject_to_their_pixels():
    """Oracle: each direction, taken back into the camera and projected with K, lands on its pixel centre;
    the principal point looks along the camera's −z axis."""
    R = _rotation("z", 30.0) @ _rotation("x", 70.0)
    c2w = torch.cat([R, torch.tensor([[1.0], [2.0], [3.0]])], dim=1)
    K = torch.tensor([[50.0, 0.0, 31.5], [0.0, 55.0, 24.0], [0.0, 0.0, 1.0]])
    dirs = pixel_directions(c2w, K, 64, 48)
    assert dirs.shape == (48, 64, 3)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(48, 64), atol=1e-6)
    cam = dirs @ R  # world → camera (R orthonormal)
    assert (cam[..., 2] < 0).all()  # every ray goes out in front of the camera
    u = K[0, 0] * cam[..., 0] / -cam[..., 2] + K[0, 2]
    v = -K[1, 1] * cam[..., 1] / -cam[..., 2] + K[1, 2]
    cols, rows = torch.meshgrid(torch.arange(64) + 0.5, torch.arange(48) + 0.5, indexing="xy")
    assert torch.allclose(u, cols, atol=1e-3) and torch.allclose(v, rows, atol=1e-3)
    centred = pixel_directions(c2w, torch.tensor([[50.0, 0.0, 31.5], [0.0, 55.0, 23.5], [0.0, 0.0, 1.0]]), 64, 48)
    assert torch.allclose(centred[23, 31], -R[:, 2], atol=1e-6)  # pixel centre (31.5, 23.5) = principal point


def test_legendre_basis_matches_closed_forms():
    u = torch.linspace(-1, 1, 21)
    basis = legendre_basis(u, 3)
    assert basis.shape == (21, 4)
    closed = torch.stack([torch.ones_like(u), u, (3 * u**2 - 1) / 2, (5 * u**3 - 3 * u) / 2], dim=-1)
    assert torch.allclose(basis, closed, atol=1e-6)
    assert legendre_basis(u, 0).shape == (21, 1)


def test_sky_colour_degree_zero_is_a_constant_and_shapes_are_checked():
    coeffs = torch.tensor([[1.0, -2.0, 0.5]])
    dirs = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    assert torch.allclose(sky_colour(coeffs, dirs), torch.sigmoid(coeffs).expand(10, 3), atol=1e-6)
    with pytest.raises(ValueError, match="degree"):
        sky_colour(torch.zeros(5, 4), dirs)


def test_sky_colour_learned_on_one_side_holds_on_the_other():
    """Fitted to a blue-to-white gradient over elevation (the sim's sky) from directions on one side only
    (x > 0, as a capture from one side sees it), the sky predicts the other side (x < 0) as well."""
    torch.manual_seed(0)

    def gradient(d: torch.Tensor) -> torch.Tensor:
        t = d[:, 2:3].clamp(0, 1) ** 0.6
        return torch.tensor([0.78, 0.84, 0.9]) * (1 - t) + torch.tensor([0.32, 0.52, 0.85]) * t

    samples = torch.nn.functional.normalize(torch.randn(4000, 3), dim=-1)
    seen, unseen = samples[samples[:, 0] > 0], samples[samples[:, 0] < 0]
    coeffs = torch.zeros(5, 3, requires_grad=True)
    opt = torch.optim.Adam([coeffs], lr=0.05)
    for _ in range(500):
        opt.zero_grad()
        loss = (sky_colour(coeffs, seen) - gradient(seen)).abs().mean()
        loss.backward()
        opt.step()
    assert (sky_colour(coeffs, seen) - gradient(seen)).abs().mean() < 0.02
    assert (sky_colour(coeffs, unseen) - gradient(unseen)).abs().mean() < 0.02
    untrained = (sky_colour(torch.zeros(5, 3), unseen) - gradient(unseen)).abs().mean()
    assert untrained > 0.2  # the grey start is far from it: the fit did the work


def test_sky_opacity_l1_values_and_gradients():
    """0 on sky pixels, 1 on surface pixels, unknown depth ignored; finite for any mix, empty included."""
    inf = float("inf")
    target = torch.tensor([[[inf], [2.0]], [[0.0], [inf]]])
    alpha = torch.tensor([[[0.25], [0.5]], [[0.9], [0.75]]], requires_grad=True)
    loss = sky_opacity_l1(alpha, target)
    assert torch.isclose(loss, torch.tensor((0.25 + 0.75) / 2 + 0.5))
    loss.backward()
    assert alpha.grad[0, 0, 0] > 0 and alpha.grad[0, 1, 0] < 0 and alpha.grad[1, 0, 0] == 0  # unknown: untouched
    for t in (torch.zeros(2, 2, 1), torch.full((2, 2, 1), inf), torch.full((2, 2, 1), 3.0)):
        a = torch.rand(2, 2, 1, requires_grad=True)
        value = sky_opacity_l1(a, t)
        value.backward()
        assert torch.isfinite(value) and torch.isfinite(a.grad).all()
    assert sky_opacity_l1(torch.ones(2, 2, 1), torch.full((2, 2, 1), 3.0)).item() == 0.0


@pytest.fixture(scope="module")
def temple_with_sky(tmp_path_factory):
    """A short base stage on a tiny temple (open sky: its transforms.json says depth 0 is far)."""
    from splatreplace_ns.tools.bench.scenes import cached_scene
    from splatreplace_ns.method.train import make_trainer_config, run_training

    data = cached_scene("temple", "64x48", 12, 2, tmp_path_factory.mktemp("scenes"))
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), base_iterations=300)
    config.pipeline.model.warmup_length = 100
    return run_training(config)


def _sky_pixels(dataset, index):
    data = dataset[index]
    return torch.isinf(data["depth"][..., 0]), data["image"][..., :3].float()


def test_sky_background_follows_the_dataset(temple_with_sky, tmp_path, capsys):
    """auto: on for a scene whose depth 0 is the sky, off for one without that key (and forced either way);
    forced on for frames without depth, the user is told that nothing then tells the sky from a surface."""
    from scenes import write_gaussian_scene
    from splatreplace_ns.method.train import make_trainer_config

    model = temple_with_sky.pipeline.model
    assert model.uses_sky
    write_gaussian_scene(tmp_path / "indoor", n_views=4, width=32, height=24)
    config = make_trainer_config(tmp_path / "indoor", tmp_path / "runs", base_iterations=1)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)
    assert not pipeline.model.uses_sky
    assert "no depth" not in capsys.readouterr().out
    config.pipeline.model.sky_background = "on"
    pipeline = config.pipeline.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)
    assert pipeline.model.uses_sky and "the frames carry no depth" in capsys.readouterr().out
    for forced, expected in (("on", True), ("off", False)):
        model.config.sky_background = forced
        assert model.uses_sky == expected
    model.config.sky_background = "auto"


def test_sky_is_transparent_and_its_colour_carries_to_views_from_behind(temple_with_sky):
    """Sky pixels of the training views are left to the background (low opacity), and the test views, taken
    from the far side where no training view looked, render the sky's colour gradient from it."""
    pipeline = temple_with_sky.pipeline
    pipeline.eval()
    train, test = pipeline.datamanager.train_dataset, pipeline.datamanager.eval_dataset
    alphas = []
    for i in range(len(train)):
        sky, _ = _sky_pixels(train, i)
        with torch.no_grad():
            out = pipeline.model.get_outputs_for_camera(train.cameras[i : i + 1])
        alphas.append(out["accumulation"][..., 0][sky])
    assert torch.cat(alphas).mean() < 0.15
    errors, skies = [], []
    for i in range(len(test)):
        sky, gt = _sky_pixels(test, i)
        with torch.no_grad():
            out = pipeline.model.get_outputs_for_camera(test.cameras[i : i + 1])
        assert torch.isfinite(out["rgb"]).all() and out["background"].shape == out["rgb"].shape
        errors.append(torch.stack([(out["background"] - gt).abs()[sky], (out["rgb"] - gt).abs()[sky]]))
        skies.append(gt[sky])
    background_error, rendered_error = torch.cat(errors, dim=1).mean(dim=(1, 2))
    # what a fixed background (the viewer's colour, shown at evaluation without the sky) would score
    fixed = (pipeline.model.background_color - torch.cat(skies)).abs().mean()
    assert background_error < 0.05 and rendered_error < 0.1 and fixed > 0.4, (background_error, rendered_error, fixed)


def test_checkpoint_without_sky_loads_with_a_grey_sky(temple_with_sky):
    """A checkpoint written before the sky background existed loads, with the grey starting sky."""
    model = temple_with_sky.pipeline.model
    full = {k: v.detach().clone() if torch.is_tensor(v) else v for k, v in model.state_dict().items()}
    assert not torch.equal(full["sky_coefficients"], torch.zeros_like(full["sky_coefficients"]))  # it was learned
    model.load_state_dict({k: v for k, v in full.items() if k != "sky_coefficients"})
    assert torch.equal(model.sky_coefficients, torch.zeros_like(model.sky_coefficients))
    assert torch.allclose(sky_colour(model.sky_coefficients, torch.tensor([[0.0, 0.0, 1.0]])), torch.full((1, 3), 0.5))
    model.load_state_dict(full)
    assert torch.equal(model.sky_coefficients, full["sky_coefficients"])
