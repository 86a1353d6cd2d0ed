"""TSDF fusion of depth maps and marching-cubes mesh extraction."""

import numpy as np
import pytest

import ghsplat_jax as gs
from ghsplat_jax.scene import surfaces, tsdf
from ghsplat_jax.scene.views import orbit_cameras

pytest.importorskip("skimage")

CFG = gs.RasterConfig(background=(0.3, 0.3, 0.3), pair_capacity=1 << 14)
NUM, SIZE = 8192, 128


def _sphere_depth(cam, radius):
    """Analytic z-depth of a sphere at the origin (0 where the ray misses)."""
    K, w2c = np.asarray(cam.K, np.float64), np.asarray(cam.world_to_cam, np.float64)
    i, j = np.mgrid[0:cam.height, 0:cam.width]
    d = np.stack([(j + 0.5 - K[0, 2]) / K[0, 0], (i + 0.5 - K[1, 2]) / K[1, 1], np.ones(i.shape)], -1)
    R, c = w2c[:3, :3], -w2c[:3, :3].T @ w2c[:3, 3]
    dw = d @ R  # world ray with unit camera z, so the ray parameter is the z-depth
    a, b, cc = (dw * dw).sum(-1), 2 * dw @ c, c @ c - radius ** 2
    disc = b * b - 4 * a * cc
    return np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)


def test_fused_analytic_sphere_is_within_a_voxel():
    voxel, radius = 0.02, 0.3
    volume = tsdf.TSDFVolume([-0.4] * 3, [0.4] * 3, voxel)
    for cam in orbit_cameras([0, 0, 0], 1.2, [-0.6, 0.0, 0.6], 6, 64, 64, 60):
        volume.integrate(_sphere_depth(cam, radius), cam.K, cam.world_to_cam)
    mesh = volume.extract_mesh()
    err = np.abs(np.linalg.norm(mesh.vertices, axis=1) - radius)
    assert err.mean() < 0.25 * voxel and err.max() < voxel, (err.mean(), err.max())
    # outward normals, and a closed surface around the whole sphere
    assert np.mean(np.sum(mesh.face_normals * mesh.triangles_center, axis=1) > 0) > 0.99
    assert mesh.area == pytest.approx(4 * np.pi * radius ** 2, rel=0.05)


def test_no_zero_crossing_is_an_error():
    volume = tsdf.TSDFVolume([0, 0, 0], [1, 1, 1], 0.1)
    with pytest.raises(ValueError, match="nothing to mesh"):
        volume.extract_mesh()
    with pytest.raises(ValueError, match="too large"):
        tsdf.TSDFVolume([0, 0, 0], [100, 100, 100], 0.01)


def test_mesh_of_a_rendered_surfel_box(tmp_path):
    """Render a surfel box from 8 views, fuse median depth: the mesh lies within a voxel or
    two of the box faces and covers them."""
    lo, hi, voxel = np.array([-0.2, -0.15, -0.1]), np.array([0.2, 0.15, 0.1]), 0.02
    box = surfaces.box(lo, hi, 0.015, surfaces.constant_colour([0.8, 0.5, 0.2]))
    cams = orbit_cameras([0, 0, 0], 1.0, [-0.6, 0.6], 4, SIZE, SIZE, 50)
    volume = tsdf.fuse_renders(box, cams, lo - 0.1, hi + 0.1, voxel, config=CFG, num=NUM)
    mesh = volume.extract_mesh()
    v = mesh.vertices
    # distance of each vertex to the nearest face plane, for vertices away from the edges
    # (a surfel's Gaussian reaches past the box edge, rounding the corners by ~a pitch)
    gap = np.abs(np.abs(v) - hi)  # per-axis distance to the two face planes of that axis
    axis = np.argmin(gap, axis=1)
    inner = np.all((np.abs(v) < hi - 2 * voxel) | (np.arange(3) == axis[:, None]), axis=1)
    d = gap[np.arange(len(v)), axis][inner]
    assert inner.sum() > 100
    assert np.median(d) < 0.5 * voxel and d.max() < 2 * voxel, (np.median(d), d.max())
    # coverage: points sampled on every face (inset) have a mesh vertex within 1.5 voxels
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    pts = rng.uniform(-(hi - 2 * voxel), hi - 2 * voxel, (600, 3))
    ax = rng.integers(0, 3, 600)
    pts[np.arange(600), ax] = np.sign(rng.normal(size=600)) * hi[ax]
    assert cKDTree(v).query(pts)[0].max() < 1.5 * voxel
    colours = mesh.visual.vertex_colors[:, :3].astype(float) / 255
    np.testing.assert_allclose(np.median(colours, axis=0), [0.8, 0.5, 0.2], atol=0.08)
    path = tsdf.save_mesh(mesh, tmp_path / "box.ply")
    import trimesh

    assert len(trimesh.load(path).faces) == len(mesh.faces)
