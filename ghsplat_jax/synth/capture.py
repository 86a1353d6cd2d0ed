"""Capture paths imitating the paper's data collection.

- "handheld": a person walks a closed loop around one row (down one aisle, round the open
  end, back up the other aisle, round the closed end) at a fixed frame rate, slowing down
  at the row ends (so more views there), camera pointed at the row with smooth height,
  tilt, pan and roll jitter. With `PathConfig.end` the walk is a U round one end of the
  row only: the paper captured each row as two segments, one from each end.
- "robot": a ground robot drives down the aisle on each side of the row at constant speed
  with a side-looking camera at robot height.
- "orbit": a turntable-like ring round one plant of the row (`PathConfig.plant`, default the
  middle one) at `orbit_radius`, evenly spaced, looking at the plant, with small smooth height
  and angle jitter; the last view is a neighbour of the first (a closed loop). Give the plant
  room (e.g. a scene of one plant per row): the ring passes through its row-neighbours' places.

Frames are uniform in time (frame i at i / fps); `frame_times(n, fps)` gives the stamps.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.core.camera import Camera, intrinsics, look_at
from ghsplat_jax.synth.scene import Scene


@dataclasses.dataclass(frozen=True)
class PathConfig:
    height: float | None = None     # camera height (m): handheld 1.15, robot 0.5 by default
    distance: float | None = None   # lateral distance from the row axis (default: mid-aisle)
    target_height: float = 0.55     # height of the looked-at point on the row axis
    end_slowdown: float = 0.4       # walking speed at the row ends relative to the aisles
    height_jitter: float = 0.06     # metres (smooth)
    angle_jitter_deg: float = 3.0   # pan / tilt / roll (smooth)
    fov_x_deg: float = 65.0
    fps: float = 2.0
    end: str | None = None          # handheld: None walks round the whole row; "x0" / "x1" walks a
    #                                 U round that end only (one row segment, as the paper captured)
    segment_fraction: float = 0.5   # share of the row's length a one-end walk covers
    plant: int | None = None        # orbit: index of the plant along the row (default: the middle one)
    orbit_radius: float = 0.7       # orbit: ring radius round the plant, metres


def frame_times(n_views: int, fps: float) -> np.ndarray:
    return np.arange(n_views) / fps


def _smooth_jitter(rng: np.random.Generator, phase: np.ndarray, amplitude: float, harmonics: int = 3) -> np.ndarray:
    """A smooth random periodic signal of the loop phase in [0, 1), RMS about `amplitude`."""
    out = np.zeros_like(phase)
    for k in range(1, harmonics + 1):
        cycles = 3 * k + rng.integers(0, 3)  # a few wobbles per loop, more at higher harmonics
        out += rng.normal(0, 1) / k * np.sin(2 * np.pi * cycles * phase + rng.uniform(0, 2 * np.pi))
    return amplitude * out / np.sqrt(sum(1 / k ** 2 for k in range(1, harmonics + 1)) / 2)


def _euler(pan: float, tilt: float, roll: float) -> np.ndarray:
    """Small rotation applied in the camera frame (y down: pan about y, tilt about x, roll about z)."""
    cy, sy, cx, sx, cz, sz = np.cos(pan), np.sin(pan), np.cos(tilt), np.sin(tilt), np.cos(roll), np.sin(roll)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ rx @ ry


def _camera(eye, target, K, width, height, jitter=np.zeros(3)) -> Camera:
    w2c = look_at(eye, target).astype(np.float64)
    w2c[:3, :] = _euler(*jitter) @ w2c[:3, :]
    return Camera(K, w2c.astype(np.float32), width, height)


def _walk_pieces(row, end: str | None, fraction: float) -> list[tuple]:
    """The walk as pieces: ("aisle", x_from, x_to, side) along the aisle on that side of the row,
    or ("arc", x_centre, start_angle) half-circles round a row end. end=None: the closed loop
    round the whole row; "x0" / "x1": a U round that end covering `fraction` of the row."""
    x0, x1 = row.x0, row.x1
    if end is None:
        return [("aisle", x0, x1, 1.0), ("arc", x1, np.pi / 2), ("aisle", x1, x0, -1.0), ("arc", x0, -np.pi / 2)]
    cut = fraction * (x1 - x0)
    if end == "x1":
        return [("aisle", x1 - cut, x1, 1.0), ("arc", x1, np.pi / 2), ("aisle", x1, x1 - cut, -1.0)]
    if end == "x0":
        return [("aisle", x0 + cut, x0, -1.0), ("arc", x0, -np.pi / 2), ("aisle", x0, x0 + cut, 1.0)]
    raise ValueError(f"unknown row end {end!r} (use 'x0', 'x1' or None for the whole row)")


def _stadium(row, d: float, slowdown: float, n_views: int, end: str | None = None, fraction: float = 1.0):
    """Positions (n,2), look-at points on the row axis (n,2) and walk phase (n,) of a walk round
    the row (or round one end of it, see _walk_pieces) at lateral distance d, sampled uniformly
    in time with slower walking on the end arcs."""
    pieces = _walk_pieces(row, end, fraction)
    lengths = np.array([abs(p[2] - p[1]) if p[0] == "aisle" else np.pi * d for p in pieces])
    durations = lengths / np.array([1.0 if p[0] == "aisle" else slowdown for p in pieces])
    tau = (np.arange(n_views) + 0.5) / n_views * durations.sum()
    ends = np.cumsum(durations)
    seg = np.searchsorted(ends, tau, side="right").clip(0, len(pieces) - 1)
    f = (tau - np.concatenate([[0], ends[:-1]])[seg]) / durations[seg]
    pos, target = np.zeros((n_views, 2)), np.zeros((n_views, 2))
    for i, (s, u) in enumerate(zip(seg, f)):
        piece = pieces[s]
        if piece[0] == "aisle":
            _, xa, xb, side = piece
            x = xa + u * (xb - xa)
            pos[i], target[i] = [x, row.y + side * d], [x, row.y]
        else:
            _, xc, start = piece
            angle = start - np.pi * u
            centre = np.array([xc, row.y])
            pos[i], target[i] = centre + d * np.array([np.cos(angle), np.sin(angle)]), centre
    return pos, target, tau / durations.sum()


def capture_path(scene: Scene, kind: str = "handheld", n_views: int = 40, *, row: int = 0,
                 width: int = 640, height: int = 480, seed: int = 0,
                 config: PathConfig | None = None) -> list[Camera]:
    """Cameras along a hand-held walk around row `row`, robot drives along its aisles, or a
    ring round one of its plants ("orbit")."""
    pc = config or PathConfig()
    if not 0 <= row < len(scene.rows):
        raise ValueError(f"row {row} does not exist (scene has {len(scene.rows)} rows)")
    if n_views < 1:
        raise ValueError("n_views must be >= 1")
    r = scene.rows[row]
    aisle = scene.config.layout.row_spacing / 2
    d = pc.distance if pc.distance is not None else aisle
    K = intrinsics(width, height, pc.fov_x_deg)
    rng = np.random.default_rng([seed, row, 0 if kind == "handheld" else 1])

    if kind == "handheld":
        h = pc.height if pc.height is not None else 1.15
        if not 0 < pc.segment_fraction <= 1:
            raise ValueError(f"segment_fraction must be in (0, 1], got {pc.segment_fraction}")
        pos, target, phase = _stadium(r, d, pc.end_slowdown, n_views, pc.end, pc.segment_fraction)
        heights = h + _smooth_jitter(rng, phase, pc.height_jitter) + rng.normal(0, pc.height_jitter / 6, n_views)
        angles = np.stack([_smooth_jitter(rng, phase, np.deg2rad(pc.angle_jitter_deg)) for _ in range(3)], -1)
        angles += rng.normal(0, np.deg2rad(pc.angle_jitter_deg) / 5, angles.shape)
        return [_camera([*p, z], [*q, pc.target_height], K, width, height, a)
                for p, q, z, a in zip(pos, target, heights, angles)]

    if kind == "robot":
        h = pc.height if pc.height is not None else 0.5
        half = n_views - n_views // 2
        margin = 0.3
        cams = []
        for side, count in ((1.0, half), (-1.0, n_views - half)):
            xs = np.linspace(r.x0 - margin, r.x1 + margin, count) if count > 1 else np.array([(r.x0 + r.x1) / 2])
            if side < 0:
                xs = xs[::-1]  # drive back along the other aisle
            for x in xs:
                eye = [x, r.y + side * d, h + rng.normal(0, 0.003)]
                jitter = rng.normal(0, np.deg2rad(0.3), 3)  # floor vibration
                cams.append(_camera(eye, [x, r.y, h + 0.1], K, width, height, jitter))
        return cams

    if kind == "orbit":
        h = pc.height if pc.height is not None else 1.1
        count = scene.config.layout.plants_per_row
        plant = count // 2 if pc.plant is None else pc.plant
        if not 0 <= plant < count:
            raise ValueError(f"plant {plant} does not exist (row has {count} plants)")
        if pc.orbit_radius <= 0:
            raise ValueError(f"orbit_radius must be > 0, got {pc.orbit_radius}")
        centre = np.array([(plant + 0.5) * scene.config.layout.plant_spacing, r.y])
        phase = np.arange(n_views) / n_views
        angle = 2 * np.pi * phase - np.pi / 2  # starts on the -y side, turns counter-clockwise
        heights = h + _smooth_jitter(rng, phase, pc.height_jitter / 3)
        angles = np.stack([_smooth_jitter(rng, phase, np.deg2rad(pc.angle_jitter_deg) / 3) for _ in range(3)], -1)
        pos = centre + pc.orbit_radius * np.stack([np.cos(angle), np.sin(angle)], -1)
        return [_camera([*p, z], [*centre, pc.target_height], K, width, height, a)
                for p, z, a in zip(pos, heights, angles)]

    raise ValueError(f"unknown capture path kind {kind!r} (use 'handheld', 'robot' or 'orbit')")
