"""Flat surfel surfaces (floor, walls) from rectangles, boxes or trimesh meshes.

Surfels lie in the surface (their normal = the face normal) on a grid of pitch `spacing`
with sigma = `overlap` x spacing: with the default 0.7, every point of the surface is
covered by several nearly opaque surfels, so a camera at robot height (0.3-0.5 m) grazing
the floor sees no gaps. Colour comes from a colour function of (world points, surface
coordinates in metres): a constant, a tiling texture image, or the captured ground.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ghsplat_jax.core import sh
from ghsplat_jax.core.quaternions import from_rotation_matrix
from ghsplat_jax.core.surfels import Surfels

ColourFn = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (points (N,3), uv (N,2) m) -> rgb (N,3)

OPAQUE_LOGIT = float(np.log(0.99 / 0.01))


def constant_colour(rgb) -> ColourFn:
    rgb = np.asarray(rgb, np.float64)
    if rgb.shape != (3,):
        raise ValueError(f"colour must be three numbers, got {rgb.tolist()}")
    return lambda points, uv: np.broadcast_to(rgb, (len(points), 3)).copy()


def load_image(path: str | Path) -> np.ndarray:
    """(H,W,3) float image in [0,1] via OpenImageIO (PNG, JPEG, EXR, ...)."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such texture image")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: cannot read image ({oiio.geterror()})")
    try:
        img = inp.read_image(format="float")
    finally:
        inp.close()
    if img is None:
        raise ValueError(f"{path}: cannot read image data")
    img = np.asarray(img, np.float64)
    if img.ndim == 2:
        img = img[..., None]
    img = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
    return np.clip(img, 0.0, 1.0)


def texture_colour(image, tile_size=(1.0, 1.0)) -> ColourFn:
    """Tile `image` (array or path) over the surface, one copy per tile_size metres (u, v);
    bilinear lookup with wrap-around. Image row 0 is at the tile's high-v edge."""
    img = load_image(image) if isinstance(image, (str, Path)) else np.asarray(image, np.float64)
    h, w = img.shape[:2]
    tu, tv = (float(v) for v in np.broadcast_to(np.asarray(tile_size, np.float64), (2,)))

    def colour(points, uv):
        x = (uv[:, 0] / tu % 1.0) * w - 0.5
        y = (1.0 - uv[:, 1] / tv % 1.0) * h - 0.5
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        at = lambda r, c: img[r % h, c % w]
        return ((1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1))
                + fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)))

    return colour


def ground_colour(captured: Surfels, k: int = 8, max_height: float | None = None) -> ColourFn:
    """Colour of the nearest captured surfels in x-y (their view-independent DC colour),
    inverse-distance weighted over k neighbours: extends a captured floor into a synthetic one.
    `max_height` keeps only captured surfels below that z (the ground, not the plants)."""
    from scipy.spatial import cKDTree

    c = captured.to_numpy()
    keep = np.ones(c.num, bool) if max_height is None else c.means[:, 2] <= max_height
    if not keep.any():
        raise ValueError("no captured surfels to sample the ground colour from")
    xy = c.means[keep, :2].astype(np.float64)
    rgb = np.clip(c.sh_dc[keep].astype(np.float64) * sh.C0 + 0.5, 0.0, 1.0)
    tree, k = cKDTree(xy), min(k, len(xy))

    def colour(points, uv):
        d, i = tree.query(points[:, :2], k=k)
        d, i = d.reshape(len(points), k), i.reshape(len(points), k)
        w = 1.0 / np.maximum(d, 1e-6)
        return np.einsum("nk,nkc->nc", w, rgb[i]) / w.sum(1, keepdims=True)

    return colour


def surfels_from_samples(points, normals, tangents, colour: np.ndarray, sigma,
                         opacity_logit: float = OPAQUE_LOGIT, sh_degree: int = 0) -> Surfels:
    """Flat isotropic surfels at `points`, normal `normals`, first tangent axis `tangents`."""
    n = np.asarray(normals, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    u = np.asarray(tangents, np.float64)
    u = u - np.sum(u * n, 1, keepdims=True) * n
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    frames = np.stack([u, np.cross(n, u), n], axis=2)  # columns t_u, t_v, normal
    count = len(points)
    sigma = np.broadcast_to(np.asarray(sigma, np.float64), (count,))
    f32 = lambda a: np.ascontiguousarray(a, np.float32)
    return Surfels(
        means=f32(points), quats=f32(from_rotation_matrix(frames)),
        log_scales=f32(np.repeat(np.log(sigma)[:, None], 2, axis=1)),
        opacity_logits=np.full(count, opacity_logit, np.float32),
        sh_dc=f32(sh.rgb_to_dc(np.asarray(colour, np.float64))),
        sh_rest=np.zeros((count, (sh_degree + 1) ** 2 - 1, 3), np.float32))


def rectangle(center, axis_u, axis_v, size_u: float, size_v: float, spacing: float,
              colour: ColourFn, overlap: float = 0.7, sh_degree: int = 0) -> Surfels:
    """A size_u x size_v rectangle spanned by axis_u, axis_v (normal = u x v), grid-sampled."""
    if spacing <= 0 or size_u <= 0 or size_v <= 0:
        raise ValueError(f"rectangle needs positive sizes and spacing, got {size_u}, {size_v}, {spacing}")
    u = np.asarray(axis_u, np.float64); u = u / np.linalg.norm(u)
    v = np.asarray(axis_v, np.float64); v = v - (v @ u) * u; v = v / np.linalg.norm(v)
    nu, nv = max(1, int(np.ceil(size_u / spacing))), max(1, int(np.ceil(size_v / spacing)))
    # cell centres, so the rectangle's edge lies half a pitch beyond the outer surfels
    a = (np.arange(nu) + 0.5) * (size_u / nu) - size_u / 2
    b = (np.arange(nv) + 0.5) * (size_v / nv) - size_v / 2
    A, B = (g.ravel() for g in np.meshgrid(a, b, indexing="ij"))
    points = np.asarray(center, np.float64) + A[:, None] * u + B[:, None] * v
    uv = np.stack([A + size_u / 2, B + size_v / 2], axis=1)
    pitch = max(size_u / nu, size_v / nv)
    count = len(points)
    return surfels_from_samples(points, np.broadcast_to(np.cross(u, v), (count, 3)),
                                np.broadcast_to(u, (count, 3)), colour(points, uv),
                                overlap * pitch, sh_degree=sh_degree)


def box(lo, hi, spacing: float, colour: ColourFn, faces=("+x", "-x", "+y", "-y", "+z", "-z"),
        overlap: float = 0.7, sh_degree: int = 0) -> Surfels:
    """Chosen faces of an axis-aligned box, normals pointing out."""
    from ghsplat_jax.scene.merge import merge

    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if np.any(hi <= lo):
        raise ValueError(f"box min {lo.tolist()} must be below max {hi.tolist()}")
    c, size, e = (lo + hi) / 2, hi - lo, np.eye(3)
    parts = []
    for face in faces:
        if face not in ("+x", "-x", "+y", "-y", "+z", "-z"):
            raise ValueError(f"unknown box face {face!r}")
        axis, sign = "xyz".index(face[1]), 1.0 if face[0] == "+" else -1.0
        iu, iv = [(1, 2), (2, 0), (0, 1)][axis]
        # u x v = +axis; flip v for the '-' face so the normal points out
        parts.append(rectangle(c + sign * size[axis] / 2 * e[axis], e[iu], sign * e[iv],
                               size[iu], size[iv], spacing, colour, overlap, sh_degree))
    return merge(parts)


def mesh(m, spacing: float, colour: ColourFn, overlap: float = 0.8, sh_degree: int = 0,
         seed: int = 0) -> Surfels:
    """Surfels on a trimesh mesh: evenly spread samples (Poisson-disk-like), face normals.
    Samples are less regular than a grid, hence the larger default overlap."""
    import trimesh

    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise ValueError("mesh surfaces need a non-empty trimesh.Trimesh")
    count = max(1, int(np.ceil(m.area / spacing ** 2)))
    points, face = trimesh.sample.sample_surface_even(m, count, radius=0.55 * spacing, seed=seed)
    normals = m.face_normals[face]
    edge = m.vertices[m.faces[face, 1]] - m.vertices[m.faces[face, 0]]  # in-plane tangent
    # surface coordinates for textures: project on the two world axes most in the face plane
    drop = np.argmax(np.abs(normals), axis=1)
    keep = np.array([[1, 2], [2, 0], [0, 1]])[drop]
    uv = np.take_along_axis(points, keep, axis=1)
    return surfels_from_samples(points, normals, edge, colour(points, uv), overlap * spacing,
                                sh_degree=sh_degree)


def load_mesh(path: str | Path):
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    try:
        m = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many types for bad files
        raise ValueError(f"{path}: cannot load mesh ({exc})") from None
    if len(m.faces) == 0:
        raise ValueError(f"{path}: mesh has no faces")
    return m
