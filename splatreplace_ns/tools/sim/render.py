"""CPU ray-casting renderer (open3d ``RaycastingScene``).

Lambertian shading: albedo from the solid textures times (hemispherical ambient + directional / point
lights). Shadow rays are cast only when the scene asks for shadows. RGB is supersampled on a regular
grid inside each pixel; instance ids, depth and hit points come from the single ray through the pixel
centre, so they are exact for that ray.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import open3d as o3d

from splatreplace_ns.tools.sim.cameras import PinholeCamera, pixel_rays, supersample_offsets
from splatreplace_ns.tools.sim.scene import Scene
from splatreplace_ns.tools.sim.textures import albedo, sky

_SHADOW_BIAS = 2e-3  # metres, offset of shadow-ray origins along the normal


@dataclass(frozen=True)
class Frame:
    """One rendered view."""

    rgb: np.ndarray  # (H, W, 3) uint8, sRGB
    ids: np.ndarray  # (H, W) uint16, 0 = background or nothing, k = instance id
    depth: np.ndarray  # (H, W) float32 z-depth in metres, 0 where the ray hits nothing
    points: np.ndarray  # (H, W, 3) float32 world hit points of the centre rays, NaN where nothing is hit


@dataclass(frozen=True)
class Hits:
    """Ray-cast results for N rays."""

    t: np.ndarray  # (N,) float32 ray parameter (z-depth for camera rays), inf = miss
    geometry: np.ndarray  # (N,) int64 geometry index, -1 = miss
    normal: np.ndarray  # (N, 3) float32 geometric normal (world), arbitrary orientation

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool."""
        return self.geometry >= 0


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Linear RGB (..., 3) → 8-bit sRGB-like (gamma 2.2) with rounding."""
    return np.round(255.0 * np.clip(rgb, 0.0, 1.0) ** (1.0 / 2.2)).astype(np.uint8)


class Renderer:
    """Holds the ray-casting acceleration structure of one scene.

    Geometry index g (as reported by open3d) maps to a material, an instance id (0 for the
    environment) and the world→local transform in which the material is evaluated.
    """

    def __init__(self, scene: Scene, supersample: int = 2) -> None:
        self.scene = scene
        self.supersample = supersample
        self._rc = o3d.t.geometry.RaycastingScene()
        self._n_geometries = 0
        materials: list[str] = []
        instance_ids: list[int] = []
        w2l: list[np.ndarray] = []
        colours: list[Optional[np.ndarray]] = []
        for surface in scene.surfaces:
            self._add(surface.mesh)
            materials.append(surface.material)
            instance_ids.append(0)
            w2l.append(np.eye(4))
            colours.append(surface.colour)
        for inst in scene.instances:
            self._add(inst.world_mesh())
            materials.append(inst.cls)
            instance_ids.append(inst.id)
            w2l.append(np.linalg.inv(inst.pose))
            colours.append(inst.colour)
        self._materials = materials
        self._colours = [None if c is None else np.asarray(c, dtype=np.float32).reshape(3, 3) for c in colours]
        self._shadow_rc = self._rc  # what shadow rays can hit: everything, unless some surfaces cast no shadows
        if scene.shadows and not all(surface.casts_shadows for surface in scene.surfaces):
            self._shadow_rc = o3d.t.geometry.RaycastingScene()
            casters = [s.mesh for s in scene.surfaces if s.casts_shadows] + [i.world_mesh() for i in scene.instances]
            for mesh in casters:
                self._shadow_rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self._instance_of = np.asarray(instance_ids, dtype=np.uint16)
        self._w2l = np.stack(w2l).astype(np.float64)

    def _add(self, mesh: o3d.geometry.TriangleMesh) -> None:
        g = self._rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        if g != self._n_geometries:
            raise RuntimeError(f"open3d returned geometry id {g}, expected {self._n_geometries}")
        self._n_geometries += 1

    # ------------------------------------------------------------------ ray casting

    @staticmethod
    def _rays(origins: np.ndarray, dirs: np.ndarray) -> o3d.core.Tensor:
        """(N, 6) float32 ray tensor from origins (N, 3) or one shared origin (3,) and directions (N, 3)."""
        rays = np.empty((dirs.shape[0], 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        return o3d.core.Tensor(rays)

    def trace(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        """Closest hits.

        Args:
            origins: (N, 3) ray origins, or (3,) shared by all rays.
            dirs: (N, 3) ray directions (not necessarily unit; t is in units of their length).
        Returns:
            Hits for the N rays (open3d reports unit geometric normals).
        """
        res = self._rc.cast_rays(self._rays(origins, dirs))
        t = res["t_hit"].numpy()
        gid = res["geometry_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t) | (gid == o3d.t.geometry.RaycastingScene.INVALID_ID)
        gid[miss] = -1
        t = np.where(miss, np.inf, t).astype(np.float32)
        return Hits(t=t, geometry=gid, normal=res["primitive_normals"].numpy())

    def instance_ids(self, hits: Hits) -> np.ndarray:
        """(N,) uint16 instance id of each ray's closest hit; 0 for the environment and for misses."""
        ids = np.zeros(hits.geometry.shape, dtype=np.uint16)
        ids[hits.hit] = self._instance_of[hits.geometry[hits.hit]]
        return ids

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, t_far: float) -> np.ndarray:
        """(N,) bool: whether anything that casts shadows lies on each ray for t in (0, t_far)."""
        return self._shadow_rc.test_occlusions(self._rays(origins, dirs), tnear=0.0, tfar=t_far).numpy().astype(bool)

    # ------------------------------------------------------------------ shading

    def albedo_at(self, points: np.ndarray, geometry: np.ndarray) -> np.ndarray:
        """Albedo of hit points.

        Args:
            points: (N, 3) world points, all hits.
            geometry: (N,) geometry index of each point (>= 0).
        Returns:
            (N, 3) float32 linear albedo.
        """
        out = np.zeros((points.shape[0], 3), dtype=np.float32)
        order = np.argsort(geometry, kind="stable")
        g_sorted = geometry[order]
        starts = np.flatnonzero(np.r_[True, g_sorted[1:] != g_sorted[:-1]])
        ends = np.r_[starts[1:], len(order)]
        for s, e in zip(starts, ends):
            g = int(g_sorted[s])
            idx = order[s:e]
            m = self._w2l[g].astype(np.float32)
            local = points[idx] @ m[:3, :3].T + m[:3, 3]
            colour = albedo(self._materials[g], local)
            if self._colours[g] is not None:
                colour = np.clip(colour @ self._colours[g].T, 0.0, 1.0)
            out[idx] = colour
        return out

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Incident light (ambient + lights, with shadow rays if the scene has shadows).

        Args:
            points: (N, 3) world points.
            normals: (N, 3) unit normals facing the viewer.
        Returns:
            (N, 3) float32 linear irradiance factors.
        """
        sc = self.scene
        nz = normals[:, 2:3]
        e = (0.5 + 0.5 * nz) * np.asarray(sc.ambient_sky, np.float32) + (0.5 - 0.5 * nz) * np.asarray(
            sc.ambient_ground, np.float32
        )
        for light in sc.lights:
            vec = np.asarray(light.vector, dtype=np.float32)
            if light.kind == "directional":
                to_light = vec / np.linalg.norm(vec)  # (3,), shared
                ndl = np.maximum(normals @ to_light, 0.0)
                t_far = np.inf
            else:
                to_light = vec[None, :] - points  # (N, 3), unnormalised: t = 1 at the light
                dist = np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
                ndl = np.maximum(np.einsum("ij,ij->i", normals, to_light) / dist, 0.0)
                ndl /= 1.0 + (dist / light.falloff) ** 2
                t_far = 1.0 - 1e-4
            if sc.shadows:
                lit = np.flatnonzero(ndl > 0.0)
                if lit.size:
                    dirs = np.broadcast_to(to_light, points.shape)[lit]
                    blocked = self.occluded(points[lit] + _SHADOW_BIAS * normals[lit], dirs, t_far)
                    ndl[lit[blocked]] = 0.0
            e = e + ndl[:, None] * np.asarray(light.colour, np.float32)
        return e.astype(np.float32)

    def shade(self, origins: np.ndarray, dirs: np.ndarray, hits: Hits) -> np.ndarray:
        """Radiance along each ray.

        Args:
            origins: (N, 3), or (3,) shared by all rays.
            dirs: (N, 3).
            hits: their ray-cast results.
        Returns:
            (N, 3) float32 linear RGB.
        """
        out = np.empty((dirs.shape[0], 3), dtype=np.float32)
        hit = hits.hit
        out[~hit] = sky(dirs[~hit])
        idx = np.flatnonzero(hit)
        d = dirs[idx].astype(np.float32)
        o = origins if origins.ndim == 1 else origins[idx]
        p = o.astype(np.float32) + hits.t[idx, None] * d
        n = hits.normal[idx]
        n *= -np.sign(np.einsum("ij,ij->i", n, d))[:, None]  # face the viewer (two-sided surfaces)
        out[idx] = self.albedo_at(p, hits.geometry[idx]) * self.irradiance(p, n)
        return out

    # ------------------------------------------------------------------ images

    def render(self, cam: PinholeCamera) -> Frame:
        """Render RGB (supersampled), instance ids, z-depth and hit points of one camera."""
        h, w = cam.height, cam.width
        eye = cam.center
        offs = supersample_offsets(self.supersample)
        d = pixel_rays(cam, offs)[1].reshape(-1, 3)
        rgb = self.shade(eye, d, self.trace(eye, d)).reshape(len(offs), h, w, 3).mean(axis=0)

        dc = pixel_rays(cam, np.array([[0.5, 0.5]]))[1].reshape(-1, 3)
        centre = self.trace(eye, dc)
        hit = centre.hit
        ids = self.instance_ids(centre)
        depth = np.where(hit, centre.t, 0.0).astype(np.float32)
        points = np.where(hit[:, None], eye + centre.t[:, None].astype(np.float64) * dc, np.nan).astype(np.float32)
        return Frame(
            rgb=linear_to_srgb8(rgb), ids=ids.reshape(h, w), depth=depth.reshape(h, w), points=points.reshape(h, w, 3)
        )
