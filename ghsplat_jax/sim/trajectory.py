"""Robot trajectories in simulated time: waypoint files, differential-drive kinematics
from velocity commands, and aisle-following paths between crop rows.

A Trajectory is a time-stamped planar pose sequence (t, x, y, yaw); `at(t)` interpolates
(yaw on the circle), `sample(rate)` gives poses on a fixed clock.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import tomllib
from pathlib import Path

import numpy as np


@dataclasses.dataclass(frozen=True)
class Trajectory:
    t: np.ndarray    # (N,) seconds, strictly increasing
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray  # radians

    def __post_init__(self):
        arrays = [np.asarray(a, np.float64) for a in (self.t, self.x, self.y, self.yaw)]
        if len({a.shape for a in arrays}) != 1 or arrays[0].ndim != 1 or len(arrays[0]) < 1:
            raise ValueError("trajectory arrays must be 1-D of one length >= 1")
        if not all(np.all(np.isfinite(a)) for a in arrays):
            raise ValueError("trajectory has non-finite values")
        if np.any(np.diff(arrays[0]) <= 0):
            raise ValueError("trajectory times must increase strictly")
        for name, a in zip(("t", "x", "y", "yaw"), arrays):
            object.__setattr__(self, name, a)

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def at(self, t) -> np.ndarray:
        """(..., 3) poses x, y, yaw at times t (clamped to the ends)."""
        t = np.asarray(t, np.float64)
        x = np.interp(t, self.t, self.x)
        y = np.interp(t, self.t, self.y)
        # Interpolate the unwrapped angle so a turn through +-pi does not spin backwards.
        yaw = np.interp(t, self.t, np.unwrap(self.yaw))
        return np.stack([x, y, np.arctan2(np.sin(yaw), np.cos(yaw))], axis=-1)

    def sample(self, rate_hz: float, start: float | None = None,
               end: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        start = self.t[0] if start is None else start
        end = self.t[-1] if end is None else end
        times = start + np.arange(int(np.floor((end - start) * rate_hz + 1e-9)) + 1) / rate_hz
        return times, self.at(times)

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """Forward speed and yaw rate per segment."""
        dt = np.diff(self.t)
        ds = np.hypot(np.diff(self.x), np.diff(self.y))
        dyaw = np.diff(np.unwrap(self.yaw))
        return ds / dt, dyaw / dt


# ----------------------------------------------------------------------- differential drive

def integrate_twist(v, w, dt: float, start=(0.0, 0.0, 0.0), t0: float = 0.0) -> Trajectory:
    """Exact unicycle integration of velocity commands (v m/s, w rad/s), each held for dt."""
    v, w = np.broadcast_arrays(np.atleast_1d(np.asarray(v, np.float64)), np.atleast_1d(np.asarray(w, np.float64)))
    x, y, yaw = (float(s) for s in start)
    out = [(x, y, yaw)]
    for vi, wi in zip(v, w):
        if abs(wi) < 1e-9:
            x += vi * dt * np.cos(yaw)
            y += vi * dt * np.sin(yaw)
        else:  # arc of radius v/w
            x += vi / wi * (np.sin(yaw + wi * dt) - np.sin(yaw))
            y -= vi / wi * (np.cos(yaw + wi * dt) - np.cos(yaw))
        yaw += wi * dt
        out.append((x, y, yaw))
    p = np.asarray(out)
    return Trajectory(t0 + dt * np.arange(len(p)), p[:, 0], p[:, 1], p[:, 2])


def wheels_to_twist(left: np.ndarray, right: np.ndarray, track: float, wheel_radius: float):
    """Wheel angular speeds (rad/s) -> (v, w) of a differential drive."""
    vl, vr = np.asarray(left) * wheel_radius, np.asarray(right) * wheel_radius
    return (vl + vr) / 2, (vr - vl) / track


def clamp_twist(v, w, max_speed: float, max_yaw_rate: float):
    return np.clip(v, -max_speed, max_speed), np.clip(w, -max_yaw_rate, max_yaw_rate)


# ------------------------------------------------------------------------------- waypoints

def from_waypoints(points: np.ndarray, speed: float = 0.5, yaw=None, times=None,
                   turn_rate: float = 1.0) -> Trajectory:
    """Constant-speed path through (x, y) waypoints heading along each segment.

    At a corner the robot turns in place at `turn_rate` rad/s (as a differential drive
    can), so the heading is always the direction of travel. Explicit `times` and `yaw`
    (per waypoint) override both.
    """
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise ValueError("need at least two (x, y) waypoints")
    if times is not None:
        t = np.asarray(times, np.float64)
        if yaw is None:
            seg = np.diff(p, axis=0)
            heading = np.arctan2(seg[:, 1], seg[:, 0])
            yaw = np.append(heading, heading[-1])
        return Trajectory(t, p[:, 0], p[:, 1], np.asarray(yaw, np.float64))
    if speed <= 0:
        raise ValueError("speed must be positive")
    keep = np.append(True, np.hypot(*np.diff(p, axis=0).T) > 1e-9)  # drop repeated points
    p = p[keep]
    seg = np.diff(p, axis=0)
    heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
    ts, xs, ys, yaws = [0.0], [p[0, 0]], [p[0, 1]], [heading[0]]
    for i, h in enumerate(heading):
        turn = abs(h - yaws[-1])
        if turn > 1e-9:  # rotate in place
            ts.append(ts[-1] + turn / turn_rate); xs.append(xs[-1]); ys.append(ys[-1]); yaws.append(h)
        ts.append(ts[-1] + np.hypot(*seg[i]) / speed); xs.append(p[i + 1, 0]); ys.append(p[i + 1, 1]); yaws.append(h)
    if yaw is not None:
        raise ValueError("per-waypoint yaw needs explicit times")
    return Trajectory(np.array(ts), np.array(xs), np.array(ys), np.array(yaws))


def load_waypoints(path: str | os.PathLike, speed: float = 0.5) -> Trajectory:
    """Waypoints from CSV (header x,y[,yaw][,t]), JSON ({"waypoints": [{x, y, yaw?, t?}]}
    or a list of such objects or of [x, y] pairs) or TOML ([[waypoint]] x=.. y=..).
    yaw in radians; with `t` the times are used as given, otherwise `speed`."""
    path = Path(path)
    try:
        suffix = path.suffix.lower()
        if suffix == ".csv":
            with open(path, newline="") as fh:
                rows = [{k.strip(): float(v) for k, v in r.items() if k is not None and v not in (None, "")}
                        for r in csv.DictReader(fh)]
        elif suffix == ".json":
            data = json.loads(path.read_text())
            rows = data["waypoints"] if isinstance(data, dict) else data
        elif suffix == ".toml":
            rows = tomllib.loads(path.read_text())["waypoint"]
        else:
            raise ValueError(f"unknown waypoint file type {suffix!r} (use .csv, .json or .toml)")
        rows = [dict(zip("xy", r)) if isinstance(r, (list, tuple)) else r for r in rows]
        pts = np.array([[float(r["x"]), float(r["y"])] for r in rows])
        has_t = all("t" in r for r in rows)
        times = np.array([float(r["t"]) for r in rows]) if has_t else None
        yaw = np.array([float(r["yaw"]) for r in rows]) if has_t and all("yaw" in r for r in rows) else None
        return from_waypoints(pts, speed=speed, yaw=yaw, times=times)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such waypoint file") from None
    except (KeyError, TypeError, ValueError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: bad waypoint file ({exc})") from None


def is_twist_file(path: str | os.PathLike) -> bool:
    """A .csv whose header has v and w columns holds velocity commands, not waypoints."""
    path = Path(path)
    if path.suffix.lower() != ".csv":
        return False
    with open(path, newline="") as fh:
        header = {h.strip() for h in (next(csv.reader(fh), None) or [])}
    return {"v", "w"} <= header


def load_twist(path: str | os.PathLike, dt: float = 0.1, max_speed: float = np.inf,
               max_yaw_rate: float = np.inf) -> Trajectory:
    """Velocity commands (CSV v,w[,dt]; `dt` when the file has none), clamped to the
    robot's limits and integrated as a differential drive."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = [{k.strip(): float(v) for k, v in r.items() if k} for r in csv.DictReader(fh)]
        v = np.array([r["v"] for r in rows])
        w = np.array([r["w"] for r in rows])
        dts = {r.get("dt", dt) for r in rows}
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: bad velocity command file ({exc})") from None
    if len(dts) != 1:
        raise ValueError(f"{path}: velocity commands need one constant dt")
    v, w = clamp_twist(v, w, max_speed, max_yaw_rate)
    return integrate_twist(v, w, dts.pop())


# ------------------------------------------------------------------------------- aisles

@dataclasses.dataclass(frozen=True)
class RowBox:
    """Axis-aligned footprint of a crop row (rows run along +x)."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float


def aisle_waypoints(rows: list[RowBox], margin: float = 1.0, min_aisle: float = 0.5) -> np.ndarray:
    """Serpentine (x, y) waypoints along the centre of every aisle between adjacent rows.

    Aisle i runs along +x for even i and -x for odd i; the robot leaves each aisle
    `margin` metres past the row ends, moves to the next aisle and comes back.
    Gaps narrower than `min_aisle` are not aisles (the robot would not fit).
    """
    rows = sorted(rows, key=lambda r: (r.ymin + r.ymax) / 2)
    if len(rows) < 2:
        raise ValueError("need at least two rows to form an aisle")
    x0 = min(r.xmin for r in rows) - margin
    x1 = max(r.xmax for r in rows) + margin
    pts = []
    aisles = [(a.ymax + b.ymin) / 2 for a, b in zip(rows, rows[1:]) if b.ymin - a.ymax >= min_aisle]
    if not aisles:
        raise ValueError(f"no gap between rows is at least {min_aisle} m wide")
    for i, y in enumerate(aisles):
        pts += [(x0, y), (x1, y)] if i % 2 == 0 else [(x1, y), (x0, y)]
    return np.array(pts)


def _runs(mask: np.ndarray, max_gap: int) -> list[tuple[int, int]]:
    """[start, end] index runs of True, bridging gaps of at most `max_gap` False cells."""
    runs, start, last = [], None, None
    for i, m in enumerate(mask):
        if m:
            if start is not None and i - last - 1 > max_gap:
                runs.append((start, last))
                start = None
            start = i if start is None else start
            last = i
    if start is not None:
        runs.append((start, last))
    return runs


def rows_from_points(points: np.ndarray, cell: float = 0.1, min_height: float = 0.15,
                     min_cover: float = 0.3, min_gap: float = 0.5) -> list[RowBox]:
    """Row footprints from scene points (surfel means), on an x-y occupancy grid of the
    points above the floor: a y-band is a row where its cells are occupied along at
    least `min_cover` of the longest row's length (end walls and posts, short in x, are
    not); bands split at empty gaps of `min_gap`; a row's x extent is its longest
    occupied run (so a wall across the row ends is not part of it)."""
    p = np.asarray(points, np.float64)
    p = p[np.isfinite(p).all(1) & (p[:, 2] > min_height)]
    if len(p) == 0:
        raise ValueError("no scene points above the floor to find rows in")
    lo = np.percentile(p[:, :2], 0.1, axis=0) - cell
    hi = np.percentile(p[:, :2], 99.9, axis=0) + cell
    nx, ny = (np.ceil((hi - lo) / cell).astype(int) + 1)
    ix = np.clip(((p[:, 0] - lo[0]) / cell).astype(int), 0, nx - 1)
    iy = np.clip(((p[:, 1] - lo[1]) / cell).astype(int), 0, ny - 1)
    occ = np.zeros((ny, nx), bool)
    occ[iy, ix] = True
    gap = max(1, int(round(min_gap / cell)))
    cover = np.array([max((b - a + 1 for a, b in _runs(r, gap)), default=0) for r in occ])
    rows = []
    for y0, y1 in _runs(cover >= min_cover * cover.max(), max_gap=gap - 1):
        band = occ[y0:y1 + 1]
        x_runs = _runs(band.mean(0) >= 0.5, gap)
        if not x_runs:
            continue
        x0, x1 = max(x_runs, key=lambda r: r[1] - r[0])
        rows.append(RowBox(float(lo[0] + x0 * cell), float(lo[0] + (x1 + 1) * cell),
                           float(lo[1] + y0 * cell), float(lo[1] + (y1 + 1) * cell)))
    return rows


def load_row_boxes(path: str | os.PathLike) -> list[RowBox]:
    """Row boxes from JSON ({"rows": [{"xmin":..,"xmax":..,"ymin":..,"ymax":..}]}) or TOML
    ([[row]] tables with the same keys, or `min = [x, y]`, `max = [x, y]`)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text()) if path.suffix.lower() == ".json" else tomllib.loads(path.read_text())
        rows = data.get("rows", data.get("row"))
        out = []
        for r in rows:
            if "min" in r:
                out.append(RowBox(float(r["min"][0]), float(r["max"][0]), float(r["min"][1]), float(r["max"][1])))
            else:
                out.append(RowBox(float(r["xmin"]), float(r["xmax"]), float(r["ymin"]), float(r["ymax"])))
        return out
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such row file") from None
    except (KeyError, TypeError, ValueError, AttributeError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: bad row file ({exc!r})") from None
