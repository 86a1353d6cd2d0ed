"""Mesh extraction: fuse depth maps into a TSDF voxel grid, then marching cubes.

The 2DGS recipe: render depth (median depth is sharpest) from many views, integrate into a
truncated signed distance volume (numpy, weighted running average), and extract the zero
level set with skimage's marching cubes; trimesh writes the mesh. Depth is OpenCV z-depth.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from ghsplat_jax.core.camera import project_points


@dataclasses.dataclass
class TSDFVolume:
    """A voxel grid over [lo, hi] with `voxel` edge (m); truncation in metres (default 3 voxels)."""
    lo: np.ndarray
    hi: np.ndarray
    voxel: float
    trunc: float | None = None

    def __post_init__(self):
        self.lo = np.asarray(self.lo, np.float64)
        self.hi = np.asarray(self.hi, np.float64)
        if not self.voxel > 0 or np.any(self.hi <= self.lo):
            raise ValueError(f"TSDF needs voxel > 0 and hi > lo, got {self.voxel}, {self.lo}, {self.hi}")
        self.trunc = 3.0 * self.voxel if self.trunc is None else float(self.trunc)
        self.shape = tuple(int(v) for v in np.ceil((self.hi - self.lo) / self.voxel).astype(int) + 1)
        if np.prod(self.shape) > 256 ** 3:
            raise ValueError(f"TSDF grid {self.shape} too large; use a larger voxel")
        self.tsdf = np.ones(self.shape, np.float32)
        self.weight = np.zeros(self.shape, np.float32)
        self.colour = np.zeros(self.shape + (3,), np.float32)
        self._axes = [self.lo[i] + self.voxel * np.arange(self.shape[i]) for i in range(3)]

    def _slabs(self, max_voxels: int = 1 << 21):
        """(flat offset, voxel centres (M,3)) per slab of x-planes: bounded memory per view."""
        nx, ny, nz = self.shape
        step = max(1, max_voxels // (ny * nz))
        for x0 in range(0, nx, step):
            ax = [self._axes[0][x0:x0 + step], self._axes[1], self._axes[2]]
            yield x0 * ny * nz, np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)

    def integrate(self, depth, K, world_to_cam, alpha=None, rgb=None, min_alpha: float = 0.5,
                  max_depth: float | None = None) -> None:
        """Fuse one depth map (H,W) z-depth; pixels with alpha < min_alpha or depth <= 0 are
        unknown. Voxels further than `trunc` behind the surface are left untouched."""
        depth = np.asarray(depth, np.float64)
        valid_px = np.isfinite(depth) & (depth > 0)
        if alpha is not None:
            valid_px &= np.asarray(alpha) >= min_alpha
        if max_depth is not None:
            valid_px &= depth <= max_depth
        K, w2c = np.asarray(K, np.float64), np.asarray(world_to_cam, np.float64)
        rgb = None if rgb is None else np.asarray(rgb, np.float64)
        for offset, points in self._slabs():
            self._integrate_points(offset, points, depth, valid_px, K, w2c, rgb)

    def _integrate_points(self, offset, points, depth, valid_px, K, w2c, rgb) -> None:
        h, w = depth.shape
        uv, z = project_points(points, K, w2c)
        j, i = np.floor(uv[:, 0]), np.floor(uv[:, 1])  # the pixel each voxel centre falls in
        inside = (z > 0) & (j >= 0) & (j < w) & (i >= 0) & (i < h)
        idx = np.flatnonzero(inside)
        ii, jj = i[idx].astype(int), j[idx].astype(int)
        ok = valid_px[ii, jj]
        idx, ii, jj = idx[ok], ii[ok], jj[ok]
        sdf = depth[ii, jj] - z[idx]
        ok = sdf >= -self.trunc
        idx, ii, jj, sdf = idx[ok] + offset, ii[ok], jj[ok], sdf[ok]
        value = np.minimum(1.0, sdf / self.trunc)
        t, wgt = self.tsdf.reshape(-1), self.weight.reshape(-1)
        new_w = wgt[idx] + 1.0
        t[idx] = (t[idx] * wgt[idx] + value) / new_w
        if rgb is not None:
            c = self.colour.reshape(-1, 3)
            c[idx] = (c[idx] * wgt[idx, None] + rgb[ii, jj]) / new_w[:, None]
        wgt[idx] = new_w

    def extract_mesh(self, min_weight: float = 1.0):
        """trimesh.Trimesh of the zero level set (vertex colours when rgb was fused)."""
        import trimesh
        from skimage.measure import marching_cubes

        observed = self.weight >= min_weight
        # unobserved voxels (outside every view, or further than `trunc` behind the surface)
        # read as empty (+1); the crossings this invents beside them are removed below.
        volume = np.where(observed, self.tsdf, 1.0)
        if not (volume.min() < 0 < volume.max()):
            raise ValueError("TSDF has no zero crossing: nothing to mesh (check views and bounds)")
        verts, faces, _, _ = marching_cubes(volume, level=0.0, spacing=(self.voxel,) * 3)
        # a vertex lies on a grid edge: keep it only if both voxels of that edge were observed
        p = verts / self.voxel
        r = np.round(p)
        on_grid = np.abs(p - r) < 1e-4
        ends = [np.clip(np.where(on_grid, r, f(p)).astype(int), 0, np.array(self.shape) - 1)
                for f in (np.floor, np.ceil)]
        good = observed[tuple(ends[0].T)] & observed[tuple(ends[1].T)]
        faces = faces[good[faces].all(axis=1)]
        if len(faces) == 0:
            raise ValueError("TSDF surface lies only beside unobserved voxels: nothing to mesh")
        verts = verts + self.lo
        colours = None
        if self.weight.any():
            idx = np.clip(np.round((verts - self.lo) / self.voxel).astype(int), 0,
                          np.array(self.shape) - 1)
            c = self.colour[idx[:, 0], idx[:, 1], idx[:, 2]]
            colours = (np.clip(c, 0, 1) * 255).astype(np.uint8)
        mesh = trimesh.Trimesh(verts, faces, vertex_colors=colours, process=True)
        mesh.remove_unreferenced_vertices()
        return mesh


def fuse_renders(surfels, cameras, lo, hi, voxel: float, trunc: float | None = None,
                 config=None, depth: str = "median_depth", min_alpha: float = 0.5,
                 num: int | None = None) -> TSDFVolume:
    """Render each camera and fuse depth (+ rgb) into a TSDF over [lo, hi]
    (`num`: padded surfel count, see views.render_stable)."""
    from ghsplat_jax.scene.views import render_stable

    volume = TSDFVolume(lo, hi, voxel, trunc)
    for cam in cameras:
        out = render_stable(surfels, cam, config, num)
        volume.integrate(np.asarray(getattr(out, depth)), np.asarray(cam.K), np.asarray(cam.world_to_cam),
                         alpha=np.asarray(out.alpha), rgb=np.asarray(out.rgb), min_alpha=min_alpha)
    return volume


def save_mesh(mesh, path: str | os.PathLike) -> Path:
    """Write a mesh atomically; the format follows the suffix (.ply, .obj, .stl, .glb)."""
    from ghsplat_jax.io_utils import atomic_write

    path = Path(path)
    data = mesh.export(file_type=path.suffix.lstrip(".").lower() or "ply")
    with atomic_write(path, "wb" if isinstance(data, bytes) else "w") as fh:
        fh.write(data)
    return path


def mesh_from_surfels(surfels, voxel: float, views_per_ring: int = 12, size: int = 256,
                      fov_x_deg: float = 60.0, config=None, margin: float = 0.05):
    """Mesh of a surfel scene: orbit cameras (three rings) around its 1-99 % bounds, fused.

    Good for objects and single segments; for a whole greenhouse, fuse the views of a
    robot trajectory with fuse_renders instead (orbits cannot see between rows).
    """
    from ghsplat_jax.scene.views import orbit_cameras

    x = np.asarray(surfels.means, np.float64)
    x = x[np.all(np.isfinite(x), axis=1)]
    lo, hi = np.percentile(x, 1, axis=0) - margin, np.percentile(x, 99, axis=0) + margin
    centre, extent = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    radius = 0.5 * extent / np.tan(np.deg2rad(fov_x_deg) / 2) * 1.1
    cams = orbit_cameras(centre, radius, [-0.5 * radius, 0.0, 0.5 * radius], views_per_ring,
                         size, size, fov_x_deg)
    from ghsplat_jax.raster import RasterConfig

    config = config or RasterConfig(near=min(0.2, 0.1 * radius))
    return fuse_renders(surfels, cams, lo, hi, voxel, config=config).extract_mesh()
