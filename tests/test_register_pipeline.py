"""End-to-end instance registration (splatreplace_ns.poses.register) against simulator ground truth.

Oracle: a "perfect" Gaussian scene built from the ground-truth meshes of the ``tiny`` preset (three crates):
surface samples coloured with the class texture in object-local coordinates, so the copies differ only by
their pose. No training involved.
"""

import json
import time
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from splatreplace_ns.poses import rotation_error_deg, translation_error_rel
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.instance import InstanceGaussians
from splatreplace_ns.poses.register import (
    choose_templates,
    register_instance,
    register_instances,
    render_instance_views,
)
from scenes import sample_mesh
from splatreplace_ns.tools.sim import class_mesh, load_scene_meshes, make_scene
from splatreplace_ns.tools.sim.textures import albedo

torch.set_num_threads(1)

N_POINTS = 3000
# The defaults: 128 × 96 views, the paper's 5 × 5 sphere, top-10 pairs (a few seconds per instance on one thread).
FAST = dict(image_size=(128, 96))


def oracle_gaussians(mesh_world, pose, cls, n=N_POINTS, seed=0, grey=False):
    """Gaussians on the surface of a world-frame mesh, textured in the object frame (pose: object→world)."""
    pts, area = sample_mesh(mesh_world, n, seed)
    local = (pts - pose[:3, 3]) @ pose[:3, :3]
    rgb = np.full((n, 3), 0.5, np.float32) if grey else albedo(cls, local)
    spacing = np.sqrt(area / n)
    return InstanceGaussians(
        means=torch.tensor(pts, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.6 * spacing),
        opacities=torch.full((n,), 0.95),
        colors=torch.tensor(rgb, dtype=torch.float32),
    )


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    path = make_scene("tiny", tmp_path_factory.mktemp("tiny"), workers=1)
    meta = json.loads(path.read_text())
    meshes = load_scene_meshes(path)
    poses = {int(i["id"]): np.asarray(i["transform_matrix"], dtype=np.float64) for i in meta["instances"]}
    classes = {int(i["id"]): i["class"] for i in meta["instances"]}
    symmetry = {int(i["id"]): i.get("symmetry", "none") for i in meta["instances"]}
    # Different sample counts make the template choice unambiguous (most Gaussians: instance 2).
    counts = {1: N_POINTS - 200, 2: N_POINTS, 3: N_POINTS - 100}
    gaussians = {
        iid: oracle_gaussians(meshes[iid], poses[iid], classes[iid], n=counts.get(iid, N_POINTS), seed=iid)
        for iid in poses
    }
    return dict(poses=poses, classes=classes, symmetry=symmetry, gaussians=gaussians, meshes=meshes)


def pose_errors(T_est, P_src, P_tpl, symmetry, cls):
    """Rotation error (deg, modulo symmetry) and translation error (fraction of the bbox diagonal) of the
    source pose implied by T_est (template ≈ T_est · source)."""
    P_est = np.linalg.inv(T_est) @ P_tpl
    diag = float(np.linalg.norm(class_mesh(cls).get_axis_aligned_bounding_box().get_extent()))
    return rotation_error_deg(P_est, P_src, symmetry), translation_error_rel(P_est, P_src, diag)


def test_choose_templates():
    assert choose_templates({"a": [1, 2, 3], "b": [7]}, {1: 10, 2: 30, 3: 20, 7: 1}) == {"a": 2, "b": 7}
    assert choose_templates({"a": [4, 2]}, {4: 5, 2: 5}) == {"a": 2}  # tie: smallest id
    with pytest.raises(ValueError):
        choose_templates({"a": [1]}, {})


def test_render_instance_views_shapes(tiny):
    cfg = RegistrationConfig(image_size=(48, 36), n_azimuth=2, n_elevation=2)
    inst = tiny["gaussians"][1]
    images, depths, alphas, viewmats, K = render_instance_views(inst, cfg)
    assert images.shape == (4, 36, 48, 3) and depths.shape == (4, 36, 48) and alphas.shape == (4, 36, 48)
    assert viewmats.shape == (4, 4, 4) and K.shape == (3, 3)
    assert (alphas > 0.5).mean() > 0.2  # the instance fills a good part of each view
    # SH colours of degree 0 give the same image as the equivalent RGB (gsplat convention: rgb = 0.2821 c + 0.5).
    c0 = 0.28209479177387814
    sh = ((torch.as_tensor(inst.colors) - 0.5) / c0)[:, None, :]
    inst_sh = InstanceGaussians(inst.means, inst.quats, inst.scales, inst.opacities, sh, sh_degree=0)
    images_sh = render_instance_views(inst_sh, cfg).images
    assert np.abs(images_sh - images).max() < 1e-4


def test_register_instances_recovers_ground_truth(tiny):
    cfg = RegistrationConfig(**FAST)
    t0 = time.perf_counter()
    results = register_instances(tiny["gaussians"], tiny["classes"], cfg)
    elapsed = time.perf_counter() - t0
    poses = tiny["poses"]
    assert sorted(results) == sorted(poses)
    assert results[2].template_id == 2 and results[2].success and np.allclose(results[2].transform, np.eye(4))
    for iid in (1, 3):
        res = results[iid]
        assert res.success, res.message
        assert res.instance_id == iid and res.template_id == 2
        rot_err, t_err = pose_errors(res.transform, poses[iid], poses[2], tiny["symmetry"][iid], tiny["classes"][iid])
        print(f"instance {iid}: rot {rot_err:.3f} deg, trans {100 * t_err:.3f} % of diag, "
              f"inliers {res.num_inliers}, fitness {res.fitness:.3f}, {res.time_s:.1f} s ({res.message})")
        assert rot_err < 1.0, res.message
        assert t_err < 0.01, res.message
        # copies on one floor: the default refines the chosen pose as a turn about up, so no tilt is left
        assert "(upright)" in res.message, res.message
        assert np.allclose(res.transform[:3, :3] @ [0, 0, 1], [0, 0, 1], atol=1e-9)
        # an accepted pose is the proposed one; the candidates are every view pair posed and every turn
        assert np.array_equal(res.proposed_transform, res.transform)
        assert sum(c["pair"][0] == -1 for c in res.candidates) == cfg.multistart_turns
        assert res.pair in [tuple(c["pair"]) for c in res.candidates]
    print(f"register_instances: {elapsed:.1f} s")


def test_upright_polish_only_when_asked_and_only_for_near_upright_poses(tiny):
    from splatreplace_ns.poses.refine import upright_polish

    g = tiny["gaussians"]
    free = register_instance(g[1], g[2], RegistrationConfig(**FAST, upright=False))
    assert free.success and "(upright" not in free.message
    src, tpl = g[1].centres(), g[2].centres()
    radius = float(np.linalg.norm(tpl - tpl.mean(0), axis=1).max())
    cfg = RegistrationConfig(**FAST)
    polished, done = upright_polish(src, tpl, free.transform, radius, cfg)
    assert done == " (upright)" and np.allclose(polished[:3, :3] @ [0, 0, 1], [0, 0, 1], atol=1e-9)
    rot_err, t_err = pose_errors(polished, tiny["poses"][1], tiny["poses"][2], tiny["symmetry"][1], tiny["classes"][1])
    assert rot_err < 1.0 and t_err < 0.01
    # a pose ICP left tilted by several degrees (as on sparse copies) is made upright again
    centre = free.transform[:3, :3] @ src.mean(0) + free.transform[:3, 3]
    lean = np.eye(4)
    lean[:3, :3] = Rotation.from_euler("x", 8.0, degrees=True).as_matrix()
    lean[:3, 3] = centre - lean[:3, :3] @ centre
    leaning = lean @ free.transform
    assert pose_errors(leaning, tiny["poses"][1], tiny["poses"][2], tiny["symmetry"][1], tiny["classes"][1])[0] > 7.0
    straightened, done = upright_polish(src, tpl, leaning, radius, cfg)
    assert done.startswith(" (upright")
    assert pose_errors(straightened, tiny["poses"][1], tiny["poses"][2], tiny["symmetry"][1], tiny["classes"][1])[0] < 1.0
    # a pose tilted beyond upright_max_tilt_deg (a copy lying on its side) is left alone and the log says so,
    # as is any pose when upright is off
    tilted = free.transform.copy()
    tilted[:3, :3] = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float) @ tilted[:3, :3]  # 90° about x
    kept, note = upright_polish(src, tpl, tilted, radius, cfg)
    assert kept is tilted and note.startswith(" (tilted 9") and "left as ICP placed it" in note
    off = replace(cfg, upright=False)
    assert upright_polish(src, tpl, free.transform, radius, off) == (free.transform, "")


def test_refine_from_a_perturbed_true_pose_comes_back(tiny):
    """refine_from (what the pipeline does to its chosen candidate) brings a pose 4° and a few centimetres off
    the truth back within the registration targets on the oracle crates, upright."""
    from splatreplace_ns.poses.refine import refine_from

    g, poses = tiny["gaussians"], tiny["poses"]
    true = poses[2] @ np.linalg.inv(poses[1])  # template ≈ true · source
    src_centre = g[1].centres().mean(0)
    off = np.eye(4)
    off[:3, :3] = Rotation.from_euler("z", 4.0, degrees=True).as_matrix()
    centre = true[:3, :3] @ src_centre + true[:3, 3]
    off[:3, 3] = centre - off[:3, :3] @ centre + np.array([0.03, -0.02, 0.0])
    start = off @ true
    errors = lambda T: pose_errors(T, poses[1], poses[2], tiny["symmetry"][1], tiny["classes"][1])
    assert errors(start)[0] > 3.9 and errors(start)[1] > 0.005
    T, fit, note = refine_from(g[1], g[2], start, RegistrationConfig(**FAST))
    assert note == " (upright)" and fit > 0.8
    rot_err, t_err = errors(T)
    assert rot_err < 0.5 and t_err < 0.01, (rot_err, t_err)
    # without ICP the start is kept as it is
    T0, _, note0 = refine_from(g[1], g[2], start, RegistrationConfig(**FAST, icp=False))
    assert np.allclose(T0, start) and note0 == ""


def test_single_instance_class_is_identity(tiny):
    results = register_instances({5: tiny["gaussians"][1]}, {5: "crate"}, RegistrationConfig(**FAST))
    assert list(results) == [5]
    assert results[5].success and results[5].template_id == 5 and np.allclose(results[5].transform, np.eye(4))


def test_untextured_source_fails_cleanly(tiny):
    grey = oracle_gaussians(tiny["meshes"][1], tiny["poses"][1], "crate", grey=True)
    grey.id = 1
    template = replace(tiny["gaussians"][2], id=2)
    res = register_instance(grey, template, RegistrationConfig(**FAST, min_photometric_fitness=0.5))
    print(res.message)
    assert not res.success, res.message
    assert "instance 1" in res.message
    assert np.allclose(res.transform, np.eye(4))
    # what was refused stays known: the chosen candidate's pose, below the colour score asked for
    assert res.proposed_transform is not None and not np.allclose(res.proposed_transform, np.eye(4))
    assert max(c["colour"] for c in res.candidates) < 0.5


def test_fpfh_method_runs(tiny):
    cfg = RegistrationConfig(method="fpfh")
    res = register_instances({k: tiny["gaussians"][k] for k in (2, 3)}, {2: "crate", 3: "crate"}, cfg)
    assert res[3].template_id == 2 and res[3].transform.shape == (4, 4)
    assert np.isfinite(res[3].transform).all() and res[3].message
    if res[3].success:
        rot_err, t_err = pose_errors(res[3].transform, tiny["poses"][3], tiny["poses"][2], "none", "crate")
        print(f"fpfh instance 3: rot {rot_err:.2f} deg, trans {100 * t_err:.2f} %")


def test_no_virtual_views_uses_given_cameras(tiny):
    from splatreplace_ns.poses import sphere_cameras

    cfg = RegistrationConfig(method="no_virtual_views", image_size=(64, 48), top_k=3)
    src, tpl = replace(tiny["gaussians"][3], id=3), replace(tiny["gaussians"][2], id=2)
    with pytest.raises(ValueError, match="cameras"):
        register_instance(src, tpl, cfg)
    # A ring of scene cameras looking at the middle of the scene (stand-in for the training views).
    viewmats, K = sphere_cameras(np.array([0.0, 0.0, 0.2]), 2.5, 64, 48, 50.0, n_azimuth=6, n_elevation=1,
                                 elevation_range_deg=(30.0, 30.0))
    res = register_instances({2: tpl, 3: src}, {2: "crate", 3: "crate"}, cfg, cameras=(viewmats, K))
    assert res[3].template_id == 2 and res[3].message and np.isfinite(res[3].transform).all()


def test_bad_config():
    with pytest.raises(ValueError):
        RegistrationConfig(method="mast3r")


def test_the_upright_polish_recovers_the_oracle_pose(tiny):
    """The upright polish on the solid centres ends at the oracle crate's pose."""
    g = tiny["gaussians"]
    res = register_instance(g[1], g[2], RegistrationConfig(**FAST))
    assert res.success and "(upright)" in res.message
    rot_err, t_err = pose_errors(res.transform, tiny["poses"][1], tiny["poses"][2], "none", "crate")
    assert rot_err < 0.5 and t_err < 0.01, (rot_err, t_err)


def test_solid_selects_opaque_gaussians_with_fallback():
    n = 10
    inst = InstanceGaussians(torch.zeros(n, 3), torch.zeros(n, 4), torch.ones(n, 3),
                             torch.tensor([0.9, 0.6, 0.5, 0.1, 0.2, 0.0, 0.3, 0.4, 0.45, 0.55]), torch.zeros(n, 3))
    keep = inst.solid(0.5, min_points=3)
    assert keep.tolist() == [True, True, True] + [False] * 6 + [True]
    assert inst.solid(0.5, min_points=5).all()  # only 4 opaque ones: use every Gaussian


def test_faint_off_surface_gaussians_do_not_pull_icp(tiny):
    """Faint Gaussians a few centimetres off the surface (as a short training leaves them) are left out of ICP
    and of the scores, so the pose is still recovered; the renders still include them."""
    src = replace(tiny["gaussians"][1], id=1)
    rng = np.random.default_rng(0)
    n = 1500
    pick = rng.choice(src.num_gaussians, n)
    offsets = rng.normal(size=(n, 3))
    offsets *= rng.uniform(0.03, 0.06, (n, 1)) / np.linalg.norm(offsets, axis=1, keepdims=True)
    fuzz = torch.as_tensor(src.centres()[pick] + offsets, dtype=torch.float32)

    def cat(a, b):
        return torch.cat([torch.as_tensor(a), torch.as_tensor(b)])

    faint = InstanceGaussians(
        means=cat(src.means, fuzz), quats=cat(src.quats, torch.as_tensor(src.quats)[pick]),
        scales=cat(src.scales, torch.as_tensor(src.scales)[pick]), opacities=cat(src.opacities, torch.full((n,), 0.1)),
        colors=cat(src.colors, torch.as_tensor(src.colors)[pick]), id=1,
    )
    cfg = RegistrationConfig(**FAST)
    res = register_instance(faint, replace(tiny["gaussians"][2], id=2), cfg)
    assert res.success, res.message
    rot_err, t_err = pose_errors(res.transform, tiny["poses"][1], tiny["poses"][2], tiny["symmetry"][1], "crate")
    print(f"with {n} faint Gaussians: rot {rot_err:.3f} deg, trans {100 * t_err:.3f} %, {res.message}")
    assert rot_err < 1.0 and t_err < 0.01, res.message
    everything = register_instance(faint, replace(tiny["gaussians"][2], id=2), replace(cfg, min_opacity=0.0))
    print(f"ICP and scores on every Gaussian: {everything.message}")
    assert everything.fitness < res.fitness - 0.1  # the faint layer, scored too, dilutes the fitness


def test_multistart_poses_turn_about_up_and_match_centroids():
    from splatreplace_ns.poses.candidates import multistart_poses

    rng = np.random.default_rng(1)
    src, tgt = rng.normal(size=(50, 3)), rng.normal(size=(40, 3)) + 5.0
    up = np.array([0.1, -0.2, 1.0])
    poses = multistart_poses(src, tgt, 12, up)
    assert len(poses) == 12 and multistart_poses(src, tgt, 0) == [] and multistart_poses(src[:0], tgt, 12) == []
    angles = []
    for T in poses:
        R = T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R @ up, up)  # a turn about the up axis
        assert np.allclose(R @ src.mean(0) + T[:3, 3], tgt.mean(0))
        angles.append(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    assert np.allclose(sorted(angles), sorted([min(30 * k, 360 - 30 * k) for k in range(12)]), atol=1e-6)


def test_multistart_registers_when_no_view_pair_gives_a_pose(tiny):
    """With PnP unable to pose any view pair (an inlier count no pair reaches), the instance fails without
    multi-start turns and is recovered with them: ICP from 12 turns about the up axis, picked by colour."""
    src, tpl = replace(tiny["gaussians"][1], id=1), replace(tiny["gaussians"][2], id=2)
    no_pnp = RegistrationConfig(**FAST, min_inliers=10**6, multistart_turns=0)
    failed = register_instance(src, tpl, no_pnp)
    assert not failed.success and "no view pair gave a pose" in failed.message
    res = register_instance(src, tpl, replace(no_pnp, multistart_turns=12))
    assert res.success, res.message
    rot_err, t_err = pose_errors(res.transform, tiny["poses"][1], tiny["poses"][2], tiny["symmetry"][1], "crate")
    print(f"multi-start only: rot {rot_err:.3f} deg, trans {100 * t_err:.3f} %, {res.message}")
    assert rot_err < 1.0 and t_err < 0.01, res.message


def test_choose_candidate_acceptable_first_then_colour_then_ties():
    """Order of the candidate choice without images: acceptable (fitness and colour over their minimums), then the
    colour score, then the tie-break."""
    from splatreplace_ns.poses.decision import choose_candidate

    cfg = RegistrationConfig()
    ties = [(0, 0, -k) for k in range(3)]
    # 0: acceptable, better colour; 1: acceptable; 2: best fitness but unacceptable (colour below the minimum)
    assert choose_candidate([0.535, 0.680, 0.99], [0.29, 0.25, 0.05], ties, cfg) == 0
    assert choose_candidate([0.535, 0.680, 0.99], [0.25, 0.25, 0.05], ties, cfg) == 0  # a tie: the tie-break
    assert choose_candidate([0.535, 0.680, 0.99], [0.25, 0.25, 0.05], ties[::-1], cfg) == 1
    # nothing acceptable: still an index (the caller reports the failure)
    assert choose_candidate([0.1, 0.15], [0.5, 0.4], ties[:2], cfg) in (0, 1)
