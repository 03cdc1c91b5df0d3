"""Random repetitive scenes (``splatreplace sim random OUT --seed K``): a distribution, not a preset.

A seed draws a :class:`Recipe`: 1–3 object classes of compatible size, 3–12 copies of each, a layout per class
(row, grid, ring, scattered, or in a row against a wall that stands behind it), how copies are turned (free yaw, quarter turns, aligned), indoor
(walls) or outdoor (open sky), floor and wall materials, colour families, and a set of :class:`Effects` — every
effect the scene simulates is drawn, and nothing else is simulated. The training path always leaves some copies
poorly seen (it covers one side only, or runs low behind occluders, or both); the test views look from high up at
what it missed (from the other side when the path covers one side).

:func:`random_preset` turns a seed into a :class:`~splatreplace_ns.tools.sim.presets.Preset`, so the generator writes
random scenes exactly as it writes the named presets (same files, same ground truth).
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import asdict, dataclass, replace
from typing import Optional

import numpy as np

from splatreplace_ns.tools.sim.cameras import PathSpec, PinholeCamera, intrinsics, pixel_rays, trajectory
from splatreplace_ns.tools.sim.geometry import CLASS_SYMMETRY, class_mesh
from splatreplace_ns.tools.sim.primitives import box, pose
from splatreplace_ns.tools.sim.presets import Effects, Layout, Preset
from splatreplace_ns.tools.sim.render import Renderer
from splatreplace_ns.tools.sim.scene import Instance, Light, Scene, Surface

SUITE_CLASSES: tuple[str, ...] = (
    "chair", "table", "round_table", "stool", "lamp", "vase", "cabinet", "window", "crate", "pillar", "rook", "knight",
)
"""The classes a random scene draws from (``pillar`` is the column)."""
LAYOUTS = ("row", "grid", "ring", "scattered", "wall")
YAWS = ("free", "quarter", "aligned")
WALL_ONLY = ("window",)  # hung on a wall
FLOORS_INDOOR, FLOORS_OUTDOOR, WALLS = ("parquet", "tiles", "concrete", "stone"), ("stone", "concrete", "tiles"), (
    "plaster", "brick")
_MAX_HEIGHT_RATIO = 2.5  # classes in one scene: tallest / shortest, so that none is a few pixels at the suite's size
_WINDOW_SILL = 0.85  # metres above the floor
_FOV_DEG = 65.0


@dataclass(frozen=True)
class Group:
    """The copies of one class."""

    cls: str
    count: int
    layout: str  # one of LAYOUTS
    yaw: str  # one of YAWS ("aligned" on a ring: every copy faces the centre; against a wall: faces the room)


@dataclass(frozen=True)
class Recipe:
    """Everything a seed decides about a random scene before any position is drawn."""

    seed: int
    groups: tuple[Group, ...]
    indoor: bool
    floor: str
    wall: str
    effects: Effects

    def describe(self) -> str:
        """Several lines for a person: classes, layouts, setting, effects on and off."""
        names = list(asdict(self.effects))
        on = set(self.effects.enabled())
        lines = [f"random scene, seed {self.seed}: {'indoor' if self.indoor else 'outdoor'}, floor {self.floor}"
                 + (f", walls {self.wall}" if self.indoor else ", open sky")]
        for g in self.groups:
            lines.append(f"    {g.count} x {g.cls} ({CLASS_SYMMETRY[g.cls]}): {g.layout}, yaw {g.yaw}")
        lines.append(f"    effects on:  {', '.join(n for n in names if n in on) or '(none)'}")
        lines.append(f"    effects off: {', '.join(n for n in names if n not in on) or '(none)'}")
        return "\n".join(lines)

    def as_json(self) -> dict:
        """The recipe as written into transforms.json (``sim.scene``)."""
        return {"indoor": self.indoor, "floor": self.floor, "wall": self.wall if self.indoor else None,
                "groups": [{**asdict(g), "symmetry": CLASS_SYMMETRY[g.cls]} for g in self.groups]}


@functools.lru_cache(maxsize=None)
def class_extent(cls: str) -> tuple[float, float, float, float]:
    """(bounding radius about z, height, back (−min x), front (max x)) of a class mesh in its object frame."""
    v = np.asarray(class_mesh(cls).vertices)
    return (float(np.hypot(v[:, 0], v[:, 1]).max()), float(v[:, 2].max()), float(-v[:, 0].min()), float(v[:, 0].max()))


def _standing_height(cls: str) -> float:
    """Height of the class's top above the floor as placed (windows hang above a sill)."""
    return class_extent(cls)[1] + (_WINDOW_SILL if cls in WALL_ONLY else 0.0)


# ----------------------------------------------------------------------------- drawing a recipe


def draw_recipe(seed: int) -> Recipe:
    """The recipe of random scene ``seed`` (stream 10 of the seed; the layout draws from stream 0)."""
    rng = np.random.default_rng([seed, 10])
    indoor = bool(rng.random() < 0.65)
    n_classes = int(rng.choice([1, 2, 3], p=[0.35, 0.4, 0.25]))
    pool = list(SUITE_CLASSES)
    classes: list[str] = []
    while len(classes) < n_classes:
        fits = [c for c in pool if c not in classes and all(
            max(_standing_height(c), _standing_height(o)) / min(_standing_height(c), _standing_height(o))
            <= _MAX_HEIGHT_RATIO for o in classes)]
        if not fits:
            break
        classes.append(str(rng.choice(fits)))
    groups = []
    for cls in classes:
        count = 3 + int(9.0 * rng.random() ** 1.6)  # 3..12, fewer more often
        if cls in WALL_ONLY:
            layout = "wall"
        else:
            weights = np.array([3.0, 2.0 if count >= 4 else 0.0, 2.0 if count >= 4 else 0.0, 2.0, 1.5])
            if cls == "cabinet":
                weights[4] = 6.0
            layout = str(rng.choice(LAYOUTS, p=weights / weights.sum()))
        yaw = "aligned" if layout == "wall" else str(rng.choice(YAWS, p=[0.35, 0.35, 0.3]))
        groups.append(Group(cls, count, layout, yaw))
    imbalance = bool(rng.random() < 0.6)
    occlusion = bool(rng.random() < 0.5)
    if not (imbalance or occlusion):  # the capture always leaves something poorly seen
        imbalance, occlusion = (True, False) if rng.random() < 0.5 else (False, True)
    slanted = bool(rng.random() < 0.6)
    effects = Effects(
        occlusion=occlusion,
        coverage_imbalance=imbalance,
        far_test_views=True,
        varied_lighting=bool(rng.random() < 0.3),
        shadows=bool(rng.random() < 0.35),
        slanted_sun=slanted,
        per_copy_appearance=bool(rng.random() < 0.35),
    )
    floor = str(rng.choice(FLOORS_INDOOR if indoor else FLOORS_OUTDOOR))
    wall = str(rng.choice(WALLS))
    return Recipe(seed, tuple(groups), indoor, floor, wall, effects)


# ----------------------------------------------------------------------------- layout


def _group_positions(g: Group, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Copy positions (count, 2) around the group's own origin and their yaw (count,), for a floor layout
    (a wall group is laid out as a row here and turned to its wall later)."""
    radius = class_extent(g.cls)[0]
    spacing = 2.0 * radius + radius * rng.uniform(0.3, 0.9) + 0.12
    n = g.count
    if g.layout in ("row", "wall"):
        rows = 2 if g.layout == "row" and n >= 7 and rng.random() < 0.5 else 1
        cols = -(-n // rows)
        k = np.arange(n)
        xy = np.stack([(k % cols - (cols - 1) / 2) * spacing, (k // cols - (rows - 1) / 2) * spacing * 1.2], 1)
    elif g.layout == "grid":
        cols = int(math.ceil(math.sqrt(n)))
        k = np.arange(n)
        xy = np.stack([(k % cols - (cols - 1) / 2) * spacing, (k // cols - (-(-n // cols) - 1) / 2) * spacing], 1)
    elif g.layout == "ring":
        ring = max(spacing / (2.0 * math.sin(math.pi / n)), spacing)
        angle = rng.uniform(0.0, 2 * math.pi) + 2 * math.pi * np.arange(n) / n
        xy = ring * np.stack([np.cos(angle), np.sin(angle)], 1)
    else:  # scattered: dart throwing with a minimum distance, the square grown until all fit
        side = spacing * math.sqrt(n) * 1.4
        while True:
            pts: list[np.ndarray] = []
            for _ in range(60 * n):
                p = rng.uniform(-side / 2, side / 2, 2)
                if all(np.hypot(*(p - q)) >= spacing for q in pts):
                    pts.append(p)
                    if len(pts) == n:
                        break
            if len(pts) == n:
                xy = np.stack(pts)
                break
            side *= 1.15
    xy = xy + rng.normal(0.0, 0.02, xy.shape)
    if g.yaw == "free":
        yaw = rng.uniform(0.0, 2 * math.pi, n)
    elif g.yaw == "quarter":
        yaw = rng.uniform(0.0, 2 * math.pi) + (math.pi / 2) * rng.integers(0, 4, n) + rng.normal(0.0, 0.02, n)
    elif g.layout == "ring":  # aligned on a ring: every copy faces the centre
        yaw = np.arctan2(-xy[:, 1], -xy[:, 0]) + rng.normal(0.0, 0.03, n)
    else:
        yaw = rng.uniform(0.0, 2 * math.pi) + rng.normal(0.0, 0.03, n)
    return xy, yaw


@dataclass
class Block:
    """One group laid out around its own origin: copies (xy, yaw, z) and, against a wall, the wall behind them."""

    cls: str
    xy: np.ndarray  # (n, 2)
    yaw: np.ndarray  # (n,)
    z: float
    walls: list  # open3d meshes in the block's frame
    lo: np.ndarray  # (2,) bounding box of copies and walls
    hi: np.ndarray
    facing: Optional[float] = None  # against a wall: the direction the copies face (radians about z)

    def moved(self, angle: float, offset: np.ndarray) -> "Block":
        """The block turned by ``angle`` about its origin, then shifted by ``offset`` (2,)."""
        rot = pose(angle)[:3, :3]
        xy = self.xy @ rot[:2, :2].T + offset
        walls = []
        for mesh in self.walls:
            m = copy.deepcopy(mesh).rotate(rot, center=(0.0, 0.0, 0.0))
            walls.append(m.translate((float(offset[0]), float(offset[1]), 0.0)))
        corners = np.array([[self.lo[0], self.lo[1]], [self.lo[0], self.hi[1]], [self.hi[0], self.lo[1]],
                            [self.hi[0], self.hi[1]]]) @ rot[:2, :2].T + offset
        facing = None if self.facing is None else self.facing + angle
        return Block(self.cls, xy, self.yaw + angle, self.z, walls, corners.min(0), corners.max(0), facing)


def _block(g: Group, rng: np.random.Generator) -> Block:
    """A group's block: its copies laid out, and for a wall layout the row faces +y with a wall behind it."""
    xy, yaw = _group_positions(g, rng)
    radius, height, back, _ = class_extent(g.cls)
    z = _WINDOW_SILL if g.cls in WALL_ONLY else 0.0
    walls = []
    lo, hi = xy.min(0) - radius, xy.max(0) + radius
    facing = None
    if g.layout == "wall":
        facing = math.pi / 2
        yaw = np.full(len(xy), math.pi / 2) + (0.0 if g.cls in WALL_ONLY else rng.normal(0.0, 0.02, len(xy)))
        xy[:, 1] = 0.0
        length = float(np.ptp(xy[:, 0])) + 2 * radius + 0.6
        wall_height = max(2.4, z + height + 0.5)
        thickness = 0.12
        walls.append(box((length, thickness, wall_height), (0.0, -(back + 0.005 + thickness / 2), wall_height / 2)))
        lo = np.array([-length / 2, -(back + 0.005 + thickness)])
        hi = np.array([length / 2, max(radius, 0.5)])
    return Block(g.cls, xy, yaw, z, walls, lo, hi, facing)


def _pack(blocks: list[Block], rng: np.random.Generator) -> list[Block]:
    """The blocks side by side without overlap: each next block beside the ones before (along x or y, turned by a
    quarter turn at random when it stands against a wall), then everything centred on the origin."""
    placed: list[Block] = []
    lo = hi = None
    for b in blocks:
        b = b.moved(float(rng.integers(0, 4)) * math.pi / 2 if b.walls else 0.0, np.zeros(2))
        off = np.zeros(2)
        if lo is not None:
            axis = int(rng.integers(0, 2))
            off[axis] = hi[axis] + 0.5 - b.lo[axis]
            off[1 - axis] = 0.5 * (lo[1 - axis] + hi[1 - axis]) - 0.5 * (b.lo[1 - axis] + b.hi[1 - axis])
        b = b.moved(0.0, off)
        placed.append(b)
        lo = b.lo if lo is None else np.minimum(lo, b.lo)
        hi = b.hi if hi is None else np.maximum(hi, b.hi)
    centre = 0.5 * (lo + hi)
    return [b.moved(0.0, -centre) for b in placed]


def _colour_family(rng: np.random.Generator, permute: bool) -> np.ndarray:
    """(3, 3) colour map: a channel permutation (sometimes), per-channel gains and some desaturation."""
    perm = rng.permutation(3) if permute and rng.random() < 0.5 else np.arange(3)
    m = np.eye(3)[perm] * rng.uniform(0.8, 1.15, 3)[:, None]
    grey = rng.uniform(0.0, 0.35)
    return (1.0 - grey) * m + grey * np.full((3, 3), 1.0 / 3.0) @ m


def _walls(x0: float, x1: float, y0: float, y1: float, height: float, material: str, colour: np.ndarray) -> list[Surface]:
    """Four 0.1 m walls whose inner faces enclose [x0, x1] × [y0, y1] (casting no shadows: the room has no roof)."""
    t, cx, cy, wx, wy = 0.1, 0.5 * (x0 + x1), 0.5 * (y0 + y1), x1 - x0, y1 - y0
    sizes_centres = [((t, wy + 2 * t, height), (x1 + t / 2, cy, height / 2)),
                     ((t, wy + 2 * t, height), (x0 - t / 2, cy, height / 2)),
                     ((wx + 2 * t, t, height), (cx, y1 + t / 2, height / 2)),
                     ((wx + 2 * t, t, height), (cx, y0 - t / 2, height / 2))]
    return [Surface(box(size, centre), material, colour, casts_shadows=False) for size, centre in sizes_centres]


def _occluders(copies: list[tuple[np.ndarray, str, np.ndarray]], count: int, rng: np.random.Generator,
               colour: np.ndarray) -> list[Surface]:
    """Up to ``count`` low partition screens, each just in front of one copy, on the side it is seen from, where
    the screen clears every other copy.

    Args:
        copies: (xy (2,), class, direction (2,) unit: the side of the copy the training path sees) per copy.
    """
    out: list[Surface] = []
    for i in rng.permutation(len(copies)):
        if len(out) == count:
            break
        xy, cls, d = copies[i]
        radius, height = class_extent(cls)[:2]
        centre = xy + d * (radius + 0.2)
        half_width = 1.2 * radius
        side = np.array([-d[1], d[0]])
        clear = all(
            np.linalg.norm(xy_o - (centre + np.clip((xy_o - centre) @ side, -half_width, half_width) * side))
            > class_extent(c_o)[0] + 0.05
            for j, (xy_o, c_o, _) in enumerate(copies) if j != i
        )
        if not clear:
            continue
        h = max(0.35, rng.uniform(0.55, 0.85) * height)
        panel = box((0.06, 2 * half_width, h), (0.0, 0.0, h / 2))
        panel.rotate(pose(math.atan2(d[1], d[0]))[:3, :3], center=(0.0, 0.0, 0.0))
        panel.translate((centre[0], centre[1], 0.0))
        out.append(Surface(panel, "screen", colour))
    return out


def _paths(recipe: Recipe, half: np.ndarray, height: float, facing: Optional[float], rng: np.random.Generator
           ) -> tuple[PathSpec, PathSpec]:
    """Training and test paths around a layout of half-size ``half`` (2,) whose tallest object is ``height``.

    Covering one side only, the training path sees the layout from one side and the test path looks from high up
    on the other; when copies stand against a wall facing ``facing`` (radians), the two sides are the two flanks
    in front of that wall (behind it there is nothing to see)."""
    e = recipe.effects
    margin = 1.0 * height + 0.8 + 0.15 * float(half.max())
    radii = (float(half[0] + margin), float(half[1] + margin))
    target = (0.0, 0.0, 0.4 * height)
    follow = (float(rng.uniform(0.25, 0.45)), 0.0)
    low = (0.75 * height + 0.25, 1.05 * height + 0.45) if e.occlusion else (0.9 * height + 0.4, 1.4 * height + 0.8)
    high = (1.8 * height + 0.9, 2.3 * height + 1.3)
    if e.coverage_imbalance:
        if facing is None:
            width, middle = rng.uniform(140.0, 200.0), rng.uniform(0.0, 360.0)
            test_arc = (middle + 120.0, middle + 240.0)
        else:
            side = float(rng.choice([-1.0, 1.0]))
            width, middle = rng.uniform(100.0, 160.0), math.degrees(facing) + side * 45.0
            test_arc = tuple(sorted((math.degrees(facing) - side * 85.0, math.degrees(facing) - side * 5.0)))
        train = PathSpec((0.0, 0.0), radii, (middle - width / 2, middle + width / 2), low, target, follow)
        test = PathSpec((0.0, 0.0), (radii[0] * 1.05, radii[1] * 1.05), test_arc, high, target, (0.3, 0.0))
    else:
        start = rng.uniform(0.0, 360.0)
        train = PathSpec((0.0, 0.0), radii, (start, start + 360.0), low, target, follow)
        test = PathSpec((0.0, 0.0), (radii[0] * 1.05, radii[1] * 1.05), (start, start + 360.0), high, target, (0.3, 0.0))
    return train, test


def _visible_pixels(scene: Scene, path: PathSpec, rng: np.random.Generator) -> dict[int, int]:
    """Pixels of each instance over 24 small views along a path (centre rays only): a cheap check that the
    capture sees every copy. {instance id: pixels}."""
    renderer = Renderer(scene, supersample=1)
    counts = {i.id: 0 for i in scene.instances}
    w, h = 64, 48
    for c2w in trajectory(path, 24, rng):
        cam = PinholeCamera(c2w, *intrinsics(w, h, _FOV_DEG), w, h)
        d = pixel_rays(cam, np.array([[0.5, 0.5]]))[1].reshape(-1, 3)
        ids, n = np.unique(renderer.instance_ids(renderer.trace(cam.center, d)), return_counts=True)
        for k, c in zip(ids.tolist(), n.tolist()):
            if k in counts:
                counts[k] += c
    return counts


def build_layout(recipe: Recipe, rng: np.random.Generator, attempts: int = 12) -> Layout:
    """Positions, environment, lights and paths of a recipe; redrawn (up to ``attempts`` times, from the same
    generator) until the training path sees every copy."""
    for _ in range(attempts):
        layout = _draw_layout(recipe, rng)
        seen = _visible_pixels(layout.scene, layout.train_path, np.random.default_rng([recipe.seed, 11]))
        if min(seen.values()) >= 6:
            return layout
    return layout


def _draw_layout(recipe: Recipe, rng: np.random.Generator) -> Layout:
    e = recipe.effects
    class_colour = {g.cls: _colour_family(rng, permute=True) for g in recipe.groups}
    blocks = _pack([_block(g, rng) for g in recipe.groups], rng)
    half = np.maximum(np.maximum(np.abs(np.stack([b.lo for b in blocks])).max(0),
                                 np.abs(np.stack([b.hi for b in blocks])).max(0)), 0.6)
    height = max(max(_standing_height(g.cls) for g in recipe.groups), 0.6)
    facing = next((b.facing for b in blocks if b.facing is not None), None)
    train, test = _paths(recipe, half, height, facing, rng)
    env_colour = np.diag(rng.uniform(0.85, 1.1, 3))

    instances: list[Instance] = []
    for b in blocks:
        for xy, yaw in zip(b.xy, b.yaw):
            colour = class_colour[b.cls]
            if e.per_copy_appearance:
                colour = np.diag(np.clip(1.0 + rng.normal(0.0, 0.12, 3), 0.75, 1.25)) @ colour
            instances.append(Instance(len(instances) + 1, b.cls, pose(float(yaw), (float(xy[0]), float(xy[1]), b.z)),
                                      colour))

    # outdoors the floor ends where depth would no longer fit the 16-bit millimetre PNGs (65 m); beyond it, sky
    reach = np.array([max(train.radii[0], test.radii[0]), max(train.radii[1], test.radii[1])]) + 0.5
    floor_half = min(float(reach.max()) + 20.0, 38.0)
    surfaces = [Surface(box((2 * floor_half, 2 * floor_half, 0.1), (0.0, 0.0, -0.05)), recipe.floor, env_colour)]
    surfaces += [Surface(mesh, recipe.wall, env_colour) for b in blocks for mesh in b.walls]
    if recipe.indoor:
        surfaces += _walls(-reach[0], reach[0], -reach[1], reach[1], max(2.8, test.height[1] + 0.5), recipe.wall,
                           env_colour)
    if e.occlusion:  # a screen on the side the training path sees a copy from
        middle = math.radians(0.5 * sum(train.azimuth_deg))
        towards_path = np.array([math.cos(middle), math.sin(middle)])
        copies = []
        for b in blocks:
            for xy in b.xy:
                if b.facing is not None:
                    d = np.array([math.cos(b.facing), math.sin(b.facing)])
                elif e.coverage_imbalance:
                    d = towards_path
                else:  # a full loop: outward from the middle of the scene through the copy
                    d = xy / np.linalg.norm(xy) if np.linalg.norm(xy) > 1e-6 else np.array([1.0, 0.0])
                copies.append((xy, b.cls, d))
        surfaces += _occluders(copies, max(2, min(len(copies) // 2, 5)), rng, env_colour)

    if e.slanted_sun:
        elevation, azimuth = math.radians(rng.uniform(30.0, 55.0)), rng.uniform(0.0, 2 * math.pi)
        sun = (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation))
    else:
        sun = (0.0, 0.0, 1.0)
    lights = [Light("directional", sun, tuple(float(c) for c in rng.uniform(0.85, 1.05) * np.array([0.8, 0.77, 0.7])))]
    if e.varied_lighting:
        for i in rng.permutation(len(instances))[: int(rng.integers(1, 4))]:
            inst = instances[i]
            radius, h = class_extent(inst.cls)[:2]
            angle = rng.uniform(0.0, 2 * math.pi)
            at = inst.pose[:3, 3] + np.array([(radius + 0.35) * math.cos(angle), (radius + 0.35) * math.sin(angle),
                                              0.8 * h])
            hue = np.eye(3)[int(rng.integers(0, 3))] * 1.6 + 0.25
            lights.append(Light("point", tuple(float(c) for c in at), tuple(float(c) for c in hue), 1.0))
    scene = Scene(
        instances=instances,
        surfaces=surfaces,
        lights=lights,
        ambient_sky=tuple(float(c) for c in rng.uniform(0.3, 0.38) * np.array([1.0, 1.03, 1.1])),
        ambient_ground=tuple(float(c) for c in rng.uniform(0.14, 0.2) * np.array([1.0, 0.92, 0.8])),
        shadows=e.shadows,
    )
    return Layout(scene, train, test)


def random_preset(seed: int) -> Preset:
    """Random scene ``seed`` as a preset: 128x96, 48 training and 8 test views by default (the suite's size)."""
    recipe = draw_recipe(seed)
    summary = "; ".join(f"{g.count} {g.cls} ({g.layout}, yaw {g.yaw})" for g in recipe.groups)
    return Preset(
        name="random",
        summary=f"seed {seed}: {summary}",
        effects=recipe.effects,
        build=lambda effects, rng: build_layout(replace(recipe, effects=effects), rng),
        res=(128, 96),
        n_train=48,
        n_test=8,
        fov_deg=_FOV_DEG,
        details=recipe.as_json(),
        open_sky=not recipe.indoor,
    )
