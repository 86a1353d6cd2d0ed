"""Mesh building blocks: each returns (vertices (n,3) float64, faces (m,3) int, uv (n,2)).

Pure numpy, no trimesh; the scene module places and assembles them.
"""

from __future__ import annotations

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray, np.ndarray]


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def transform(mesh: Mesh, rotation: np.ndarray, translation) -> Mesh:
    v, f, uv = mesh
    return v @ np.asarray(rotation).T + np.asarray(translation), f, uv


def merge(meshes: list[Mesh]) -> Mesh:
    vs, fs, uvs, offset = [], [], [], 0
    for v, f, uv in meshes:
        vs.append(v)
        fs.append(f + offset)
        uvs.append(uv)
        offset += len(v)
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(uvs)


def grid_faces(rows: int, cols: int, wrap: bool = False) -> np.ndarray:
    """Two triangles per cell of a (rows x cols) vertex grid, row-major; `wrap` closes columns."""
    c_end = cols if wrap else cols - 1
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(c_end), indexing="ij")
    a = r * cols + c
    b = r * cols + (c + 1) % cols
    d = (r + 1) * cols + c
    e = (r + 1) * cols + (c + 1) % cols
    return np.concatenate([np.stack([a, b, e], -1).reshape(-1, 3),
                           np.stack([a, e, d], -1).reshape(-1, 3)])


def leaf_outline(theta: np.ndarray, lobes: int, lobe_depth: float, notch: float) -> np.ndarray:
    """Radius (unit blade) of a palmate, heart-based blade at angle theta from the tip."""
    lobed = 1 + lobe_depth * np.cos((lobes - 1) / 2 * 2 * theta) * 0.5
    pointed = 1 + 0.18 * np.exp(-(theta / 0.35) ** 2)
    sinus = 1 - notch * np.exp(-((np.pi - np.abs(theta)) / 0.45) ** 2)
    return 0.5 * lobed * pointed * sinus


def leaf_blade(length: float, lobes: int, lobe_depth: float, cup: float, droop: float,
               wave: float, n_rings: int = 4, n_theta: int = 28, width: float = 1.0) -> Mesh:
    """A blade in its local frame: petiole junction at the origin, tip toward +y, face +z;
    `width` scales it across (x): below 1 a narrower, strap-like blade of the same length.

    Polar rings around the blade centre; UVs are the planar (x, y) / length, shifted so the
    junction lies at (0.5, 0.04) as textures.leaf_texture expects.
    """
    theta = np.linspace(-np.pi, np.pi, n_theta, endpoint=False) + np.pi / n_theta
    radius = leaf_outline(theta, lobes, lobe_depth, notch=0.55)
    base_r = leaf_outline(np.array([np.pi]), lobes, lobe_depth, notch=0.55)[0]
    centre_y = base_r  # the notch's bottom point sits at the origin
    rho = np.linspace(0, 1, n_rings + 1)[1:]
    x = rho[:, None] * radius[None] * np.sin(theta)[None]
    y = centre_y + rho[:, None] * radius[None] * np.cos(theta)[None]
    x = np.concatenate([[0.0], x.ravel()]) * width
    y = np.concatenate([[centre_y], y.ravel()])
    # shape: cupped across, drooping toward the tip, wavy margin
    r_all = np.concatenate([[0.0], np.repeat(rho, n_theta)])
    th_all = np.concatenate([[0.0], np.tile(theta, n_rings)])
    z = -cup * x ** 2 - droop * np.clip(y - centre_y, 0, None) ** 2 + wave * r_all ** 3 * np.sin(7 * th_all)
    v = np.stack([x, y, z], -1) * length
    fan = np.stack([np.zeros(n_theta, int), 1 + np.arange(n_theta), 1 + (np.arange(n_theta) + 1) % n_theta], -1)
    rings = 1 + grid_faces(n_rings, n_theta, wrap=True)
    uv = np.stack([0.5 + x / 1.1, 0.04 + y / 1.1], -1)
    return v, np.concatenate([fan, rings]), uv


def _frames(path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Perpendicular unit frames (n1, n2) along a polyline, propagated to avoid twisting."""
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    ref = np.array([1.0, 0, 0]) if abs(tangents[0, 0]) < 0.9 else np.array([0, 1.0, 0])
    n1 = np.empty_like(path)
    prev = ref
    for i, t in enumerate(tangents):
        n = prev - np.dot(prev, t) * t
        n1[i] = n / np.linalg.norm(n)
        prev = n1[i]
    return n1, np.cross(tangents, n1)


def tube(path: np.ndarray, radii, sides: int = 6, uv_scale: float = 1.0) -> Mesh:
    """An open tube along a polyline (k,3) with per-point radii; u around, v along (metres * scale)."""
    path = np.asarray(path, np.float64)
    radii = np.broadcast_to(np.asarray(radii, np.float64), (len(path),))
    n1, n2 = _frames(path)
    angle = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(angle)[None, :, None] * n1[:, None] + np.sin(angle)[None, :, None] * n2[:, None]
    v = (path[:, None] + radii[:, None, None] * ring).reshape(-1, 3)
    along = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    uv = np.stack(np.broadcast_arrays(np.tile(angle / (2 * np.pi), len(path)),
                                      np.repeat(along * uv_scale, sides)), -1)
    return v, grid_faces(len(path), sides, wrap=True), uv


def quad(centre, x_axis, y_axis, half_x: float, half_y: float, uv_rect=(0.0, 0.0, 1.0, 1.0)) -> Mesh:
    """A rectangle facing x_axis cross y_axis; uv_rect = (u0, v0, u1, v1) maps its corners."""
    c, ex, ey = (np.asarray(a, np.float64) for a in (centre, x_axis, y_axis))
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)
    v = c + corners[:, :1] * half_x * ex + corners[:, 1:] * half_y * ey
    u0, v0, u1, v1 = uv_rect
    uv = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]]), uv


def ground_grid(lo, hi, cell: float, tile: float) -> Mesh:
    """Horizontal z = 0 grid over [lo, hi] (xy) facing +z, UVs = xy / tile (wrapping texture).

    Cells keep faces small, so surface samples can be restricted to what cameras see."""
    nx = max(1, int(np.ceil((hi[0] - lo[0]) / cell)))
    ny = max(1, int(np.ceil((hi[1] - lo[1]) / cell)))
    x, y = np.meshgrid(np.linspace(lo[0], hi[0], nx + 1), np.linspace(lo[1], hi[1], ny + 1), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], -1)
    f = grid_faces(nx + 1, ny + 1)[:, ::-1]  # counter-clockwise seen from above
    return v, f, v[:, :2] / tile


def box(centre, size, uv_scale: float = 1.0) -> Mesh:
    """Axis-aligned closed box, outward faces; UVs are metres * uv_scale on each face."""
    c, s = np.asarray(centre, np.float64), np.asarray(size, np.float64) / 2
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            a, b = [i for i in range(3) if i != axis]
            ex, ey = np.zeros(3), np.zeros(3)
            ex[a], ey[b] = 1.0, 1.0
            if np.dot(np.cross(ex, ey), normal) < 0:
                ex = -ex
            faces.append(quad(c + normal * s[axis], ex, ey, s[a], s[b],
                              (0, 0, 2 * s[a] * uv_scale, 2 * s[b] * uv_scale)))
    return merge(faces)


def disc(centre, radius: float, petals: int = 0, petal_depth: float = 0.0, segments: int = 20,
         normal_up: bool = True) -> Mesh:
    """A horizontal disc (optionally petal-shaped) with planar UVs centred at (0.5, 0.5)."""
    theta = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    r = radius * (1 - petal_depth * (0.5 - 0.5 * np.cos(petals * theta))) if petals else np.full(segments, radius)
    rim = np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros(segments)], -1)
    v = np.concatenate([[[0, 0, 0]], rim]) + np.asarray(centre, np.float64)
    f = np.stack([np.zeros(segments, int), 1 + np.arange(segments), 1 + (np.arange(segments) + 1) % segments], -1)
    if not normal_up:
        f = f[:, ::-1]
    uv = 0.5 + np.concatenate([[[0, 0]], rim[:, :2]]) / (2 * radius)
    return v, f, uv


def frustum(centre_bottom, r_bottom: float, r_top: float, height: float, sides: int = 16) -> Mesh:
    """Open-topped pot wall (a truncated cone) standing on centre_bottom."""
    c = np.asarray(centre_bottom, np.float64)
    path = np.array([c, c + [0, 0, height]])
    return tube(path, [r_bottom, r_top], sides=sides, uv_scale=1.0)
