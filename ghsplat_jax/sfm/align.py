"""Greenhouse alignment: a similarity that puts z up, the row along x, its open end at +x.

Spherical-harmonic colours are orientation-aware, so a reconstruction is aligned to the
greenhouse frame (metres, z up, rows along +x, a row's open end toward +x) before any
training. Everything here is a pure function on numpy arrays (camera `world_to_cam`
matrices in the OpenCV convention and sparse points), testable without pycolmap.

The rules, in order:

- **Up.** First a hint from the cameras: a hand-held camera is mostly upright, so the
  mean of the cameras' up vectors (-y of the OpenCV camera, in world) points up; its
  component along the mean right vector is removed, because pitching the camera down
  at the plants tilts its up vector about the right axis but keeps the right axis
  level. Then a ground plane is fitted to the sparse points: RANSAC over planes whose
  normal lies within `max_ground_tilt_deg` of the hint and that lie below the median
  camera, refined by a robust (Cauchy) least-squares fit with optimistix
  Levenberg-Marquardt. When the plane holds at least `min_ground_fraction` of the
  points its normal is the up axis (the camera hint is biased by any systematic
  pitch or roll); otherwise the camera hint is used.
- **Row axis.** The principal direction, in the ground plane, of the camera path and of
  the plant points (points above the ground), each counted only when clearly elongated
  (1 - minor/major eigenvalue >= 0.5; a loop round a short row is not) and weighted by
  that elongation.
- **Sign (row end toward +x).** The open end of a row faces the main path, and end-on
  views of a row are taken from there looking into the row: when at least 3 cameras
  look within `end_on_deg` of the row axis and two thirds of them look the same way,
  +x is opposite to that way. Otherwise (no end-on views, or a loop around the row that
  sees both ends alike) the capture is taken to begin moving toward the open end, as
  the procedural captures of ghsplat_jax.synth do (hand-held loops and robot drives
  start at the closed end): +x is the direction of the first clear move along the row
  (a quarter of the path's length) in capture (image-name) order. The report names the
  rule used; `flip` turns the result around when a capture follows another habit.
- **Origin and scale.** x = y = 0 below the median sparse point, z = 0 on the ground
  plane (or the 2nd percentile of point heights when no plane was found). Scale is 1
  unless a metric cue is given: an explicit factor, the true mean camera height above
  the ground, or the true distance between two camera centres.
- **Manual override.** `rotation` replaces the automatic up/row estimate; `yaw_deg`
  and `flip` (180 degrees about z) are applied after either.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np


@dataclasses.dataclass(frozen=True)
class AlignOptions:
    """How to align; defaults are fully automatic at the reconstruction's own scale."""

    rotation: np.ndarray | None = None  # manual new_from_old 3x3 rotation; skips up/row estimation
    yaw_deg: float = 0.0  # extra rotation about the final z axis, degrees
    flip: bool = False  # turn 180 degrees about z: the row end goes to -x
    scale: float | None = None  # explicit metric scale factor (new units per old unit)
    camera_height: float | None = None  # true mean camera height above the ground, metres
    known_distance: tuple[int, int, float] | None = None  # (camera i, camera j, metres)
    min_ground_fraction: float = 0.05  # inlier share for the ground plane to set up
    max_ground_tilt_deg: float = 45.0  # ground normal within this of the camera up hint
    plane_threshold: float | None = None  # RANSAC inlier distance; default 1% of extent
    end_on_deg: float = 45.0  # a camera looking within this of the row axis is end-on
    ransac_iterations: int = 500
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class Alignment:
    """The applied similarity `new = scale * rotation @ old + translation`, and how it was found."""

    rotation: np.ndarray  # (3,3) new_from_old
    translation: np.ndarray  # (3,)
    scale: float
    up: np.ndarray  # (3,) up axis in the old frame
    row: np.ndarray  # (3,) +x (row end) axis in the old frame
    up_source: str  # "ground_plane", "camera_up" or "manual"
    row_source: str  # "camera_path+plants", "camera_path", "plants" or "manual"
    sign_rule: str  # "end_on_views", "capture_direction", "undetermined" or "manual"
    scale_source: str  # "none", "explicit", "camera_height" or "known_distance"
    ground_fraction: float  # share of points on the fitted ground plane (0 if none)
    camera_up_angle_deg: float  # angle between the camera up hint and the chosen up

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 similarity new_from_old."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def to_json(self) -> dict:
        return {
            "matrix": self.matrix.tolist(),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "scale": float(self.scale),
            "up_in_input_frame": self.up.tolist(),
            "row_in_input_frame": self.row.tolist(),
            "up_source": self.up_source,
            "row_source": self.row_source,
            "sign_rule": self.sign_rule,
            "scale_source": self.scale_source,
            "ground_fraction": float(self.ground_fraction),
            "camera_up_angle_deg": float(self.camera_up_angle_deg),
        }


# ---------------------------------------------------------------------------- small helpers


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors in degrees."""
    c = np.dot(_unit(np.asarray(a, float)), _unit(np.asarray(b, float)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rotation_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_centres(world_to_cam: np.ndarray) -> np.ndarray:
    """(N,3) camera centres from (N,4,4) world_to_cam."""
    rot, t = world_to_cam[:, :3, :3], world_to_cam[:, :3, 3]
    return -np.einsum("nji,nj->ni", rot, t)


def camera_up_hint(world_to_cam: np.ndarray) -> np.ndarray:
    """Up from the cameras: mean of -y (OpenCV), made perpendicular to the mean right (+x)."""
    rot = world_to_cam[:, :3, :3]
    up = _unit(-rot[:, 1, :].mean(0))
    right = rot[:, 0, :].mean(0)
    if np.linalg.norm(right) > 0.5:  # rights agree: the cameras were not rolled about
        right = _unit(right)
        up = _unit(up - np.dot(up, right) * right)
    return up


def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """Rows e1, e2, n: an orthonormal basis whose last row is `normal`."""
    helper = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = _unit(np.cross(normal, helper))
    return np.stack([e1, np.cross(normal, e1), normal])


def _plane_threshold(points: np.ndarray, options: AlignOptions) -> float:
    """Ground-plane inlier distance: as given, else 1% of the points' robust extent."""
    if options.plane_threshold is not None:
        return options.plane_threshold
    lo, hi = np.percentile(points, [5, 95], axis=0)
    return 0.01 * float(np.linalg.norm(hi - lo))


# ---------------------------------------------------------------------------- ground plane


def ransac_plane(
    points: np.ndarray,
    up_hint: np.ndarray,
    threshold: float,
    max_tilt_deg: float,
    below: np.ndarray | None = None,
    iterations: int = 500,
    seed: int = 0,
    max_below_fraction: float = 0.15,
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """The ground-like plane n.p = d with most inliers, or None: (n, d, inlier mask).

    A candidate qualifies when its normal lies within `max_tilt_deg` of `up_hint`, the
    point `below` (the median camera) is above it, at most `max_below_fraction` of the
    points lie more than 3 thresholds below it (the ground is the bottom of the scene),
    and its band holds at least twice the points of the band just above it (a surface,
    not a slice through a volume of foliage).
    """
    if len(points) < 3:
        return None
    rng = np.random.default_rng(seed)
    if len(points) > 20000:  # plenty for a plane; keeps the score matrix small
        points_eval = points[rng.choice(len(points), 20000, replace=False)]
    else:
        points_eval = points
    samples = points[rng.integers(0, len(points), size=(iterations, 3))]
    normals = np.cross(samples[:, 1] - samples[:, 0], samples[:, 2] - samples[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12
    normals = normals[ok] / norms[ok, None]
    normals *= np.sign(normals @ up_hint)[:, None]  # orient along the hint
    offsets = np.einsum("ni,ni->n", normals, samples[ok, 0])
    keep = normals @ up_hint >= np.cos(np.radians(max_tilt_deg))
    if below is not None:  # the ground lies below the cameras
        keep &= normals @ below > offsets
    if not keep.any():
        return None
    normals, offsets = normals[keep], offsets[keep]
    signed = points_eval @ normals.T - offsets
    counts = (np.abs(signed) < threshold).sum(0)
    above = ((signed >= threshold) & (signed < 3 * threshold)).sum(0)
    under = (signed < -3 * threshold).mean(0)
    valid = (under <= max_below_fraction) & (counts >= 2 * above)
    if not valid.any():
        return None
    best = int(np.argmax(np.where(valid, counts, -1)))
    inliers = np.abs(points @ normals[best] - offsets[best]) < threshold
    return normals[best], float(offsets[best]), inliers


@functools.cache
def _plane_solver():
    """A jit-compiled robust plane fit; inputs are padded to power-of-two sizes so that
    repeated alignments reuse a handful of compilations."""
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    def residuals(params, args):
        xyz, mask = args
        a, b, c = params
        r = (xyz[:, 2] - a * xyz[:, 0] - b * xyz[:, 1] - c) / jnp.sqrt(1 + a * a + b * b)
        u = r * r
        safe = jnp.where(u > 1e-6, u, 1.0)
        weight = jnp.where(u > 1e-6, jnp.sqrt(jnp.log1p(safe) / safe), 1.0 - u / 4)
        return r * weight * mask

    @jax.jit
    def solve(xyz, mask):
        solver = optx.LevenbergMarquardt(rtol=1e-7, atol=1e-9)
        sol = optx.least_squares(
            residuals, solver, jnp.zeros(3, xyz.dtype), args=(xyz, mask), max_steps=200,
            throw=False,
        )
        return sol.value

    return solve


def refine_plane(points: np.ndarray, normal: np.ndarray, offset: float, loss_scale: float):
    """Robust least-squares plane through `points` from an initial (normal, offset).

    The plane is z = a x + b y + c in a frame whose z is the initial normal (well
    conditioned near the start), in units of `loss_scale`; residuals are orthogonal
    distances under a Cauchy loss, written as r * sqrt(rho(r) / r^2) so that
    0.5 * sum(res^2) is the Cauchy cost and the residual stays smooth at 0. Solved with
    optimistix Levenberg-Marquardt.
    """
    basis = _plane_basis(normal)
    centre = points.mean(0)
    anchor = normal * offset + (centre - normal * (centre @ normal))
    local = (points - anchor) @ basis.T / loss_scale
    size = max(256, 1 << int(np.ceil(np.log2(len(local)))))
    xyz = np.zeros((size, 3), np.float32)
    xyz[: len(local)] = local
    mask = np.zeros(size, np.float32)
    mask[: len(local)] = 1.0
    a, b, c = (float(v) for v in np.asarray(_plane_solver()(xyz, mask), np.float64))
    if not np.all(np.isfinite([a, b, c])):
        return normal, offset
    new_normal = basis.T @ _unit(np.array([-a, -b, 1.0]))
    point = anchor + loss_scale * c * basis[2]
    return new_normal, float(new_normal @ point)


def fit_ground_plane(
    points: np.ndarray, up_hint: np.ndarray, centres: np.ndarray, options: AlignOptions
) -> tuple[np.ndarray, float, float] | None:
    """(normal, offset, inlier fraction) of the ground, or None when no plane qualifies."""
    threshold = _plane_threshold(points, options)
    found = ransac_plane(
        points, up_hint, threshold, options.max_ground_tilt_deg,
        below=np.median(centres, axis=0), iterations=options.ransac_iterations,
        seed=options.seed,
    )
    if found is None:
        return None
    normal, offset, inliers = found
    fraction = float(inliers.mean())
    if fraction < options.min_ground_fraction or inliers.sum() < 10:
        return None
    # Refine on a band around the RANSAC plane: the Cauchy loss handles what is left.
    band = np.abs(points @ normal - offset) < 3 * threshold
    normal, offset = refine_plane(points[band], normal, offset, threshold)
    return normal, offset, fraction


# ---------------------------------------------------------------------------- row axis


def principal_direction(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Major axis of 2D points and its elongation 1 - minor/major eigenvalue (0 if < 2 points)."""
    if len(xy) < 2:
        return np.array([1.0, 0.0]), 0.0
    centred = xy - np.median(xy, axis=0)
    values, vectors = np.linalg.eigh(centred.T @ centred / len(xy))
    if values[1] <= 0:
        return np.array([1.0, 0.0]), 0.0
    return vectors[:, 1], float(1.0 - values[0] / values[1])


def row_axis(
    centres: np.ndarray, plant_points: np.ndarray, basis: np.ndarray, min_elongation: float = 0.5
) -> tuple[np.ndarray, str]:
    """Row direction (unsigned, in the old frame) from the camera path and the plant points.

    Each source counts only when clearly elongated (a loop or U-turn round a short row is
    not); the qualifying directions are averaged as direction tensors weighted by their
    elongation. Failing both, the more elongated source is used.
    """
    found = {}
    for name, pts in (("camera_path", centres), ("plants", plant_points)):
        direction, elongation = principal_direction(pts @ basis[:2].T)
        found[name] = (direction, elongation)
    used = [n for n, (_, e) in found.items() if e >= min_elongation]
    if not used:
        best = max(found, key=lambda n: found[n][1])
        used = [best] if found[best][1] > 0.05 else []
    if not used:
        return basis[0], "undetermined"
    tensor = sum(found[n][1] * np.outer(found[n][0], found[n][0]) for n in used)
    direction = np.linalg.eigh(tensor)[1][:, 1]
    return _unit(direction @ basis[:2]), "+".join(used)


def row_sign(
    axis: np.ndarray, up: np.ndarray, world_to_cam: np.ndarray, end_on_deg: float
) -> tuple[float, str]:
    """+1 or -1 so that `sign * axis` points at the row's open end (see module docstring)."""
    forward = world_to_cam[:, 2, :3]
    level = forward - np.outer(forward @ up, up)
    norms = np.linalg.norm(level, axis=1)
    usable = norms > 0.3  # cameras looking nearly straight down say nothing about the row
    cosines = (level[usable] @ axis) / norms[usable]
    looks = np.sign(cosines[np.abs(cosines) >= np.cos(np.radians(end_on_deg))])
    # Decisive only when most end-on views agree: a loop around the row sees both ends.
    if len(looks) >= 3 and abs(looks.sum()) >= len(looks) / 3:
        return (-1.0 if looks.sum() > 0 else 1.0), "end_on_views"
    along = (camera_centres(world_to_cam) @ axis)
    along = along - along[0]
    span = np.ptp(along)
    if span > 0:
        first = int(np.argmax(np.abs(along) >= 0.25 * span))  # first clear move along the row
        return (1.0 if along[first] > 0 else -1.0), "capture_direction"
    return 1.0, "undetermined"


# ---------------------------------------------------------------------------- the alignment


def _scale_from_cues(
    options: AlignOptions, centres: np.ndarray, heights: np.ndarray | None
) -> tuple[float, str]:
    cues = [options.scale is not None, options.camera_height is not None,
            options.known_distance is not None]
    if sum(cues) > 1:
        raise ValueError("give at most one of scale, camera_height and known_distance")
    if options.scale is not None:
        if not options.scale > 0:
            raise ValueError(f"scale must be positive, got {options.scale}")
        return float(options.scale), "explicit"
    if options.camera_height is not None:
        if heights is None:
            raise ValueError("camera_height needs a ground plane, and none was found")
        median = float(np.median(heights))
        if median <= 0:
            raise ValueError("the cameras are not above the fitted ground plane")
        return options.camera_height / median, "camera_height"
    if options.known_distance is not None:
        i, j, metres = options.known_distance
        n = len(centres)
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise ValueError(f"known_distance camera indices {i}, {j} not valid for {n} cameras")
        gap = float(np.linalg.norm(centres[i] - centres[j]))
        if gap <= 0:
            raise ValueError(f"cameras {i} and {j} share a centre: no scale from their distance")
        return metres / gap, "known_distance"
    return 1.0, "none"


def _check_rotation(rotation) -> np.ndarray:
    rot = np.asarray(rotation, float).reshape(3, 3)
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-3) or np.linalg.det(rot) < 0:
        raise ValueError(f"manual rotation is not a proper rotation matrix:\n{rot}")
    return rot


def estimate_alignment(
    world_to_cam: np.ndarray, points: np.ndarray, options: AlignOptions = AlignOptions()
) -> Alignment:
    """The greenhouse alignment of cameras (N,4,4), in capture order, and points (M,3)."""
    world_to_cam = np.asarray(world_to_cam, float)
    points = np.asarray(points, float).reshape(-1, 3)
    if world_to_cam.ndim != 3 or world_to_cam.shape[1:] != (4, 4) or len(world_to_cam) < 2:
        raise ValueError(f"need at least 2 cameras as (N,4,4) world_to_cam, got {world_to_cam.shape}")
    centres = camera_centres(world_to_cam)
    hint = camera_up_hint(world_to_cam)
    ground = fit_ground_plane(points, hint, centres, options) if len(points) >= 10 else None

    if options.rotation is not None:
        rotation = _check_rotation(options.rotation)
        up_source = row_source = sign_rule = "manual"
    else:
        up, up_source = (ground[0], "ground_plane") if ground is not None else (hint, "camera_up")
        basis = _plane_basis(up)
        if ground is not None:  # plants: clearly above the ground
            plants = points[points @ up - ground[1] > 3 * _plane_threshold(points, options)]
        else:
            plants = points
        row, row_source = row_axis(centres, plants, basis)
        sign, sign_rule = row_sign(row, up, world_to_cam, options.end_on_deg)
        row = sign * row
        rotation = np.stack([row, np.cross(up, row), up])
    rotation = rotation_z(options.yaw_deg + (180.0 if options.flip else 0.0)) @ rotation

    # Origin below the median point; z = 0 on the ground plane when it agrees with the
    # final z axis, else at a low percentile of the point heights.
    ref = points if len(points) else centres
    rotated = ref @ rotation.T
    x0, y0 = np.median(rotated[:, :2], axis=0)
    use_plane = ground is not None and angle_deg(ground[0], rotation[2]) < 10.0
    if use_plane:
        n = rotation @ ground[0]  # plane n . p = d in the rotated frame
        z0 = (ground[1] - n[0] * x0 - n[1] * y0) / n[2]
        heights = centres @ ground[0] - ground[1]
    else:
        z0 = float(np.percentile(rotated[:, 2], 2))
        heights = None
    scale, scale_source = _scale_from_cues(options, centres, heights)
    translation = -scale * np.array([x0, y0, z0])
    return Alignment(
        rotation=rotation, translation=translation, scale=scale, up=rotation[2], row=rotation[0],
        up_source=up_source, row_source=row_source, sign_rule=sign_rule,
        scale_source=scale_source, ground_fraction=ground[2] if ground is not None else 0.0,
        camera_up_angle_deg=angle_deg(hint, rotation[2]),
    )


def transform_points(alignment: Alignment, points: np.ndarray) -> np.ndarray:
    """Points (M,3) in the aligned frame."""
    return alignment.scale * np.asarray(points) @ alignment.rotation.T + alignment.translation


def transform_world_to_cam(alignment: Alignment, world_to_cam: np.ndarray) -> np.ndarray:
    """Cameras (N,4,4) in the aligned frame (rigid: camera coordinates scale with the world)."""
    rot, t = world_to_cam[..., :3, :3], world_to_cam[..., :3, 3]
    new = np.array(world_to_cam, float, copy=True)
    new[..., :3, :3] = rot @ alignment.rotation.T
    new[..., :3, 3] = alignment.scale * t - np.einsum(
        "...ij,j->...i", rot @ alignment.rotation.T, alignment.translation
    )
    return new


def load_align_config(path: Path | None) -> dict:
    """The alignment settings of a TOML or JSON file (an [align] table or the whole file),
    keys checked; {} without a file. Error texts name the `--align-config` option."""
    if path is None:
        return {}
    import json
    import tomllib

    try:
        text = path.read_text()
        config = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except FileNotFoundError as exc:
        raise ValueError(f"--align-config {path}: no such file") from exc
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"--align-config {path}: cannot parse ({exc})") from exc
    config = config.get("align", config)  # allow an [align] table
    allowed = {"rotation", "yaw_deg", "flip", "scale", "camera_height", "known_distance"}
    unknown = set(config) - allowed
    if unknown:
        raise ValueError(f"--align-config {path}: unknown keys {sorted(unknown)}; allowed {sorted(allowed)}")
    return config
