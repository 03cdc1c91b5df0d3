"""Exporting the replaced scene: a standard 3DGS PLY and a compact instanced file.

The PLY is written by nerfstudio's own ``ns-export gaussian-splat`` exporter: loading a run for inference
bakes the composed scene into plain Gaussians (``SplatReplaceModel.bake_replaced_scene``), so any 3DGS
viewer shows the replaced scene.

The instanced file (``.npz``) stores what the method actually learned: the background Gaussians, one
template per class in template space, and per instance its pose, its SH offsets and, where the run learned
them (``--pipeline.model.copy-colour-gain``), its colour gain per channel. Loading it with
:func:`load_instanced` and :meth:`InstancedScene.compose` gives the same Gaussians as the model, up to a
colour difference the file bounds (below).

Per-instance offsets are what instancing costs: one set of SH coefficients per template Gaussian and
instance, more bytes than the instances' own Gaussians saved on the office scene when stored densely. The L1
penalty of fine-tuning leaves most of them near zero, so each instance stores a bitmask of the offsets larger
than ε and those values (float16). ε is set from a colour tolerance: an offset o changes a Gaussian's colour by
(1 − λ) · Σ_k Y_k(d) o_k, so zeroing every |o_k| ≤ ε changes it by at most (1 − λ) · ε · max_d Σ_k |Y_k(d)|;
a rendered pixel (a convex combination of clamped colours) by no more.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch

from splatreplace_ns.template.compose import ComposedScene, compose_scene, instance_poses

FORMAT = "splatreplace-instanced-v2"
READABLE_FORMATS = ("splatreplace-instanced-v1", FORMAT)  # v1: dense float16 offsets
DEFAULT_COLOUR_TOLERANCE = 0.5 / 255
PLY_FLOATS_PER_GAUSSIAN = 3 + 3 + 3 + 1 + 3 + 4  # xyz, normals, f_dc, opacity, scale, rot (+ f_rest)


def ply_bytes(num_gaussians: int, sh_coeffs: int) -> int:
    """Approximate size of a standard 3DGS PLY (float32 per property, header ignored)."""
    return 4 * num_gaussians * (PLY_FLOATS_PER_GAUSSIAN + 3 * (sh_coeffs - 1))


def sh_basis_abs_bound(num_coeffs: int, samples: int = 20000) -> float:
    """max over view directions d of Σ_k |Y_k(d)|, the first ``num_coeffs`` real SH bases as the renderer
    evaluates them (sampled on a Fibonacci sphere, plus 5 % for the directions between samples)."""
    from splatreplace_ns.render.sh import sh_basis
    from splatreplace_ns.render.transform import sample_directions

    degree = int(round(num_coeffs**0.5)) - 1
    return 1.05 * float(sh_basis(degree, sample_directions(samples))[:, :num_coeffs].abs().sum(dim=1).max())


def offset_epsilon(lam: float, num_coeffs: int, colour_tolerance: float = DEFAULT_COLOUR_TOLERANCE) -> float:
    """Largest |offset| that may be stored as zero so that no colour changes by more than ``colour_tolerance``
    (``inf`` for λ ≥ 1, where offsets do not reach the colour; 0 for a tolerance of 0)."""
    if lam >= 1.0:
        return float("inf")
    if colour_tolerance <= 0.0:
        return 0.0
    return float(colour_tolerance / ((1.0 - lam) * sh_basis_abs_bound(num_coeffs)))


def pack_offsets(offsets: np.ndarray, epsilon: float) -> tuple[np.ndarray, np.ndarray]:
    """Sparse form of one instance's offsets.

    Args:
        offsets: [n, K, 3] float.
        epsilon: entries with |o| ≤ epsilon are dropped (stored as zero).
    Returns:
        (bits [ceil(n·K·3 / 8)] uint8: bitmask of the kept entries in C order, values [m] float16: the kept entries).
    """
    flat = np.asarray(offsets, dtype=np.float32).reshape(-1)
    keep = np.abs(flat) > epsilon
    return np.packbits(keep), flat[keep].astype(np.float16)


def unpack_offsets(bits: np.ndarray, values: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Inverse of :func:`pack_offsets`: [*shape] float32 with the dropped entries zero."""
    count = int(np.prod(shape))
    keep = np.unpackbits(np.asarray(bits, dtype=np.uint8), count=count).astype(bool)
    if int(keep.sum()) != len(values):
        raise ValueError(f"offset bitmask keeps {int(keep.sum())} entries but {len(values)} values are stored")
    out = np.zeros(count, dtype=np.float32)
    out[keep] = np.asarray(values, dtype=np.float32)
    return out.reshape(shape)


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
            offsets[rows, slot[i]] = self.instance_offsets(int(ids[i]), len(rows), K)
        q, R, t = instance_poses(a["pose_q"].float(), a["pose_t"].float(), torch.zeros(len(ids), 6))
        gain = a.get("colour_gain")  # absent: the run learned no per-copy colour gain
        if "class_shading" in a:
            raise ValueError("this file holds a shading in world coordinates (class_shading), an option this version "
                             "no longer has; export the run again with the version that trained it")
        return compose_scene(
            a["means"].float(), a["quats"].float(), a["scales"].float(), a["opacities"].float(), a["sh"].float(),
            offsets, gauss_class, cls, slot, ids, q, R, t, lam=float(a["lam"]),
            colour_gain=None if gain is None else gain.float(),
        )

    def instance_offsets(self, instance_id: int, rows: int, num_coeffs: int) -> torch.Tensor:
        """[rows, K, 3] float32 SH offsets of one instance (dense in v1 files, bitmask + values in v2)."""
        dense = self.arrays.get(f"offsets_{instance_id}")
        if dense is not None:
            return torch.from_numpy(np.asarray(dense, dtype=np.float32))
        return torch.from_numpy(unpack_offsets(self.arrays[f"offsets_bits_{instance_id}"],
                                               self.arrays[f"offsets_values_{instance_id}"], (rows, num_coeffs, 3)))


@torch.no_grad()
def instanced_arrays(model, colour_tolerance: float = DEFAULT_COLOUR_TOLERANCE) -> Dict[str, np.ndarray]:
    """The model's templates, background and per-instance references as numpy arrays.

    Args:
        model: a ``SplatReplaceModel`` in the fine-tuning stage (``has_templates``).
        colour_tolerance: largest colour change (RGB in [0, 1]) that dropping small offsets may cause
            (:func:`offset_epsilon`); 0 keeps every offset.
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
    if model.config.copy_colour_gain:
        out["colour_gain"] = model.instance_colour_gain  # [I, 3] natural log per channel, in the table's order
    epsilon = offset_epsilon(model.config.template_mix, offsets.shape[2], colour_tolerance)
    if "colour_gain" in out and len(table.ids):  # a gain scales a dropped offset's colour change too
        epsilon /= max(float(torch.exp(model.instance_colour_gain.detach()).max()), 1.0)
    out["offsets_epsilon"] = np.float32(min(epsilon, np.finfo(np.float32).max))
    for i in range(len(table.ids)):
        rows = gauss_class == table.class_index[i].item()
        bits, values = pack_offsets(offsets[rows, int(table.slot[i])].detach().cpu().numpy(), epsilon)
        out[f"offsets_bits_{int(table.ids[i])}"], out[f"offsets_values_{int(table.ids[i])}"] = bits, values
    return {k: (v.detach().cpu().numpy() if torch.is_tensor(v) else v) for k, v in out.items()}


def offset_counts(arrays: Dict[str, np.ndarray]) -> tuple[int, int]:
    """(offsets stored, offsets in all) over the instances of an instanced file's arrays (v2)."""
    kept = total = 0
    per_gaussian = arrays["sh"].shape[1] * 3
    for iid, cls in zip(arrays["instance_ids"], arrays["instance_class"]):
        values = arrays.get(f"offsets_values_{int(iid)}")
        if values is not None:
            kept += len(values)
            total += int((arrays["gauss_class"] == cls).sum()) * per_gaussian
    return kept, total


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
    if str(arrays.get("format", "")) not in READABLE_FORMATS:
        raise ValueError(f"{path}: format {arrays.get('format')!r}, expected one of {READABLE_FORMATS}")
    return InstancedScene(arrays)


@torch.no_grad()
def render_difference(model, path: Path, cameras, max_views: int = 1) -> Dict[str, float]:
    """How faithfully an instanced file reproduces the model: its scene and the model's composed scene
    rendered in the first ``max_views`` of ``cameras`` (nerfstudio Cameras).

    Returns:
        {"views", "max_abs": largest |Δ| of any pixel channel (RGB in [0, 1]), "psnr": PSNR of the file's renders
        against the model's (inf when identical)}.
    """
    from splatreplace_ns.render import rasterize, world_to_camera

    device = model.means.device
    scenes = [model.composed_scene(), load_instanced(path).compose()]
    degree = int(round(scenes[0].sh.shape[1] ** 0.5)) - 1
    worst, squared, pixels = 0.0, 0.0, 0
    views = min(int(max_views), len(cameras))
    for k in range(views):
        camera = cameras[k : k + 1].to(device)
        viewmat = world_to_camera(camera.camera_to_worlds)[0]
        K = camera.get_intrinsics_matrices()[0]
        width, height = int(camera.width), int(camera.height)
        images = [rasterize(sc.means.to(device), sc.quats.to(device), torch.exp(sc.log_scales.to(device)),
                            torch.sigmoid(sc.logit_opacities.to(device)).reshape(-1), sc.sh.to(device), viewmat, K,
                            width, height, sh_degree=degree).image.clamp(0.0, 1.0) for sc in scenes]
        diff = (images[1] - images[0]).float()
        worst = max(worst, float(diff.abs().max()))
        squared += float((diff**2).sum())
        pixels += diff.numel()
    mse = squared / max(pixels, 1)
    return {"views": views, "max_abs": worst, "psnr": float("inf") if mse == 0 else float(-10.0 * np.log10(mse))}


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
