"""Synthetic repetitive scenes with ground truth (``splatreplace sim``).

Scenes modelled on the paper's synthetic set (§5.1), ray-cast on the CPU with open3d. A dataset folder
holds (world frame: z up, ground plane z = 0, metres):

- ``transforms.json``: nerfstudio format, PINHOLE camera, OpenGL camera→world poses; per frame
  ``instance_mask_path`` (16-bit PNG, 0 = background, k = instance id) and ``depth_file_path`` (16-bit PNG,
  z-depth in millimetres, 0 = no hit, ``depth_unit_scale_factor`` 0.001); ``train_filenames``,
  ``val_filenames`` (= test) and ``test_filenames``; ``instances`` (id, class, object→world
  ``transform_matrix``, symmetry about the object's z axis); ``sim`` (preset, seed, effects, statistics).
- ``clicks.json``: one ``{"file_path", "xy": [u, v], "class", "id"}`` per instance; (u, v) = (column, row) of
  the middle of the instance (well inside its outline) in the training view that shows it best.
- ``points3d.ply``: SfM-like coloured, noisy surface samples from the training views.
- ``images/``, ``masks/``, ``depth/`` and ``contact_sheet.png``.

See :func:`make_scene`, :data:`PRESETS` and :func:`load_scene_meshes` / :func:`class_mesh` for geometry.
"""

from splatreplace_ns.tools.sim.cli import SimCommand
from splatreplace_ns.tools.sim.generate import is_current_scene, make_scene, parse_res
from splatreplace_ns.tools.sim.geometry import CLASS_SYMMETRY, CLASSES, class_mesh
from splatreplace_ns.tools.sim.presets import PRESETS, Effects, Preset
from splatreplace_ns.tools.sim.scene import load_scene_meshes

__all__ = [
    "CLASSES",
    "CLASS_SYMMETRY",
    "PRESETS",
    "Effects",
    "Preset",
    "SimCommand",
    "class_mesh",
    "is_current_scene",
    "load_scene_meshes",
    "make_scene",
    "parse_res",
]
