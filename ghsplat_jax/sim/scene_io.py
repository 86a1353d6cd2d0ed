"""Load a simulation scene: a composed PLY (with its `<stem>.tags.json` beside it) or a
layout TOML composed in memory. Row footprints come from the layout's placements, or
are estimated from the surfels of a PLY."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from ghsplat_jax.sim.trajectory import RowBox, rows_from_points


class SceneError(ValueError):
    """A scene that cannot be simulated; the message names the file."""


@dataclasses.dataclass
class SimScene:
    path: Path
    surfels: object
    tags: list            # scene.tags.Tag
    rows: list[RowBox] | None

    @property
    def num(self) -> int:
        return int(self.surfels.num)


def _merge_rows(placements) -> list[RowBox]:
    boxes: dict[str, np.ndarray] = {}
    for p in placements:
        fp = np.asarray(p.footprint, np.float64)
        name = p.row.split("#")[0]
        if name in boxes:
            b = boxes[name]
            boxes[name] = np.array([np.minimum(b[0], fp[0]), np.maximum(b[1], fp[1])])
        else:
            boxes[name] = fp
    return [RowBox(b[0, 0], b[1, 0], b[0, 1], b[1, 1]) for b in boxes.values()]


def load_scene(path: str | os.PathLike, tags_path: str | os.PathLike | None = None,
               configuration: str | None = None) -> SimScene:
    """Raises SceneError (or FileNotFoundError) with the file named; nothing is published
    before this succeeds."""
    import jax

    from ghsplat_jax.data.ply import PlyError, load_ply
    from ghsplat_jax.scene.tags import load_tags, tags_beside

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such scene file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            from ghsplat_jax.scene.compose import compose
            from ghsplat_jax.scene.layout import load_layout

            comp = compose(load_layout(path, configuration))
            surfels, tags, rows = comp.surfels, list(comp.tags), _merge_rows(comp.placements) or None
        elif suffix == ".ply":
            surfels = load_ply(path)
            tags, rows = [], None
            default_tags = tags_beside(path)
            if tags_path is None and default_tags.exists():
                tags_path = default_tags
        else:
            raise SceneError(f"{path}: expected a layout .toml or a .ply scene")
        if tags_path is not None:
            _, tags = load_tags(tags_path)
    except (PlyError, ValueError, KeyError) as exc:
        raise SceneError(f"{path}: cannot load scene ({exc})") from None
    surfels = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), surfels)
    if surfels.num == 0:
        raise SceneError(f"{path}: the scene has no surfels")
    if not all(np.all(np.isfinite(a)) for a in jax.tree_util.tree_leaves(surfels)):
        raise SceneError(f"{path}: the scene has non-finite surfel parameters")
    return SimScene(path, surfels, tags, rows)


def scene_rows(scene: SimScene) -> list[RowBox]:
    if scene.rows:
        return scene.rows
    return rows_from_points(np.asarray(scene.surfels.means))
