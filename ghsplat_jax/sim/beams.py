"""LiDAR beam patterns: elevation table, columns per revolution, rate, range limits, noise.

Ring r is the r-th entry of `elevations_deg`; presets list them bottom to top, as the
Velodyne and Ouster ROS drivers number rings.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
from pathlib import Path

import numpy as np


@dataclasses.dataclass(frozen=True)
class BeamPattern:
    name: str
    elevations_deg: tuple[float, ...]
    columns: int            # firings per revolution
    rate_hz: float = 10.0   # revolutions per second
    min_range: float = 0.5
    max_range: float = 100.0
    noise_std: float = 0.0  # Gaussian range noise, metres

    def __post_init__(self):
        el = np.asarray(self.elevations_deg, np.float64)
        if el.ndim != 1 or len(el) == 0 or not np.all(np.isfinite(el)) or np.any(np.abs(el) >= 60):
            raise ValueError(f"beam pattern {self.name!r}: elevations must be finite and within +-60 deg")
        if self.columns < 4 or self.rate_hz <= 0 or not 0 <= self.min_range < self.max_range or self.noise_std < 0:
            raise ValueError(f"beam pattern {self.name!r}: bad columns, rate, range or noise")

    @property
    def rings(self) -> int:
        return len(self.elevations_deg)

    @property
    def max_abs_elevation_deg(self) -> float:
        return float(np.max(np.abs(self.elevations_deg)))

    def face_half_fov_deg(self) -> float:
        """Vertical half field of view a 90-degree face needs to hold every beam at its
        edge: the beam at 45 deg off the face axis meets the image plane sqrt(2) times
        further out."""
        return float(np.rad2deg(np.arctan(np.sqrt(2.0) * np.tan(np.deg2rad(self.max_abs_elevation_deg)))))

    def replace(self, **kw) -> "BeamPattern":
        return dataclasses.replace(self, **kw)


PRESETS = {
    # Velodyne VLP-16 (Jackal's): 16 beams, -15..15 deg every 2 deg, 0.2 deg at 10 Hz, 100 m.
    "vlp16": BeamPattern("VLP-16", tuple(float(e) for e in np.arange(-15, 16, 2)), 1800, 10.0, 0.5, 100.0, 0.0),
    # Velodyne HDL-32E: 32 beams, -30.67..+10.67 deg every 4/3 deg, ~2170 firings at 10 Hz.
    "hdl32e": BeamPattern("HDL-32E", tuple(float(e) for e in np.round(np.linspace(-30.67, 10.67, 32), 4)),
                          2170, 10.0, 1.0, 100.0, 0.0),
    # Ouster OS1-64 (uniform beam spacing, 45 deg vertical field), 1024 columns at 10 Hz.
    "os1-64": BeamPattern("OS1-64", tuple(float(e) for e in np.round(np.linspace(-22.5, 22.5, 64), 4)),
                          1024, 10.0, 0.3, 120.0, 0.0),
}


def get_pattern(name_or_path: str) -> BeamPattern:
    key = name_or_path.lower().replace("_", "-")
    aliases = {"vlp-16": "vlp16", "hdl-32e": "hdl32e", "hdl32": "hdl32e", "os1": "os1-64", "os164": "os1-64"}
    key = aliases.get(key, key)
    if key in PRESETS:
        return PRESETS[key]
    if Path(name_or_path).suffix.lower() in (".json", ".csv"):
        return load_pattern(name_or_path)
    raise ValueError(f"unknown LiDAR {name_or_path!r}: use one of {sorted(PRESETS)} or a .json/.csv beam table")


def load_pattern(path: str | os.PathLike) -> BeamPattern:
    """A custom beam table. JSON: {"name", "elevations_deg": [...], "columns", "rate_hz",
    "min_range", "max_range", "noise_std"} (all but elevations optional). CSV: one
    `elevation_deg` column, one row per ring (other settings take VLP-16 defaults)."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".csv":
            with open(path, newline="") as fh:
                el = [float(r["elevation_deg"]) for r in csv.DictReader(fh)]
            return BeamPattern(path.stem, tuple(el), 1800)
        data = json.loads(path.read_text())
        return BeamPattern(
            str(data.get("name", path.stem)), tuple(float(e) for e in data["elevations_deg"]),
            int(data.get("columns", 1800)), float(data.get("rate_hz", 10.0)),
            float(data.get("min_range", 0.5)), float(data.get("max_range", 100.0)),
            float(data.get("noise_std", 0.0)))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such beam table") from None
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: bad beam table ({exc})") from None
