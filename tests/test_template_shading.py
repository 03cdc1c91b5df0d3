"""World-frame shading of template copies: exact colour scaling, normals turned the right way, composition."""

import math

import numpy as np
import torch

from splatreplace_ns.render.sh import sh_basis
from splatreplace_ns.template.compose import compose_scene, instance_poses
from splatreplace_ns.template.shading import camera_votes, oriented_normals, shade_sh, shading_factors


def _colour(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """[M, 3] rendered colour (before clamping) of SH [M, K, 3] seen along dirs [M, 3]."""
    degree = int(round(math.sqrt(sh.shape[1]))) - 1
    return torch.einsum("mk,mkc->mc", sh_basis(degree, dirs), sh) + 0.5


def test_shaded_sh_scales_the_rendered_colour_in_every_direction():
    torch.manual_seed(0)
    sh = torch.randn(50, 16, 3) * 0.3
    factors = torch.rand(50, 3) * 2.0 + 0.1
    dirs = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    assert torch.allclose(_colour(shade_sh(sh, factors), dirs), factors * _colour(sh, dirs), atol=1e-5)


def test_factors_are_one_without_a_normal_and_have_finite_gradients():
    weights = torch.tensor([[0.5, -0.2, 0.1], [0.0, 0.3, 0.0], [1.0, 0.0, -2.0]], requires_grad=True)
    normals = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    factors = shading_factors(normals, weights)
    assert torch.allclose(factors[0], torch.ones(3))
    assert torch.allclose(factors[1], torch.exp(weights[:, 0]).detach())
    factors.sum().backward()
    assert torch.isfinite(weights.grad).all()


def _camera_looking_at_origin(centre: np.ndarray):
    """world→camera (OpenCV) of a camera at ``centre`` looking at the origin, and K for 64×48."""
    forward = -centre / np.linalg.norm(centre)
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    viewmat = np.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ centre
    K = np.array([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
    return torch.tensor(viewmat, dtype=torch.float32), torch.tensor(K, dtype=torch.float32)


def _cube_surface(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Points on the faces of the cube [-0.5, 0.5]³ and their true outward normals."""
    g = np.linspace(-0.45, 0.45, n)
    u, v = [a.ravel() for a in np.meshgrid(g, g)]
    points, normals = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros((len(u), 3))
            others = [a for a in range(3) if a != axis]
            p[:, others[0]], p[:, others[1]], p[:, axis] = u, v, 0.5 * sign
            nrm = np.zeros_like(p)
            nrm[:, axis] = sign
            points.append(p)
            normals.append(nrm)
    return np.concatenate(points), np.concatenate(normals)


def _cube_depth(viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H, W] z-depth of the cube [-0.5, 0.5]³ (0 where a pixel's ray misses it), by the slab method."""
    R, t = viewmat[:3, :3].double(), viewmat[:3, 3].double()
    centre = -R.T @ t
    cols, rows = torch.meshgrid(torch.arange(width) + 0.5, torch.arange(height) + 0.5, indexing="xy")
    pix = torch.stack((cols, rows, torch.ones_like(cols)), -1).double()
    dirs_cam = pix @ torch.linalg.inv(K.double()).T  # z = 1 in the camera
    dirs = dirs_cam @ R  # world directions whose camera z is 1
    lo = (-0.5 - centre) / dirs  # ±inf where a direction component is 0
    hi = (0.5 - centre) / dirs
    near = torch.minimum(lo, hi).max(-1).values
    far = torch.maximum(lo, hi).min(-1).values
    hit = (near <= far) & (near > 0)
    return torch.where(hit, near, torch.zeros_like(near)).float()


def test_normals_face_the_cameras_that_saw_them_and_away_from_the_centre_elsewhere():
    points, truth = _cube_surface()
    means = torch.tensor(points, dtype=torch.float32)
    cams = [_camera_looking_at_origin(np.array([3.0, 0.4 * k, 0.5])) for k in (-1, 0, 1)]
    viewmats = torch.stack([c[0] for c in cams])
    Ks = torch.stack([c[1] for c in cams])
    depths = torch.stack([_cube_depth(viewmats[v], Ks[v], 64, 48) for v in range(3)])
    votes = camera_votes(means, viewmats, Ks, 64, 48, depths, depth_tolerance=0.05)
    front = truth[:, 0] > 0.5
    back = truth[:, 0] < -0.5
    assert (votes[torch.from_numpy(back)].norm(dim=-1) == 0).all()  # hidden behind the front face
    assert (votes[torch.from_numpy(front)].norm(dim=-1) > 0).all()
    labels = torch.ones(len(means), dtype=torch.long)
    normals = oriented_normals(means, labels, votes).numpy()
    agree = np.einsum("ij,ij->i", normals, truth)
    away_from_edges = np.abs(points).max(axis=1) - np.sort(np.abs(points), axis=1)[:, 1] > 0.1
    assert (agree[front & away_from_edges] > 0.9).all()
    assert (agree[back & away_from_edges] > 0.9).all()  # unseen: turned away from the centroid
    assert np.mean(agree[away_from_edges] > 0.9) > 0.95
    # background stays without a normal
    labels[:10] = 0
    assert (oriented_normals(means, labels, votes)[:10] == 0).all()


def test_a_copy_turned_by_half_a_turn_gets_the_light_of_its_world_facing():
    """Two copies of a one-Gaussian template facing +x in the template: the copy turned by 180° faces -x in
    the world, so with W along +x the first is brightened and the second darkened, by exp(±w)."""
    means = torch.tensor([[0.0, 0.0, 0.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.zeros(1, 3)
    opac = torch.zeros(1, 1)
    sh = torch.zeros(1, 1, 3)
    sh[0, 0] = torch.tensor([0.2, 0.1, -0.1])
    offsets = torch.zeros(1, 2, 1, 3)
    gauss_class = torch.tensor([1])
    half_turn = torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 1]])  # identity, 180° about z
    q, R, t = instance_poses(half_turn, torch.zeros(2, 3), torch.zeros(2, 6))
    weights = torch.zeros(3, 3)
    weights[:, 0] = 0.4
    scene = compose_scene(means, quats, scales, opac, sh, offsets, gauss_class, torch.tensor([1, 1]),
                          torch.tensor([0, 1]), torch.tensor([1, 2]), q, R, t, lam=1.0,
                          normals=torch.tensor([[1.0, 0.0, 0.0]]), shading=weights)
    plain = compose_scene(means, quats, scales, opac, sh, offsets, gauss_class, torch.tensor([1, 1]),
                          torch.tensor([0, 1]), torch.tensor([1, 2]), q, R, t, lam=1.0)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    lit, dark = _colour(scene.sh, d)
    base = _colour(plain.sh, d)
    assert torch.allclose(lit, base[0] * math.exp(0.4), atol=1e-5)
    assert torch.allclose(dark, base[1] * math.exp(-0.4), atol=1e-5)
