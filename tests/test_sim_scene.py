"""Synthetic scenes: object geometry, textures, presets and their effects, rendering."""

from __future__ import annotations

import json
import math
from collections import Counter

import cv2
import numpy as np
import open3d as o3d
import pytest

from splatreplace_ns.tools.sim import CLASS_SYMMETRY, CLASSES, PRESETS, class_mesh
from splatreplace_ns.tools.sim.cameras import PinholeCamera, intrinsics, look_at, trajectory
from splatreplace_ns.tools.sim.geometry import class_signed_distance
from splatreplace_ns.tools.sim.primitives import rotation_z
from splatreplace_ns.tools.sim.render import Renderer
from splatreplace_ns.tools.sim.textures import albedo


def _max_distance(a: o3d.geometry.TriangleMesh, b: o3d.geometry.TriangleMesh) -> float:
    """Largest distance from a's vertices to b's surface."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(b))
    pts = np.asarray(a.vertices, dtype=np.float32)
    return float(scene.compute_distance(o3d.core.Tensor(pts)).numpy().max())


def _surface_points(name: str, n: int = 3000) -> np.ndarray:
    """(n, 3) area-uniform samples on a class mesh (object frame), deterministic."""
    m = class_mesh(name)
    v, f = np.asarray(m.vertices), np.asarray(m.triangles)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(1)
    t = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random((2, n, 1))
    s = np.sqrt(r1)
    return (1 - s) * a[t] + s * (1 - r2) * b[t] + s * r2 * c[t]


@pytest.mark.parametrize("name", CLASSES)
def test_symmetry_metadata_is_true_for_geometry_and_texture(name):
    sym = CLASS_SYMMETRY[name]
    mesh = class_mesh(name)
    p = _surface_points(name)
    base = albedo(name, p)
    if sym == "none":
        angles = [math.pi / 2, math.pi, 3 * math.pi / 2]
        # no rotation about z reproduces the appearance (texture and/or shape differ)
        for a in angles:
            rotated = p @ rotation_z(a).T
            assert (
                np.abs(albedo(name, rotated) - base).mean() > 0.02
                or _max_distance(class_mesh(name).rotate(rotation_z(a), center=(0, 0, 0)), mesh) > 0.02
            )
        return
    n = sym.split(":")[1]
    angles = [0.7, 2.3] if n == "inf" else [2 * math.pi * k / int(n) for k in range(1, int(n))]
    for a in angles:
        rotated = class_mesh(name).rotate(rotation_z(a), center=(0, 0, 0))
        assert _max_distance(rotated, mesh) < 4e-3, f"{name} geometry not symmetric under {a:.2f} rad"
        assert np.abs(albedo(name, p @ rotation_z(a).T) - base).max() < 1e-4, f"{name} texture not symmetric"


def test_class_meshes_are_object_frame_and_distinct():
    for name in CLASSES:
        m = class_mesh(name)
        v = np.asarray(m.vertices)
        assert abs(v[:, 2].min()) < 1e-9, f"{name} stands on z = 0"
        assert np.abs(v[:, :2].mean(axis=0)).max() < 0.15, f"{name} centred on the z axis"
        assert 0.3 < v[:, 2].max() < 3.5
    chair = np.asarray(class_mesh("chair").vertices)
    assert not np.allclose(np.sort(chair[:, 0]), np.sort(-chair[:, 0])), "chair is not mirror-symmetric front/back"
    colours = {name: albedo(name, _surface_points(name, 500)).mean(axis=0) for name in CLASSES}
    names = list(colours)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            assert np.abs(colours[names[i]] - colours[names[j]]).max() > 0.04, (names[i], names[j])


# (class, points inside its solid, points outside it), from the part sizes in sim/geometry.py
_SOLID_CASES = [
    ("chair", [(0.0, 0.0, 0.465), (0.2, 0.2, 0.22), (-0.205, 0.0, 0.8)], [(0.0, 0.0, 0.3), (0.0, 0.0, 0.6)]),
    ("table", [(0.0, 0.0, 0.74), (0.62, 0.32, 0.3), (0.3, -0.12, 0.665)], [(0.0, 0.0, 0.3), (0.0, 0.2, 0.5)]),
    ("pillar", [(0.0, 0.0, 1.5), (0.3, 0.3, 0.08), (0.35, 0.35, 2.89)], [(0.35, 0.0, 1.5), (0.0, 0.0, -1.0),
                                                                         (-2.177, -2.028, -1.795)]),
    ("pawn", [(0.0, 0.0, 0.2), (0.0, 0.0, 0.41), (0.14, 0.0, 0.02)], [(0.12, 0.0, 0.2), (0.0, 0.0, 0.6)]),
    ("crate", [(0.0, 0.0, 0.2), (0.2, 0.15, 0.02), (0.0, 0.0, 0.385)], [(0.0, 0.0, 0.02), (0.0, 0.3, 0.2)]),
]


@pytest.mark.parametrize("name, inside, outside", _SOLID_CASES)
def test_signed_distance_knows_the_inside_of_a_mesh_made_of_parts(name, inside, outside):
    mesh = class_mesh(name)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    points = np.array(inside + outside, dtype=np.float64)
    unsigned = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
    signed = class_signed_distance(name, points)
    assert (signed[: len(inside)] < 0).all() and (signed[len(inside):] > 0).all(), signed
    np.testing.assert_allclose(np.abs(signed), unsigned, rtol=1e-5)


def test_signed_distance_far_from_every_class_is_outside():
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(64, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for name in CLASSES:
        mesh = class_mesh(name)
        low, high = mesh.get_min_bound(), mesh.get_max_bound()
        far = (low + high) / 2 + 2.0 * np.linalg.norm(high - low) * directions  # a diagonal beyond the box
        assert (class_signed_distance(name, far) > 0.5 * np.linalg.norm(high - low)).all(), name


def test_presets_have_the_requested_content_and_only_their_effects():
    assert set(PRESETS) >= {"office", "temple", "chess", "lighting", "tiny"}
    office = PRESETS["office"]
    assert office.contents() == {"table": 3, "chair": 9}
    assert office.effects.enabled() == ["occlusion", "coverage_imbalance", "slanted_sun"]
    assert (office.res, office.n_train, office.n_test) == ((320, 240), 200, 50)
    assert PRESETS["temple"].contents()["pillar"] >= 8 and PRESETS["temple"].effects.far_test_views
    chess = Counter(PRESETS["chess"].contents())
    assert chess["pawn"] >= 2 and CLASS_SYMMETRY["pawn"] == "rot_z:inf" and CLASS_SYMMETRY["rook"] == "rot_z:4"
    assert CLASS_SYMMETRY["knight"] == "none"
    assert set(PRESETS["lighting"].effects.enabled()) == {"varied_lighting", "shadows", "slanted_sun"}
    tiny = PRESETS["tiny"]
    assert tiny.res == (64, 48) and tiny.n_train + tiny.n_test <= 12 and sum(tiny.contents().values()) == 3
    for name, p in PRESETS.items():
        assert p.layout(0).scene.shadows == p.effects.shadows, name
        # a slanted sun is declared exactly where a directional light is not overhead; lit overhead, it is not
        suns = [light.vector for light in p.layout(0).scene.lights if light.kind == "directional"]
        assert p.effects.slanted_sun == any(abs(v[0]) + abs(v[1]) > 1e-9 for v in suns), name
        assert not p.effects_lit("overhead").slanted_sun
        assert not any(abs(v[0]) + abs(v[1]) > 1e-9 for v in (light.vector for light in p.layout(0, "overhead").scene.lights
                                                             if light.kind == "directional")), name


def test_layout_depends_on_seed_only():
    a, b, c = (PRESETS["office"].layout(s).scene.instances for s in (0, 0, 1))
    assert all(np.array_equal(x.pose, y.pose) for x, y in zip(a, b))
    assert not all(np.array_equal(x.pose, y.pose) for x, y in zip(a, c))


def _first_camera(name: str, w: int, h: int) -> tuple[Renderer, PinholeCamera]:
    p = PRESETS[name]
    layout = p.layout(0)
    c2w = trajectory(layout.train_path, 10, np.random.default_rng(0))[5]
    return Renderer(layout.scene), PinholeCamera(c2w, *intrinsics(w, h, p.fov_deg), w, h)


def test_shadow_rays_only_where_the_preset_asks(monkeypatch):
    calls = {"n": 0}
    original = Renderer.occluded

    def counting(self, *args, **kwargs):
        calls["n"] += 1
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Renderer, "occluded", counting)
    for name in ("office", "temple", "chess", "tiny"):
        r, cam = _first_camera(name, 32, 24)
        r.render(cam)
    assert calls["n"] == 0
    r, cam = _first_camera("lighting", 32, 24)
    r.render(cam)
    assert calls["n"] > 0


def test_copies_identical_up_to_lighting():
    """Textures live in the object frame: corresponding points on two copies have the same albedo."""
    r = Renderer(PRESETS["office"].layout(0).scene)
    chairs = [i for i in r.scene.instances if i.cls == "chair"]
    a, b = chairs[0], chairs[4]
    local = _surface_points("chair", 2000)
    pa = local @ a.pose[:3, :3].T + a.pose[:3, 3]
    pb = local @ b.pose[:3, :3].T + b.pose[:3, 3]
    geometry_of = {inst.id: len(r.scene.surfaces) + k for k, inst in enumerate(r.scene.instances)}
    alb_a = r.albedo_at(pa, np.full(len(pa), geometry_of[a.id]))
    alb_b = r.albedo_at(pb, np.full(len(pb), geometry_of[b.id]))
    assert np.abs(alb_a - alb_b).max() < 1e-4
    assert alb_a.std(axis=0).max() > 0.05, "textured, not flat"


def test_lighting_differs_between_copies_only_in_the_lighting_preset():
    """Light reaching the same seat points of every chair: equal in the office, different under varied lighting."""

    def spread(name: str) -> float:
        r = Renderer(PRESETS[name].layout(0).scene)
        g = np.linspace(-0.15, 0.15, 5)
        local = np.stack(np.meshgrid(g, g, [0.492]), -1).reshape(-1, 3)  # points on the seat top
        up = np.tile([0.0, 0.0, 1.0], (len(local), 1))
        light = []
        for inst in (i for i in r.scene.instances if i.cls == "chair"):
            p = local @ inst.pose[:3, :3].T + inst.pose[:3, 3]
            light.append(r.irradiance(p, up).mean(axis=0))
        return float(np.ptp(np.stack(light), axis=0).max())

    assert spread("office") < 1e-6
    assert spread("lighting") > 0.1


def _face_light_spread(light: str, preset: str = "office", cls: str = "chair") -> float:
    """Largest spread, over a preset's copies of ``cls``, of the light reaching the same points of every face of
    the object (its side faces turn with the copy)."""
    r = Renderer(PRESETS[preset].layout(0, light).scene)
    mesh = class_mesh(cls)
    mesh.compute_triangle_normals()
    tri = np.asarray(mesh.triangles)
    centres = np.asarray(mesh.vertices)[tri].mean(axis=1)
    normals = np.asarray(mesh.triangle_normals)
    light_per_copy = []
    for inst in (i for i in r.scene.instances if i.cls == cls):
        R, t = inst.pose[:3, :3], inst.pose[:3, 3]
        light_per_copy.append(r.irradiance(centres @ R.T + t, normals @ R.T))
    return float(np.ptp(np.stack(light_per_copy), axis=0).max())


def test_a_slanted_sun_lights_turned_copies_differently_and_overhead_alike():
    """Under the office's slanted sun a face of a chair gets different light on copies turned differently
    (per-instance lighting the preset does not ask for); with ``light="overhead"`` every copy gets the same."""
    assert _face_light_spread("preset") > 0.3
    assert _face_light_spread("overhead") < 1e-5
    # the temple's columns, turned between -165 and 97 degrees, more so
    assert _face_light_spread("preset", "temple", "pillar") > 0.7
    assert _face_light_spread("overhead", "temple", "pillar") < 1e-5
    with pytest.raises(ValueError, match="light"):
        PRESETS["office"].layout(0, "sideways")


def test_overhead_light_changes_the_images_only(tmp_path):
    from splatreplace_ns.tools.sim import make_scene

    for light in ("preset", "overhead"):
        make_scene("tiny", tmp_path / light, seed=0, n_train=2, n_test=1, workers=1, light=light)
    meta = json.loads((tmp_path / "overhead" / "transforms.json").read_text())
    assert meta["sim"]["light"] == "overhead"
    for sub in ("masks", "depth", "images"):
        same = [(tmp_path / "preset" / sub / f.name).read_bytes() == f.read_bytes()
                for f in sorted((tmp_path / "overhead" / sub).iterdir())]
        assert all(same) if sub != "images" else not any(same), sub


def test_matchers_find_features_on_instances():
    r, cam = _first_camera("office", 240, 180)
    frame = r.render(cam)
    gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
    kps = cv2.SIFT_create().detect(gray, None)
    on_objects = [k for k in kps if frame.ids[int(k.pt[1]), int(k.pt[0])] > 0]
    assert len(on_objects) >= 40, len(on_objects)


def test_camera_convention():
    eye, target = np.array([1.0, -2.0, 1.5]), np.array([0.0, 0.0, 0.5])
    c2w = look_at(eye, target)
    assert np.allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3))
    forward = -c2w[:3, 2]
    assert np.allclose(forward, (target - eye) / np.linalg.norm(target - eye))
    assert c2w[2, 1] > 0, "camera y axis points up"
    assert abs(c2w[2, 0]) < 1e-12, "no roll"
