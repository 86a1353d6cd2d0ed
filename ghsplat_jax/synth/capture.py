"""Capture paths imitating the paper's data collection.

- "handheld": a person walks a closed loop around one row (down one aisle, round the open
  end, back up the other aisle, round the closed end) at a fixed frame rate, slowing down
  at the row ends (so more views there), camera pointed at the row with smooth height,
  tilt, pan and roll jitter.
- "robot": a ground robot drives down the aisle on each side of the row at constant speed
  with a side-looking camera at robot height.

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


def _stadium(row, d: float, slowdown: float, n_views: int):
    """Positions (n,2), look-at points on the row axis (n,2) and loop phase (n,) of a walk around
    the row at lateral distance d, sampled uniformly in time with slower walking on the end arcs."""
    x0, x1, y = row.x0, row.x1, row.y
    straight, arc = x1 - x0, np.pi * d
    # segments: +y aisle (x0 -> x1), open-end arc, -y aisle (x1 -> x0), closed-end arc
    lengths = np.array([straight, arc, straight, arc])
    durations = lengths / np.array([1.0, slowdown, 1.0, slowdown])
    tau = (np.arange(n_views) + 0.5) / n_views * durations.sum()
    ends = np.cumsum(durations)
    seg = np.searchsorted(ends, tau, side="right").clip(0, 3)
    f = (tau - np.concatenate([[0], ends[:-1]])[seg]) / durations[seg]
    pos, target = np.zeros((n_views, 2)), np.zeros((n_views, 2))
    for i, (s, u) in enumerate(zip(seg, f)):
        if s == 0:
            pos[i], target[i] = [x0 + u * straight, y + d], [x0 + u * straight, y]
        elif s == 2:
            pos[i], target[i] = [x1 - u * straight, y - d], [x1 - u * straight, y]
        else:
            centre = np.array([x1, y]) if s == 1 else np.array([x0, y])
            angle = np.pi / 2 - np.pi * u + (0 if s == 1 else np.pi)
            pos[i], target[i] = centre + d * np.array([np.cos(angle), np.sin(angle)]), centre
    return pos, target, tau / durations.sum()


def capture_path(scene: Scene, kind: str = "handheld", n_views: int = 40, *, row: int = 0,
                 width: int = 640, height: int = 480, seed: int = 0,
                 config: PathConfig | None = None) -> list[Camera]:
    """Cameras along a hand-held walk around row `row` or robot drives along its aisles."""
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
        pos, target, phase = _stadium(r, d, pc.end_slowdown, n_views)
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

    raise ValueError(f"unknown capture path kind {kind!r} (use 'handheld' or 'robot')")
