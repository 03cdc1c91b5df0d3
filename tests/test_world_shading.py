"""Shading in world coordinates (``template.world_shading``, ``model.world_shading``): the normals, the gain, and
that copies turned under one sun are explained by one template colour and one shading."""

import math

import pytest
import torch

from splatreplace_ns.render.sh import SH_C0
from splatreplace_ns.render.transform import rotmat_to_quat
from splatreplace_ns.template.compose import compose_scene
from splatreplace_ns.template.world_shading import shading_log_gain, template_normals


def _turn_z(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _box_faces():
    """Four flat Gaussians, the side faces of a unit box (normals ±x, ±y), as a template about the origin."""
    normals = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    means = 0.5 * normals
    # the flat axis (smallest scale) along each face's normal: z of the Gaussian turned onto the normal
    rots = []
    for n in normals:
        z = n
        x = torch.tensor([0.0, 0.0, 1.0])
        y = torch.linalg.cross(z, x)
        rots.append(torch.stack((x, y, z), dim=1))
    quats = rotmat_to_quat(torch.stack(rots))
    log_scales = torch.log(torch.tensor([[0.3, 0.3, 0.01]])).expand(4, 3).clone()
    return means, quats, log_scales, normals


def test_normals_are_the_flat_axis_pointing_outwards():
    means, quats, log_scales, normals = _box_faces()
    got = template_normals(means, -quats, log_scales, torch.zeros(3))  # -q is the same rotation
    assert torch.allclose(got, normals, atol=1e-5)
    # a Gaussian's axis has no sign: the same Gaussians seen from a centre beyond them point the other way
    assert torch.allclose(template_normals(means, quats, log_scales, 2 * means), -normals, atol=1e-5)
    zero = template_normals(means[:1], torch.zeros(1, 4), log_scales[:1], torch.zeros(3))  # zero quaternion
    assert torch.isfinite(zero).all() and zero.norm() == pytest.approx(1.0)


def test_the_gain_follows_the_world_normal():
    coeffs = torch.zeros(3, 4, 3)
    coeffs[:, 1] = 0.5  # brighter where the normal points to +x
    normals = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0]])
    gain = shading_log_gain(normals, coeffs)
    assert torch.allclose(gain, torch.tensor([[0.5] * 3, [-0.5] * 3, [0.0] * 3]))


def _compose(means, quats, log_scales, sh, turns, shading=None):
    n = len(means)
    R = torch.stack([_turn_z(t) for t in turns])
    return compose_scene(means, quats, log_scales, torch.zeros(n), sh, torch.zeros(n, len(turns), 1, 3),
                         torch.ones(n, dtype=torch.long), torch.ones(len(turns), dtype=torch.long),
                         torch.arange(len(turns)), torch.arange(1, len(turns) + 1), rotmat_to_quat(R), R,
                         torch.zeros(len(turns), 3), lam=0.8, shading=shading)


def test_a_face_turned_away_from_the_light_is_shaded_on_that_copy_only():
    means, quats, log_scales, _ = _box_faces()
    sh = torch.full((4, 1, 3), 0.1)
    shading = torch.zeros(1, 4, 3)
    shading[0, 1] = 0.4  # the sun in +x
    plain = _compose(means, quats, log_scales, sh, [0.0, 180.0])
    shaded = _compose(means, quats, log_scales, sh, [0.0, 180.0], shading)
    rgb_plain, rgb = SH_C0 * plain.sh[:, 0] + 0.5, SH_C0 * shaded.sh[:, 0] + 0.5
    # rows: copy 1's four faces, then copy 2's; face 0 (+x in the template) faces +x on copy 1 and -x on copy 2
    assert torch.allclose(rgb[0], rgb_plain[0] * math.exp(0.4), atol=1e-5)
    assert torch.allclose(rgb[4], rgb_plain[4] * math.exp(-0.4), atol=1e-5)
    assert torch.allclose(rgb[[2, 3, 6, 7]], rgb_plain[[2, 3, 6, 7]], atol=1e-5)  # ±y faces: side-on to the sun
    assert torch.equal(_compose(means, quats, log_scales, sh, [0.0, 180.0], torch.zeros(1, 4, 3)).sh, plain.sh)


def test_turned_copies_under_one_sun_are_fitted_by_one_colour_and_one_shading():
    """Four copies of a box turned 0/90/180/270° about the vertical, lit by a sun from +x (Lambert plus ambient).
    Shared colours alone cannot explain a face that is lit on one copy and dark on another; shared colours with the
    world shading can (fitted by Adam on the colours directly: the capacity of the model, not the renderer)."""
    means, quats, log_scales, normals = _box_faces()
    turns = [0.0, 90.0, 180.0, 270.0]
    albedo = torch.tensor([[0.8, 0.3, 0.2], [0.2, 0.7, 0.3], [0.3, 0.3, 0.8], [0.6, 0.6, 0.2]])
    sun = torch.tensor([1.0, 0.0, 0.0])
    target = torch.cat([albedo * (0.3 + 0.7 * ((normals @ _turn_z(t).T) @ sun).clamp_min(0))[:, None]
                        for t in turns])  # [copies × faces, 3]

    def fit(with_shading: bool) -> float:
        torch.manual_seed(0)
        sh = torch.nn.Parameter(torch.zeros(4, 1, 3))
        shading = torch.nn.Parameter(torch.zeros(1, 4, 3))
        optimizer = torch.optim.Adam([sh, shading] if with_shading else [sh], lr=0.02)
        for _ in range(500):
            optimizer.zero_grad()
            scene = _compose(means, quats, log_scales, sh, turns, shading if with_shading else None)
            loss = ((SH_C0 * scene.sh[:, 0] + 0.5 - target) ** 2).mean()
            loss.backward()
            optimizer.step()
        return float(loss.detach())

    without, with_shading = fit(False), fit(True)
    assert without > 0.01  # a shared colour per face leaves the light that differs between the copies
    assert with_shading < 0.2 * without, (with_shading, without)
