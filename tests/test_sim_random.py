"""Random scenes (``splatreplace sim random``): a distribution with ground truth, declared effects and nothing else."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import tyro
from sim_checks import check_clicks_inside_instances, mask_iou_against_meshes

from splatreplace_ns.tools.sim import CLASS_SYMMETRY, SimCommand, class_mesh, make_scene
from splatreplace_ns.tools.sim.presets import Effects
from splatreplace_ns.tools.sim.random_scenes import LAYOUTS, SUITE_CLASSES, YAWS, class_extent, draw_recipe, random_preset
from splatreplace_ns.tools.sim.render import Renderer

DEV = range(100)


def _seeds_covering_every_class() -> list[int]:
    """The first dev seeds whose scenes, together, hold every suite class."""
    need, chosen = set(SUITE_CLASSES), []
    for seed in DEV:
        classes = {g.cls for g in draw_recipe(seed).groups}
        if classes & need:
            chosen.append(seed)
            need -= classes
        if not need:
            return chosen
    raise AssertionError(f"no dev scene holds {sorted(need)}")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[int, Path]:
    root = tmp_path_factory.mktemp("random")
    return {s: make_scene("random", root / str(s), seed=s, res=(64, 48), n_train=16, n_test=2)
            for s in _seeds_covering_every_class()}


def test_recipes_draw_the_whole_distribution():
    recipes = [draw_recipe(s) for s in DEV]
    counts = Counter()
    for r in recipes:
        assert 1 <= len(r.groups) <= 3 and len({g.cls for g in r.groups}) == len(r.groups)
        assert all(3 <= g.count <= 12 for g in r.groups)
        heights = [class_extent(g.cls)[1] for g in r.groups]
        assert r.effects.coverage_imbalance or r.effects.occlusion, "the capture leaves some copy poorly seen"
        assert r.effects.far_test_views
        counts.update(g.cls for g in r.groups)
        counts.update(f"layout {g.layout}" for g in r.groups)
        counts.update(f"yaw {g.yaw}" for g in r.groups)
        counts.update(f"effect {e}" for e in r.effects.enabled())
        counts.update(f"{len(r.groups)} classes" for _ in [0])
        counts.update(["indoor" if r.indoor else "outdoor"])
        assert max(heights) / min(heights) < 7.0
    assert len(SUITE_CLASSES) >= 8 and all(counts[c] > 0 for c in SUITE_CLASSES), counts
    assert all(counts[f"layout {k}"] > 0 for k in LAYOUTS) and all(counts[f"yaw {k}"] > 0 for k in YAWS), counts
    for name in (f.name for f in fields(Effects)):
        on = counts[f"effect {name}"]
        assert on > 0 and (on < len(recipes) or name == "far_test_views"), (name, on)
    assert all(counts[f"{n} classes"] > 0 for n in (1, 2, 3)) and counts["indoor"] and counts["outdoor"]
    # several symmetries, and at least half of the classes carry a detail that breaks their overall shape's
    symmetries = {CLASS_SYMMETRY[c] for c in SUITE_CLASSES}
    assert {"none", "rot_z:3", "rot_z:4", "rot_z:inf"} <= symmetries
    assert sum(CLASS_SYMMETRY[c] == "none" for c in SUITE_CLASSES) >= len(SUITE_CLASSES) / 2


def test_same_seed_same_bytes(tmp_path):
    a = make_scene("random", tmp_path / "a", seed=6, res=(48, 36), n_train=10, n_test=2, workers=1)
    b = make_scene("random", tmp_path / "b", seed=6, res=(48, 36), n_train=10, n_test=2, workers=2)
    files = sorted(p.relative_to(a.parent) for p in a.parent.rglob("*") if p.is_file())
    assert len(files) > 30 and files == sorted(p.relative_to(b.parent) for p in b.parent.rglob("*") if p.is_file())
    assert all((a.parent / f).read_bytes() == (b.parent / f).read_bytes() for f in files)
    c = make_scene("random", tmp_path / "c", seed=7, res=(48, 36), n_train=10, n_test=2)
    assert json.loads(c.read_text())["instances"] != json.loads(a.read_text())["instances"]


def test_masks_of_every_class_match_its_mesh(scenes):
    """Every suite class's instances, ray-cast from their ground-truth poses, reproduce the masks (IoU >= 0.98)."""
    seen = set()
    for path in scenes.values():
        meta = json.loads(path.read_text())
        classes = {i["id"]: i["class"] for i in meta["instances"]}
        for k, iou in mask_iou_against_meshes(path).items():
            assert iou >= 0.98, f"{path.parent.name}: instance {k} ({classes[k]}) IoU {iou:.3f}"
            seen.add(classes[k])
    assert seen == set(SUITE_CLASSES)


def test_clicks_inside_their_instance(scenes):
    for path in scenes.values():
        check_clicks_inside_instances(path)


def test_written_metadata_names_classes_symmetries_and_effects(scenes):
    for seed, path in scenes.items():
        meta = json.loads(path.read_text())
        recipe = draw_recipe(seed)
        assert meta["sim"]["preset"] == "random" and meta["sim"]["seed"] == seed
        assert meta["sim"]["effects"] == {f.name: getattr(recipe.effects, f.name) for f in fields(Effects)}
        assert meta["sim"]["scene"] == recipe.as_json()
        assert Counter(i["class"] for i in meta["instances"]) == Counter({g.cls: g.count for g in recipe.groups})
        for inst in meta["instances"]:
            assert inst["symmetry"] == CLASS_SYMMETRY[inst["class"]]
            pose = np.asarray(inst["transform_matrix"])
            assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
        coverage = meta["sim"]["instance_coverage"]
        assert sorted(map(int, coverage)) == sorted(i["id"] for i in meta["instances"])
        assert all(c["train_views"] >= 1 and c["train_pixels"] >= 1 for c in coverage.values())
        assert (meta.get("depth_zero") == "far") == (not recipe.indoor)


def _face_light(renderer: Renderer, cls: str) -> np.ndarray:
    """(copies, faces, 3) light reaching the centre of every face of each copy of ``cls``."""
    mesh = class_mesh(cls)
    mesh.compute_triangle_normals()
    centres = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    normals = np.asarray(mesh.triangle_normals)
    out = []
    for inst in (i for i in renderer.scene.instances if i.cls == cls):
        R, t = inst.pose[:3, :3], inst.pose[:3, 3]
        out.append(renderer.irradiance(centres @ R.T + t, normals @ R.T))
    return np.stack(out)


def test_declared_effects_are_on_and_the_others_off():
    """Each effect is simulated exactly where the scene declares it; without a lighting effect every copy of a
    class is lit alike, without per-copy appearance every copy of a class has the same colours."""
    lit_alike = lit_apart = 0
    for seed in range(40):
        recipe = draw_recipe(seed)
        e = recipe.effects
        layout = random_preset(seed).layout(seed)
        scene = layout.scene
        suns = [light.vector for light in scene.lights if light.kind == "directional"]
        assert len(suns) == 1 and e.slanted_sun == (abs(suns[0][0]) + abs(suns[0][1]) > 1e-9), seed
        assert e.varied_lighting == any(light.kind == "point" for light in scene.lights), seed
        assert e.shadows == scene.shadows, seed
        assert e.occlusion == any(s.material == "screen" for s in scene.surfaces), seed
        assert e.coverage_imbalance == (not layout.train_path.closed), seed
        by_class: dict[str, list[np.ndarray]] = {}
        for inst in scene.instances:
            by_class.setdefault(inst.cls, []).append(np.asarray(inst.colour))
        spread = max(np.ptp(np.stack(c), axis=0).max() for c in by_class.values())
        assert (spread > 1e-3) if e.per_copy_appearance else (spread == 0.0), seed
        renderer = Renderer(scene)
        for g in recipe.groups:
            light = _face_light(renderer, g.cls)
            light_spread = float(np.ptp(light, axis=0).max())
            if not (e.slanted_sun or e.varied_lighting or e.shadows):
                assert light_spread < 1e-5, (seed, g.cls)
                lit_alike += 1
            elif e.slanted_sun and g.yaw in ("free", "quarter"):
                assert light_spread > 0.05, (seed, g.cls)  # turned copies show a face differently lit
                lit_apart += 1
    assert lit_alike and lit_apart


def test_describe_and_the_command_line(tmp_path, capsys):
    tyro.cli(SimCommand, args=["random", "--seed", "6", "--list"]).main()
    text = capsys.readouterr().out
    recipe = draw_recipe(6)
    assert "seed 6" in text and "effects on:" in text and "effects off:" in text
    assert all(f"{g.count} x {g.cls}" in text for g in recipe.groups)
    tyro.cli(SimCommand, args=["--list"]).main()
    assert "random:" in capsys.readouterr().out
    SimCommand(preset="random", out=tmp_path / "r", seed=3, res="48x36", n_train=10, n_test=2).main()
    text = capsys.readouterr().out
    assert "random 48x36" in text and "effects on:" in text
    assert (tmp_path / "r" / "transforms.json").exists()
