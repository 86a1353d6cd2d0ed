"""AprilTag ground-truth files (`tags.json`), shared by synthesis, composition, simulation
and localization.

Tag frame (OpenCV ArUco object points): origin at the tag centre, x right, y up, z out of
the printed face toward a viewer. `size` is the edge of the black border in metres.
Corners, in OpenCV order: top-left (-s/2, s/2), top-right (s/2, s/2), bottom-right
(s/2, -s/2), bottom-left (-s/2, -s/2), all at z = 0.

    {"family": "tag36h11", "tags": [{"id": 3, "size": 0.16, "world_from_tag": [[...4x4...]]}]}
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from ghsplat_jax.io_utils import write_json


@dataclasses.dataclass(frozen=True)
class Tag:
    id: int
    size: float
    world_from_tag: np.ndarray  # (4,4)

    def corners_tag(self) -> np.ndarray:
        """(4,3) corners in the tag frame, OpenCV order."""
        h = self.size / 2
        return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], np.float64)

    def corners_world(self) -> np.ndarray:
        c = self.corners_tag()
        return c @ self.world_from_tag[:3, :3].T + self.world_from_tag[:3, 3]


def tags_beside(ply: str | os.PathLike) -> Path:
    """Where a scene PLY's tags file goes by default: <stem>.tags.json beside it."""
    ply = Path(ply)
    return ply.with_name(ply.stem + ".tags.json")


def save_tags(path: str | os.PathLike, tags: list[Tag], family: str = "tag36h11") -> Path:
    return write_json(path, {"family": family, "tags": [
        {"id": int(t.id), "size": float(t.size),
         "world_from_tag": np.asarray(t.world_from_tag, np.float64).tolist()} for t in tags]})


def load_tags(path: str | os.PathLike) -> tuple[str, list[Tag]]:
    """(family, tags) from a tags file; clear errors for malformed files."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        family = data["family"]
        tags = [Tag(int(t["id"]), float(t["size"]), np.asarray(t["world_from_tag"], np.float64))
                for t in data["tags"]]
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such tags file") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: malformed tags file ({exc!r})") from None
    for t in tags:
        if t.world_from_tag.shape != (4, 4) or not np.all(np.isfinite(t.world_from_tag)) or t.size <= 0:
            raise ValueError(f"{path}: tag {t.id} has a bad pose or size")
    if len({t.id for t in tags}) != len(tags):
        raise ValueError(f"{path}: duplicate tag ids")
    return family, tags
