"""Building the shared templates from segmented, registered instances (paper §4.3, first paragraph).

Per class, the template is the union of all its registered instances mapped into template space (the
world frame of the class's template instance). Each instance becomes a reference: its pose is the
inverse of its registration transform, and its SH offsets start at zero with the shared colour scaled
by 1/λ, so that the first render of the replaced scene shows every Gaussian with its own colour.
Instances whose registration failed are left as ordinary background Gaussians (not replaced).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Mapping

import numpy as np
import torch
from torch import Tensor

from splatreplace_ns.render.transform import rotmat_to_quat, transform_gaussians


@dataclass
class InstanceTable:
    """Per-instance references into the templates (I instances, C classes).

    Attributes:
        ids [I] long: instance ids; class_index [I] long (1-based, into ``classes``); slot [I] long: the
        instance's column in ``sh_offsets``; q0 [I, 4], t0 [I, 3]: initial pose (template space → world);
        classes: class names (index c-1 for class c); template_ids: {class index: template instance id};
        kept_in_background: instance ids whose registration failed (not replaced).
    """

    ids: Tensor
    class_index: Tensor
    slot: Tensor
    q0: Tensor
    t0: Tensor
    classes: List[str] = field(default_factory=list)
    template_ids: Dict[int, int] = field(default_factory=dict)
    kept_in_background: List[int] = field(default_factory=list)

    @property
    def slots_per_class(self) -> Dict[int, int]:
        return {c + 1: int((self.class_index == c + 1).sum()) for c in range(len(self.classes))}

    def state(self) -> Dict:
        return {
            "ids": self.ids, "class_index": self.class_index, "slot": self.slot, "q0": self.q0, "t0": self.t0,
            "classes": list(self.classes), "template_ids": dict(self.template_ids),
            "kept_in_background": list(self.kept_in_background),
        }

    @classmethod
    def from_state(cls, state: Mapping) -> "InstanceTable":
        return cls(**{k: state[k] for k in ("ids", "class_index", "slot", "q0", "t0")},
                   classes=list(state.get("classes", [])), template_ids=dict(state.get("template_ids", {})),
                   kept_in_background=list(state.get("kept_in_background", [])))

    @classmethod
    def empty(cls) -> "InstanceTable":
        z = torch.zeros(0, dtype=torch.long)
        return cls(z, z.clone(), z.clone(), torch.zeros(0, 4), torch.zeros(0, 3))


def merge_union(part: Dict[str, Tensor], reference: Tensor, cells_per_radius: int = 30) -> Tensor:
    """Indices that keep one Gaussian per voxel of a template union (the most opaque one).

    The union of N registered copies holds N Gaussians wherever the copies overlap; every instance then
    renders all of them. Merging on a grid whose cell is a fixed fraction of the template instance's radius
    keeps the most opaque Gaussian of the copies at each place, so the template stays near one instance in
    size. (The median spacing of the centres is no cell size: densification leaves clumps of near-duplicate
    Gaussians, and on the demo scene it was 1/1000 of a chair's radius and merged almost nothing.)

    Args:
        part: the union's tensors; uses means [n, 3] and opacities [n, 1] (logits).
        reference: [m, 3] centres of the template instance (for the cell size).
        cells_per_radius: the cell is the template's robust radius / this.
    Returns:
        [k] long indices into the union, sorted.
    """
    from splatreplace_ns.poses.virtual_cameras import fit_sphere

    ref = reference.detach().cpu().double().numpy()
    if len(ref) < 2 or len(part["means"]) < 2 or cells_per_radius <= 0:
        return torch.arange(len(part["means"]))
    _, radius = fit_sphere(ref)
    cell = float(radius) / float(cells_per_radius)
    if not np.isfinite(cell) or cell <= 0:
        return torch.arange(len(part["means"]))
    cells = torch.floor(part["means"].detach().cpu().double() / cell).long()
    _, cell_id = torch.unique(cells, dim=0, return_inverse=True)
    opacity = part["opacities"].detach().cpu().reshape(-1).double()
    # most opaque per cell: sort by (cell, -opacity) and take each cell's first entry
    order = np.lexsort((-opacity.numpy(), cell_id.numpy()))
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell_id.numpy()[order][1:] != cell_id.numpy()[order][:-1]
    return torch.from_numpy(np.sort(order[first]))


def build_templates(
    params: Mapping[str, Tensor],
    labels: Tensor,
    instance_classes: Mapping[int, str],
    transforms: Mapping[int, Tensor],
    templates: Mapping[str, int],
    lam: float = 0.8,
    merge: bool = False,
    merge_cells_per_radius: int = 30,
) -> tuple[Dict[str, Tensor], InstanceTable]:
    """The stored Gaussians of the replaced scene.

    Args:
        params: stored Gaussians (N): means [N, 3], quats [N, 4], scales [N, 3] (log), opacities [N, 1]
            (logit), features_dc [N, 3], features_rest [N, K-1, 3], and any other per-Gaussian tensors
            (carried along unchanged).
        labels: [N] long instance id per Gaussian (0 = background).
        instance_classes: {instance id: class name} of the segmented instances.
        transforms: {instance id: [4, 4] float (template ≈ T · instance, world)} for every *registered*
            instance (the template itself maps by the identity); instances missing here stay background.
        templates: {class name: template instance id}.
        lam: mixing weight λ (shared colours are stored divided by λ, offsets start at 0; with λ = 0 the
            offsets carry the colour and start equal to it).
        merge: keep one Gaussian per voxel of each class's union of two or more copies (see
            :func:`merge_union`) instead of the plain union of the paper; a class of one copy keeps all of it.
        merge_cells_per_radius: merge grid cell = template radius / this.
    Returns:
        (new params with ``template_class`` [N', 1] float and ``sh_offsets`` [N', S, K, 3] added, table).
    """
    labels = labels.to(params["means"].device)
    dtype = params["means"].dtype
    device = params["means"].device
    classes = sorted({instance_classes[i] for i in transforms if i in instance_classes})
    class_of = {name: c + 1 for c, name in enumerate(classes)}
    registered = [i for i in sorted(transforms) if i in instance_classes]
    kept = sorted(int(i) for i in instance_classes if i not in transforms)

    background = torch.ones_like(labels, dtype=torch.bool)
    for i in registered:
        background &= labels != i
    chunks: List[Dict[str, Tensor]] = []
    bg = {k: v[background] for k, v in params.items()}
    bg["template_class"] = torch.zeros(int(background.sum()), 1, dtype=dtype, device=device)
    chunks.append(bg)

    ids, cls_idx, slots, q0, t0 = [], [], [], [], []
    template_ids = {}
    for name in classes:
        c = class_of[name]
        members = [i for i in registered if instance_classes[i] == name]
        template_ids[c] = int(templates.get(name, members[0]))
        class_parts = []
        for slot, i in enumerate(members):
            T = torch.as_tensor(transforms[i], dtype=dtype, device=device)
            sel = labels == i
            part = {k: v[sel] for k, v in params.items()}
            sh = torch.cat((part["features_dc"][:, None], part["features_rest"]), dim=1)
            means, quats, sh = transform_gaussians(T, part["means"], part["quats"], sh)
            shared = sh / lam if lam > 0 else sh
            part.update(means=means, quats=quats, features_dc=shared[:, 0], features_rest=shared[:, 1:])
            part["template_class"] = torch.full((len(means), 1), float(c), dtype=dtype, device=device)
            class_parts.append(part)
            pose = torch.linalg.inv(T)  # template space → this instance in the world
            ids.append(int(i))
            cls_idx.append(c)
            slots.append(slot)
            q0.append(rotmat_to_quat(pose[:3, :3]))
            t0.append(pose[:3, 3])
        union = {k: torch.cat([p[k] for p in class_parts]) for k in class_parts[0]}
        if merge and len(members) > 1:  # one copy overlaps nothing: merging would only thin it
            reference = class_parts[members.index(template_ids[c])]["means"] if template_ids[c] in members else union["means"]
            keep = merge_union(union, reference, merge_cells_per_radius).to(device)
            union = {k: v[keep] for k, v in union.items()}
        chunks.append(union)

    out = {k: torch.cat([ch[k] for ch in chunks]) for k in chunks[0]}
    n_slots = max(slots) + 1 if slots else 0  # most instances in one class
    K = out["features_rest"].shape[1] + 1
    out["sh_offsets"] = torch.zeros(len(out["means"]), n_slots, K, 3, dtype=dtype, device=device)
    if lam <= 0:  # c = c_offset: every instance starts from the colour of the Gaussian
        templ = out["template_class"][:, 0] > 0
        sh_all = torch.cat((out["features_dc"][:, None], out["features_rest"]), dim=1)
        out["sh_offsets"][templ] = sh_all[templ][:, None].expand(-1, n_slots, K, 3)
    table = InstanceTable(
        ids=torch.tensor(ids, dtype=torch.long),
        class_index=torch.tensor(cls_idx, dtype=torch.long),
        slot=torch.tensor(slots, dtype=torch.long),
        q0=torch.stack(q0).to(dtype).cpu() if q0 else torch.zeros(0, 4),
        t0=torch.stack(t0).to(dtype).cpu() if t0 else torch.zeros(0, 3),
        classes=classes,
        template_ids=template_ids,
        kept_in_background=kept,
    )
    return out, table
