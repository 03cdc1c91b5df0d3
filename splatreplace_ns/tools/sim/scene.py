"""Scene description: instances with ground-truth poses, environment surfaces, lights.

Also reads ground-truth geometry back from a written dataset (:func:`load_scene_meshes`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import open3d as o3d

from splatreplace_ns.tools.sim.geometry import CLASS_SYMMETRY, CLASSES, class_mesh


@dataclass(frozen=True)
class Instance:
    """One repetition of an object class."""

    id: int  # > 0, the value written in the instance masks
    cls: str
    pose: np.ndarray  # (4, 4) object→world, rigid
    colour: Optional[np.ndarray] = None
    """(3, 3) linear map applied to the class material's albedo (``albedo @ colour.T``); None = as the material is.
    Copies of a class share it unless the scene declares per-copy appearance."""

    @property
    def symmetry(self) -> str:
        return CLASS_SYMMETRY[self.cls]

    def world_mesh(self) -> o3d.geometry.TriangleMesh:
        """The class mesh placed in the world by the ground-truth pose."""
        return class_mesh(self.cls).transform(self.pose)


@dataclass(frozen=True)
class Surface:
    """A piece of background (floor, wall, step, beam); its material is evaluated in world coordinates."""

    mesh: o3d.geometry.TriangleMesh  # world frame
    material: str
    colour: Optional[np.ndarray] = None
    """(3, 3) linear map applied to the material's albedo; None = as the material is."""
    casts_shadows: bool = True
    """False for a room's enclosing walls: their shadow would cover the room under a slanted sun (a room with no
    roof), which no scene asks for."""


@dataclass(frozen=True)
class Light:
    """A directional light (``vector`` = direction towards the light) or a point light (``vector`` = position).

    Point lights fall off as ``1 / (1 + (d / falloff)²)``.
    """

    kind: Literal["directional", "point"]
    vector: tuple[float, float, float]
    colour: tuple[float, float, float]
    falloff: float = 1.0


@dataclass
class Scene:
    """Everything the renderer needs."""

    instances: list[Instance]
    surfaces: list[Surface]
    lights: list[Light]
    ambient_sky: tuple[float, float, float] = (0.3, 0.32, 0.36)  # ambient from above (normal +z)
    ambient_ground: tuple[float, float, float] = (0.16, 0.14, 0.12)  # ambient from below (normal -z)
    shadows: bool = False
    notes: dict = field(default_factory=dict)


def instances_json(instances: list[Instance]) -> list[dict]:
    """The ``instances`` list of transforms.json: id, class, object→world matrix, symmetry, and size (the bounding-box
    diagonal of the class's mesh in the object's frame, before the pose's scale)."""
    return [
        {"id": int(i.id), "class": i.cls, "transform_matrix": np.asarray(i.pose).tolist(), "symmetry": i.symmetry,
         "size": class_size(i.cls)}
        for i in instances
    ]


def class_size(cls: str) -> Optional[float]:
    """Bounding-box diagonal of a class's mesh in its object frame; None for a class the simulator does not know."""
    if cls not in CLASSES:
        return None
    mesh = class_mesh(cls)
    return float(np.linalg.norm(mesh.get_max_bound() - mesh.get_min_bound()))


def load_scene_meshes(transforms_json: str | Path) -> dict[int, o3d.geometry.TriangleMesh]:
    """Ground-truth geometry of every instance of a written dataset.

    Args:
        transforms_json: path to a transforms.json with an ``instances`` list (or its directory).
    Returns:
        {instance id: open3d legacy TriangleMesh in the world frame of the dataset}.
    """
    path = Path(transforms_json)
    if path.is_dir():
        path = path / "transforms.json"
    meta = json.loads(path.read_text())
    if "instances" not in meta:
        raise ValueError(f"{path}: no 'instances' list")
    out = {}
    for inst in meta["instances"]:
        out[int(inst["id"])] = class_mesh(inst["class"]).transform(
            np.asarray(inst["transform_matrix"], dtype=np.float64)
        )
    return out
