"""Exporting the replaced scene: a standard 3DGS PLY and a compact instanced file.

The PLY is written by nerfstudio's own ``ns-export gaussian-splat`` exporter: loading a run for inference
bakes the composed scene into plain Gaussians (``SplatReplaceModel.bake_replaced_scene``), so any 3DGS
viewer shows the replaced scene.

The instanced file (``.npz``) stores what the method actually learned: the background Gaussians, one
template per class in template space, and per instance its pose and SH offsets (float16). Loading it
with :func:`load_instanced` and :meth:`InstancedScene.compose` gives the same Gaussians as the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch

from splatreplace_ns.template.compose import ComposedScene, compose_scene, instance_poses

FORMAT = "splatreplace-instanced-v1"
PLY_FLOATS_PER_GAUSSIAN = 3 + 3 + 3 + 1 + 3 + 4  # xyz, normals, f_dc, opacity, scale, rot (+ f_rest)


def ply_bytes(num_gaussians: int, sh_coeffs: int) -> int:
    """Approximate size of a standard 3DGS PLY (float32 per property, header ignored)."""
    return 4 * num_gaussians * (PLY_FLOATS_PER_GAUSSIAN + 3 * (sh_coeffs - 1))


@dataclass
class InstancedScene:
    """Contents of an instanced file (numpy arrays, see :func:`save_instanced`)."""

    arrays: Dict[str, np.ndarray]

    @property
    def num_stored(self) -> int:
        return int(self.arrays["means"].shape[0])

    def compose(self) -> ComposedScene:
        """The replaced scene in world coordinates (float32 torch tensors on the CPU)."""
        a = {k: torch.from_numpy(np.asarray(v)) for k, v in self.arrays.items() if k not in ("format", "class_names")}
        n, K = a["means"].shape[0], a["sh"].shape[1]
        ids, cls, slot = a["instance_ids"].long(), a["instance_class"].long(), a["instance_slot"].long()
        gauss_class = a["gauss_class"].long()
        # scatter the per-class offset blocks back to [N, S, K, 3]
        n_slots = int(slot.max()) + 1 if len(slot) else 0
        offsets = torch.zeros(n, n_slots, K, 3)
        for i in range(len(ids)):
            rows = torch.nonzero(gauss_class == cls[i]).squeeze(-1)
            offsets[rows, slot[i]] = a[f"offsets_{int(ids[i])}"].float()
        q, R, t = instance_poses(a["pose_q"].float(), a["pose_t"].float(), torch.zeros(len(ids), 6))
        return compose_scene(
            a["means"].float(), a["quats"].float(), a["scales"].float(), a["opacities"].float(), a["sh"].float(),
            offsets, gauss_class, cls, slot, ids, q, R, t, lam=float(a["lam"]),
        )


@torch.no_grad()
def instanced_arrays(model) -> Dict[str, np.ndarray]:
    """The model's templates, background and per-instance references as numpy arrays.

    Args:
        model: a ``SplatReplaceModel`` in the fine-tuning stage (``has_templates``).
    """
    if not model.has_templates:
        raise ValueError("the run has no shared templates (it stopped before registration, or no instance registered)")
    table = model.instance_table
    q, _, t = instance_poses(table.q0.to(model.means), table.t0.to(model.means), model.instance_pose_delta.detach())
    gauss_class = model.gauss_params["template_class"][:, 0].round().long()
    offsets = model.gauss_params["sh_offsets"]
    out = {
        "format": np.array(FORMAT),
        "means": model.means, "quats": model.quats, "scales": model.scales, "opacities": model.opacities,
        "sh": torch.cat((model.features_dc[:, None], model.features_rest), dim=1),
        "gauss_class": gauss_class.to(torch.int16),
        "instance_ids": table.ids, "instance_class": table.class_index, "instance_slot": table.slot,
        "pose_q": q, "pose_t": t, "lam": torch.tensor(model.config.template_mix),
        "class_names": np.array(table.classes),
    }
    for i in range(len(table.ids)):
        rows = gauss_class == table.class_index[i].item()
        out[f"offsets_{int(table.ids[i])}"] = offsets[rows, int(table.slot[i])].to(torch.float16)
    return {k: (v.detach().cpu().numpy() if torch.is_tensor(v) else v) for k, v in out.items()}


def save_instanced(path: Path, arrays: Dict[str, np.ndarray]) -> int:
    """Writes the instanced file (uncompressed npz) and returns its size in bytes."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path.stat().st_size


def load_instanced(path: Path) -> InstancedScene:
    """Reads a file written by :func:`save_instanced`; a clear error when it is not one."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such instanced file")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (ValueError, OSError) as err:
        raise ValueError(f"{path}: not an instanced file written by splatreplace export ({err})") from err
    if str(arrays.get("format", "")) != FORMAT:
        raise ValueError(f"{path}: format {arrays.get('format')!r}, expected {FORMAT!r}")
    return InstancedScene(arrays)


def size_report(model, ply_path: Path, instanced_path: Path) -> List[Dict]:
    """Rows (what, Gaussians, bytes) comparing the exports with the base scene before replacement."""
    K = model.features_rest.shape[1] + 1
    base = int(getattr(model, "base_gaussians", 0) or 0)
    composed = int(len(model.composed_scene().means)) if model.has_templates else model.num_points
    rows = []
    if base:
        rows.append({"what": "base scene (before replacement, as PLY)", "gaussians": base, "bytes": ply_bytes(base, K)})
    rows.append({"what": f"replaced scene PLY ({Path(ply_path).name})", "gaussians": composed,
                 "bytes": Path(ply_path).stat().st_size if Path(ply_path).exists() else ply_bytes(composed, K)})
    rows.append({"what": f"instanced file ({Path(instanced_path).name})", "gaussians": model.num_points,
                 "bytes": Path(instanced_path).stat().st_size})
    return rows
