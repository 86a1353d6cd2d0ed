"""AprilTag 36h11 markers made of surfels, with their ground-truth poses.

Bits come from cv2.aruco (the 8x8 cell image including the one-cell black border). The
physical `size` is the black border's edge (ArUco/AprilTag convention), so a cell is
size/8. A white quiet zone (default one cell) surrounds the border; an optional backing
plate sits just behind. Each cell is a `subdiv` x `subdiv` grid of small square-ish,
nearly opaque surfels whose sigma (0.7 x pitch) tiles the cell without gaps while
keeping edges sharp (the tail beyond a cell edge is a fraction of a cell).
Tag frame = tags.py: origin at the centre, x right, y up, z out of the printed face.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.core.surfels import Surfels
from ghsplat_jax.scene import surfaces
from ghsplat_jax.scene.tags import Tag

CELLS = 8  # 6x6 data bits + 1-cell black border


@dataclasses.dataclass(frozen=True)
class Backing:
    """A plate behind the tag: `margin` (m) beyond the quiet zone on every side."""
    margin: float = 0.02
    thickness: float = 0.01  # >= ~2 sigma of the tag surfels keeps the back face behind at 45 deg
    colour: tuple = (0.55, 0.55, 0.55)


def tag_bits(tag_id: int) -> np.ndarray:
    """(8,8) array, 1 = white, row 0 at the top of the printed tag."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    count = dictionary.bytesList.shape[0]
    if not 0 <= int(tag_id) < count:
        raise ValueError(f"AprilTag 36h11 id must be in 0..{count - 1}, got {tag_id}")
    img = cv2.aruco.generateImageMarker(dictionary, int(tag_id), CELLS, borderBits=1)
    return (img > 127).astype(np.uint8)


def tag_pose(position, facing=None, up=(0.0, 0.0, 1.0), euler_deg=None) -> np.ndarray:
    """world_from_tag (4,4): either tag z along `facing` (the direction the printed face
    looks) with tag y as close to `up` as possible, or explicit xyz Euler angles (degrees)."""
    T = np.eye(4)
    T[:3, 3] = np.asarray(position, np.float64)
    if euler_deg is not None:
        from ghsplat_jax.scene.transform import rotation_from_euler

        T[:3, :3] = rotation_from_euler(euler_deg)
        return T
    z = np.asarray((1.0, 0.0, 0.0) if facing is None else facing, np.float64)
    z = z / np.linalg.norm(z)
    up = np.asarray(up, np.float64)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"tag facing {z.tolist()} is parallel to up {up.tolist()}; give another up")
    x /= np.linalg.norm(x)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    return T


def marker_surfels_tag_frame(tag_id: int, size: float, subdiv: int = 4, quiet_zone: float = 1.0,
                             backing: Backing | None = None, overlap: float = 0.7,
                             sh_degree: int = 0, black: float = 0.0, white: float = 1.0) -> Surfels:
    """Surfels of one marker in its own tag frame (printed face at z = 0, facing +z)."""
    from ghsplat_jax.scene.merge import merge

    if not size > 0:
        raise ValueError(f"marker size must be positive, got {size}")
    if subdiv < 1 or quiet_zone < 0:
        raise ValueError("subdiv must be >= 1 and quiet_zone >= 0")
    bits = tag_bits(tag_id)
    cell = size / CELLS
    q = int(np.ceil(quiet_zone))
    # pad the cell image with white quiet-zone cells (rounded up to whole cells, then cut)
    grid = np.pad(bits, q, constant_values=1)
    n = CELLS + 2 * q
    pitch = cell / subdiv
    k = np.arange(n * subdiv)
    centres = (k + 0.5) * pitch - n * cell / 2  # x increases to the right, from the left edge
    X, Y = np.meshgrid(centres, -centres)  # image row 0 is the top: y decreases with row
    rows, cols = np.meshgrid(k // subdiv, k // subdiv, indexing="ij")
    half = (CELLS / 2 + quiet_zone) * cell
    inside = (np.abs(X) < half) & (np.abs(Y) < half)
    value = np.where(grid[rows, cols] > 0, white, black)[inside]
    points = np.stack([X[inside], Y[inside], np.zeros(inside.sum())], axis=1)
    count = len(points)
    # Shuffled order: coplanar surfels at equal depth composite in index order, and a
    # row-major order would let one colour win every edge on one side, shifting the tag by
    # a fraction of a pixel; a random order makes the edge symmetric (pose errors ~halve).
    parts = [surfaces.surfels_from_samples(
        points, np.broadcast_to([0.0, 0.0, 1.0], (count, 3)), np.broadcast_to([1.0, 0.0, 0.0], (count, 3)),
        np.repeat(value[:, None], 3, axis=1), overlap * pitch, sh_degree=sh_degree)]
    if backing is not None:
        plate = _backing(half, backing, pitch, sh_degree)
        parts += [plate] if plate is not None else []
    parts[0] = parts[0].take(np.random.default_rng(int(tag_id)).permutation(parts[0].num))
    return merge(parts)


def _backing(half: float, backing: Backing, pitch: float, sh_degree: int) -> Surfels:
    """Plate around and behind the tag: a front frame coplanar with the tag (nothing sits
    behind the printed face, because a 2DGS renderer sorts by surfel centre depth and a
    close plate surfel could win over the tag at oblique views), four sides and a back face."""
    from ghsplat_jax.scene.merge import merge

    colour = surfaces.constant_colour(backing.colour)
    h, m, t = half + backing.margin, backing.margin, backing.thickness
    e = np.eye(3)
    parts = []
    if m > 0:
        for sign in (1.0, -1.0):  # top/bottom strips span the full width, left/right the rest
            parts.append(surfaces.rectangle([0, sign * (half + m / 2), 0], e[0], e[1], 2 * h, m,
                                            pitch, colour, sh_degree=sh_degree))
            parts.append(surfaces.rectangle([sign * (half + m / 2), 0, 0], e[0], e[1], m, 2 * half,
                                            pitch, colour, sh_degree=sh_degree))
    if t > 0:
        parts.append(surfaces.box([-h, -h, -t], [h, h, 0.0], pitch, colour,
                                  faces=("+x", "-x", "+y", "-y", "-z"), overlap=1.0,
                                  sh_degree=sh_degree))  # denser: hides the tag from behind
    return merge(parts) if parts else None


def marker_surfels(tag_id: int, size: float, world_from_tag, **kwargs) -> tuple[Surfels, Tag]:
    """(surfels in the world, Tag ground truth) for one marker at `world_from_tag`."""
    from ghsplat_jax.scene.transform import similarity

    T = np.asarray(world_from_tag, np.float64)
    R = T[:3, :3]
    if T.shape != (4, 4) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(f"marker {tag_id}: world_from_tag must be a rigid 4x4 transform")
    local = marker_surfels_tag_frame(tag_id, size, **kwargs)
    return similarity(local, 1.0, R, T[:3, 3]), Tag(int(tag_id), float(size), T)
