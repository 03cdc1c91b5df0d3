"""Scene presets. Each preset switches on only the effects its scene calls for.

A preset is a layout builder plus an explicit set of :class:`Effects`; the builder reads the flags
(an effect that is off is simply not simulated), so ``--list`` shows exactly what a scene contains.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from splatreplace_ns.tools.sim.cameras import PathSpec
from splatreplace_ns.tools.sim.primitives import box, pose
from splatreplace_ns.tools.sim.scene import Instance, Light, Scene, Surface


@dataclass(frozen=True)
class Effects:
    """Which effects a scene simulates (everything off by default)."""

    occlusion: bool = False
    """Instances hide each other (and get hidden by furniture) in the training views."""
    coverage_imbalance: bool = False
    """The training path covers one side only: some instances are seen from one side, another copy shows the rest."""
    far_test_views: bool = False
    """The test path runs far from the training path (else: a full loop close to it, interleaved)."""
    varied_lighting: bool = False
    """Copies receive different light: local coloured lights and a shadowing canopy."""
    shadows: bool = False
    """Cast shadows with secondary rays toward every light."""
    slanted_sun: bool = False
    """The sun is slanted (not overhead), so one face of upright copies turned differently is lit differently."""
    per_copy_appearance: bool = False
    """Copies of a class differ slightly in colour (the paper's per-instance SH offsets exist for this)."""

    def enabled(self) -> list[str]:
        """Names of the effects that are on."""
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name)]


EFFECT_HELP: dict[str, str] = {
    "occlusion": "instances hide each other in training views",
    "coverage_imbalance": "training path on one side; unseen sides are shown by other copies",
    "far_test_views": "test path far from the training path",
    "varied_lighting": "copies lit differently (coloured local lights, canopy)",
    "shadows": "shadow rays toward every light",
    "slanted_sun": "the sun is slanted: copies turned differently show a face differently lit",
    "per_copy_appearance": "copies of a class differ slightly in colour",
}


LIGHTS = ("preset", "overhead")
"""How a scene is lit: "preset" as the preset draws it; "overhead": every directional light moved to the zenith
(:func:`overhead_lighting`)."""


def overhead_lighting(scene: Scene) -> Scene:
    """The scene with every directional light straight overhead, colours kept (point lights, ambient and shadows
    unchanged).

    Under a slanted sun a face's shading depends on where it points in the world, so two upright copies turned
    differently show the same face differently lit: an effect of its own (per-instance lighting) that a preset
    without ``varied_lighting`` does not call for. Overhead, Lambertian shading depends on a face's tilt only, the
    same for every upright copy whatever its turn.
    """
    lights = [
        dataclasses.replace(light, vector=(0.0, 0.0, 1.0)) if light.kind == "directional" else light
        for light in scene.lights
    ]
    return dataclasses.replace(scene, lights=lights)


@dataclass(frozen=True)
class Layout:
    """A built scene with its capture paths."""

    scene: Scene
    train_path: PathSpec
    test_path: PathSpec


@dataclass(frozen=True)
class Preset:
    """A named synthetic scene."""

    name: str
    summary: str
    effects: Effects
    build: Callable[[Effects, np.random.Generator], Layout]
    res: tuple[int, int] = (320, 240)  # (W, H)
    n_train: int = 200
    n_test: int = 50
    fov_deg: float = 65.0
    supersample: int = 2  # RGB rays per pixel = supersample²
    details: Optional[dict] = None
    """What a drawn scene is made of (a random scene's recipe), written into transforms.json as ``sim.scene``."""
    open_sky: bool = False
    """Outdoors: where a ray hits nothing it sees the sky, and transforms.json says ``"depth_zero": "far"`` so
    that the base stage puts the sky far away rather than just behind the scene. Indoor presets leave depth 0
    unknown: their few such pixels are the void above the walls (office, one demo run each: ours 22.85 / 22.92
    dB full / masked with them supervised as far, 23.47 / 23.39 without; the baseline's full PSNR 23.13 and
    23.21)."""

    def layout(self, seed: int = 0, light: str = "preset") -> Layout:
        """Build the scene and capture paths for a seed (layout jitter only), lit as ``light`` says (:data:`LIGHTS`)."""
        if light not in LIGHTS:
            raise ValueError(f"light must be one of {LIGHTS}, got {light!r}")
        layout = self.build(self.effects, np.random.default_rng([seed, 0]))
        if light == "overhead":
            layout = dataclasses.replace(layout, scene=overhead_lighting(layout.scene))
        return layout

    def effects_lit(self, light: str = "preset") -> Effects:
        """The effects the scene shows when lit as ``light`` says: lit from overhead, its sun is not slanted."""
        return dataclasses.replace(self.effects, slanted_sun=False) if light == "overhead" else self.effects

    def contents(self) -> dict[str, int]:
        """{class: count} of the repeated objects."""
        return dict(Counter(i.cls for i in self.layout(0).scene.instances))


# ----------------------------------------------------------------------------- helpers


def _floor(size: float, material: str, z: float = 0.0) -> Surface:
    """Square slab whose top face is the plane z (default 0)."""
    return Surface(box((size, size, 0.1), (0.0, 0.0, z - 0.05)), material)


def _walls(half_x: float, half_y: float, height: float, material: str) -> list[Surface]:
    """Four walls (0.1 m thick) enclosing the rectangle |x| < half_x, |y| < half_y."""
    t = 0.1
    return [
        Surface(box((t, 2 * half_y, height), (half_x + t / 2, 0.0, height / 2)), material),
        Surface(box((t, 2 * half_y, height), (-half_x - t / 2, 0.0, height / 2)), material),
        Surface(box((2 * half_x + 2 * t, t, height), (0.0, half_y + t / 2, height / 2)), material),
        Surface(box((2 * half_x + 2 * t, t, height), (0.0, -half_y - t / 2, height / 2)), material),
    ]


def _near_test_path(train: PathSpec, height: tuple[float, float], radius_scale: float = 0.93) -> PathSpec:
    """A full loop close to the training path (what a test capture looks like when it is not far)."""
    a0 = train.azimuth_deg[0]
    return dataclasses.replace(
        train,
        azimuth_deg=(a0, a0 + 360.0),
        radii=(train.radii[0] * radius_scale, train.radii[1] * radius_scale),
        height=height,
        height_waves=2.0,
    )


# ----------------------------------------------------------------------------- scenes


def _office(e: Effects, rng: np.random.Generator) -> Layout:
    """Room with 3 tables and 9 chairs (3 per table, on alternating sides)."""
    instances: list[Instance] = []
    slots = [
        ((1, -0.33), (1, 0.33), (-1, 0.0)),
        ((-1, -0.33), (-1, 0.33), (1, 0.0)),
        ((1, -0.33), (1, 0.33), (-1, 0.0)),
    ]
    # Tucked-in chairs slide under the table top (occlusion); otherwise they stand clear of it.
    pull = 0.52 if e.occlusion else 0.98
    chairs = []
    for ti, tx in enumerate((-2.2, 0.0, 2.2)):
        t_xy = np.array([tx, 0.0]) + rng.normal(0.0, 0.05, 2)
        t_yaw = math.pi * int(rng.integers(0, 2)) + rng.normal(0.0, 0.03)
        instances.append(Instance(len(instances) + 1, "table", pose(t_yaw, (t_xy[0], t_xy[1], 0.0))))
        for side, dx in slots[ti]:
            xy = t_xy + np.array([dx, side * pull]) + rng.normal(0.0, 0.03, 2)
            yaw = -side * math.pi / 2 + rng.normal(0.0, 0.12 if e.occlusion else 0.3)
            chairs.append((xy, yaw))
    for xy, yaw in chairs:
        instances.append(Instance(len(instances) + 1, "chair", pose(yaw, (xy[0], xy[1], 0.0))))
    scene = Scene(
        instances=instances,
        surfaces=[_floor(10.0, "parquet")] + _walls(4.7, 3.4, 2.8, "plaster"),
        lights=[Light("directional", (0.4, -0.6, 1.0), (0.75, 0.72, 0.65))],
        ambient_sky=(0.36, 0.36, 0.38),
        ambient_ground=(0.2, 0.18, 0.15),
        shadows=e.shadows,
    )
    height = (1.05, 1.45) if e.occlusion else (2.0, 2.5)
    azimuth = (170.0, 370.0) if e.coverage_imbalance else (0.0, 360.0)
    train = PathSpec((0.0, 0.0), (3.95, 2.6), azimuth, height, (0.0, 0.0, 0.55), follow=(0.4, 0.0))
    if e.far_test_views:
        test = PathSpec((0.0, 0.0), (4.2, 3.0), (0.0, 180.0), (2.4, 2.7), (0.0, 0.0, 0.4), follow=(0.3, 0.0))
    else:
        test = _near_test_path(train, (1.35, 1.75))
    return Layout(scene, train, test)


def _temple(e: Effects, rng: np.random.Generator) -> Layout:
    """A colonnade of 9 columns on a stepped platform under an entablature, open sky."""
    base_z = 0.45
    rows = [0.0, 2.2] if e.occlusion else [0.0]
    instances: list[Instance] = []
    for y in rows:
        for i in range(9):
            x = (i - 4) * 1.9 + rng.normal(0.0, 0.02)
            instances.append(
                Instance(len(instances) + 1, "pillar", pose(rng.uniform(0.0, 2 * math.pi), (x, y, base_z)))
            )
    yc = 0.5 * (rows[0] + rows[-1])
    depth = 1.6 + (rows[-1] - rows[0])
    surfaces = [_floor(60.0, "stone")]
    for k in range(3):  # steps
        surfaces.append(
            Surface(box((17.6 - 0.4 * k, depth + 0.8 - 0.4 * k, 0.15), (0.0, yc, 0.075 + 0.15 * k)), "travertine")
        )
    top = base_z + 3.0
    surfaces.append(Surface(box((17.2, depth - 0.7, 0.5), (0.0, yc, top + 0.25)), "travertine"))  # architrave
    surfaces.append(Surface(box((17.2, depth - 0.65, 0.45), (0.0, yc, top + 0.725)), "travertine"))  # frieze
    surfaces.append(Surface(box((17.8, depth - 0.3, 0.15), (0.0, yc, top + 1.025)), "travertine"))  # cornice
    scene = Scene(
        instances=instances,
        surfaces=surfaces,
        lights=[Light("directional", (-0.5, -0.8, 0.9), (0.85, 0.8, 0.7))],
        ambient_sky=(0.34, 0.37, 0.43),
        ambient_ground=(0.2, 0.18, 0.15),
        shadows=e.shadows,
    )
    azimuth = (205.0, 335.0) if e.coverage_imbalance else (0.0, 360.0)
    train = PathSpec((0.0, yc), (9.5, 6.0), azimuth, (1.5, 2.2), (0.0, yc, 2.0), follow=(0.55, 0.0))
    if e.far_test_views:
        test = PathSpec((0.0, yc), (12.5, 9.0), (25.0, 155.0), (3.5, 5.0), (0.0, yc, 1.8), follow=(0.4, 0.0))
    else:
        test = _near_test_path(train, (1.7, 2.4))
    return Layout(scene, train, test)


def _chess(e: Effects, rng: np.random.Generator) -> Layout:
    """A chessboard in mid-game: 8 pawns, 2 rooks, 2 knights, 2 bishops on distinct squares."""
    classes = ["pawn"] * 8 + ["rook"] * 2 + ["knight"] * 2 + ["bishop"] * 2
    squares = rng.choice(64, size=len(classes), replace=False)
    instances = []
    for k, (cls, sq) in enumerate(zip(classes, squares)):
        xy = (np.array([sq % 8, sq // 8]) - 3.5) * 0.35 + rng.normal(0.0, 0.015, 2)
        instances.append(Instance(k + 1, cls, pose(rng.uniform(0.0, 2 * math.pi), (xy[0], xy[1], 0.0))))
    scene = Scene(
        instances=instances,
        surfaces=[_floor(30.0, "chessboard")],
        lights=[Light("directional", (0.3, -0.5, 1.0), (0.8, 0.76, 0.68))],
        shadows=e.shadows,
    )
    azimuth = (200.0, 340.0) if e.coverage_imbalance else (0.0, 360.0)
    train = PathSpec((0.0, 0.0), (3.6, 3.6), azimuth, (1.9, 2.7), (0.0, 0.0, 0.15), jitter=0.06, target_jitter=0.1)
    if e.far_test_views:
        test = PathSpec((0.0, 0.0), (5.5, 5.5), (20.0, 160.0), (0.7, 1.0), (0.0, 0.0, 0.2))
    else:
        test = _near_test_path(train, (1.0, 1.4), radius_scale=0.85)
    return Layout(scene, train, test)


def _lighting(e: Effects, rng: np.random.Generator) -> Layout:
    """Six identical chairs in two facing rows under a low sun, coloured lamps and a canopy."""
    instances = []
    for row, y in enumerate((-0.75, 0.75)):
        for x in (-1.3, 0.0, 1.3):
            yaw = (math.pi / 2 if row == 0 else -math.pi / 2) + rng.normal(0.0, 0.25)
            xy = np.array([x, y]) + rng.normal(0.0, 0.04, 2)
            instances.append(Instance(len(instances) + 1, "chair", pose(yaw, (xy[0], xy[1], 0.0))))
    surfaces = [_floor(20.0, "concrete"), Surface(box((10.0, 0.1, 3.0), (0.0, 3.25, 1.5)), "plaster")]
    lights = [Light("directional", (-0.25, -0.3, 0.92), (1.0, 0.94, 0.82))]
    if e.varied_lighting:
        # The canopy's shadow (sun offset ≈ (0.68, 0.82) m at its height) falls on the x = 1.3 chairs.
        surfaces.append(Surface(box((1.9, 2.6, 0.06), (0.62, -0.82, 2.5)), "canvas"))
        lights.append(Light("point", (-2.1, 0.0, 0.8), (2.2, 0.9, 0.2), falloff=1.0))  # warm lamp by the x < 0 chairs
        lights.append(
            Light("point", (0.0, 1.75, 0.7), (0.2, 0.55, 2.2), falloff=0.8)
        )  # cool lamp by the +y middle chair
    scene = Scene(
        instances=instances,
        surfaces=surfaces,
        lights=lights,
        ambient_sky=(0.22, 0.24, 0.28),
        ambient_ground=(0.1, 0.09, 0.08),
        shadows=e.shadows,
    )
    azimuth = (200.0, 340.0) if e.coverage_imbalance else (0.0, 360.0)
    train = PathSpec((0.0, 0.0), (3.3, 2.6), azimuth, (1.6, 2.2), (0.0, 0.0, 0.45))
    if e.far_test_views:
        test = PathSpec((0.0, 0.0), (5.5, 2.9), (20.0, 160.0), (2.6, 2.9), (0.0, 0.0, 0.4))
    else:
        test = _near_test_path(train, (1.1, 1.5))
    return Layout(scene, train, test)


def _tiny(e: Effects, rng: np.random.Generator) -> Layout:
    """Three crates on a parquet floor before a wall: a scene for tests."""
    spots = [(-0.75, -0.1, 0.3), (0.05, 0.45, 2.4), (0.8, -0.25, 4.3)]
    instances = []
    for k, (x, y, yaw) in enumerate(spots):
        xy = np.array([x, y]) + rng.normal(0.0, 0.03, 2)
        instances.append(Instance(k + 1, "crate", pose(yaw + rng.normal(0.0, 0.1), (xy[0], xy[1], 0.0))))
    scene = Scene(
        instances=instances,
        surfaces=[_floor(8.0, "parquet"), Surface(box((8.0, 0.1, 2.0), (0.0, 2.55, 1.0)), "plaster")],
        lights=[Light("directional", (0.3, -0.6, 1.0), (0.8, 0.78, 0.7))],
        shadows=e.shadows,
    )
    azimuth = (200.0, 340.0) if e.coverage_imbalance else (0.0, 360.0)
    train = PathSpec((0.0, 0.0), (2.2, 1.9), azimuth, (1.1, 1.5), (0.0, 0.1, 0.2), jitter=0.05, target_jitter=0.08)
    if e.far_test_views:
        test = PathSpec((0.0, 0.0), (2.3, 2.0), (20.0, 160.0), (1.8, 2.0), (0.0, 0.1, 0.2))
    else:
        test = _near_test_path(train, (0.9, 1.2))
    return Layout(scene, train, test)


PRESETS: dict[str, Preset] = {
    p.name: p
    for p in (
        Preset(
            "office",
            "3 tables and 9 chairs in a room; chairs tucked under tables, low training path along one side.",
            Effects(occlusion=True, coverage_imbalance=True, slanted_sun=True),
            _office,
        ),
        Preset(
            "temple",
            "a colonnade of 9 columns under an entablature; trained from the front, tested from far behind.",
            Effects(coverage_imbalance=True, far_test_views=True, slanted_sun=True),
            _temple,
            open_sky=True,
        ),
        Preset(
            "chess",
            "8 pawns (rot_z:inf), 2 rooks (rot_z:4), 2 knights, 2 bishops (rot_z:inf) on a board.",
            Effects(slanted_sun=True),
            _chess,
        ),
        Preset(
            "lighting",
            "6 identical chairs under a low sun, a warm and a cool lamp and a canopy, with cast shadows.",
            Effects(varied_lighting=True, shadows=True, slanted_sun=True),
            _lighting,
        ),
        Preset(
            "tiny",
            "3 crates, 64x48, 8 train + 4 test views: generated in about a second, for tests.",
            Effects(coverage_imbalance=True, slanted_sun=True),
            _tiny,
            res=(64, 48),
            n_train=8,
            n_test=4,
        ),
    )
}


def get_preset(name: str) -> Preset:
    """Look a preset up by name, with a clear error."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of: {', '.join(PRESETS)}")
    return PRESETS[name]
