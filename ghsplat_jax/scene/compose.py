"""Assemble a greenhouse from a layout: placed row segments, floor/wall surfels, markers.

Everything is built and checked in memory first; the caller writes the PLY and the tags
file only when the whole scene is valid, so a failed composition leaves no output.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ghsplat_jax.core.surfels import Surfels
from ghsplat_jax.scene import edit, surfaces
from ghsplat_jax.scene.layout import Layout, LayoutError, Row, SurfaceSpec
from ghsplat_jax.scene.tags import Tag


@dataclasses.dataclass
class Placement:
    row: str          # row name (as in the layout, configuration suffix included)
    copy: int
    footprint: np.ndarray  # (2,2) x-y min/max in the world
    count: int


@dataclasses.dataclass
class Composition:
    surfels: Surfels
    tags: list[Tag]
    placements: list[Placement]
    parts: dict  # name -> surfel count

    def summary(self) -> dict:
        return {"count": int(self.surfels.num), "sh_degree": int(self.surfels.sh_degree),
                "parts": self.parts, "markers": [t.id for t in self.tags],
                "rows": [{"row": p.row, "copy": p.copy, "count": p.count,
                          "footprint_xy": p.footprint.tolist()} for p in self.placements]}


def row_matrix(row: Row) -> np.ndarray:
    """Orthogonal part of a row's placement: yaw about +z after the optional mirror."""
    from ghsplat_jax.scene.transform import mirror_matrix, yaw_matrix

    M = np.eye(3) if row.mirror is None else mirror_matrix(row.mirror)
    return yaw_matrix(row.yaw_deg) @ M


def _robust_box(x: np.ndarray) -> np.ndarray:
    """1-99 % percentile box (2,3): floaters do not inflate a segment's footprint."""
    return np.stack([np.percentile(x, 1, axis=0), np.percentile(x, 99, axis=0)])


def _prepare_segment(row: Row, source: Surfels) -> Surfels:
    s, _ = edit.remove_non_finite(source)
    if row.crop_box is not None:
        s, _ = edit.crop_box(s, *row.crop_box)
    if row.min_opacity > 0:
        s, _ = edit.threshold_opacity(s, row.min_opacity)
    return s


def place_row(row: Row, source: Surfels) -> list[tuple[Surfels, Placement]]:
    """All copies of a row segment in the world: x' = Rz M (scale x) + position + k spacing Rz e_x."""
    from ghsplat_jax.scene.transform import similarity, yaw_matrix

    try:
        seg = _prepare_segment(row, source)
    except edit.EmptyResultError as exc:
        raise LayoutError(f"row {row.name} ({row.source}): {exc}") from None
    M = row_matrix(row)
    box = _robust_box(seg.means.astype(np.float64)) * row.scale
    spacing = row.spacing if row.spacing is not None else (box[1, 0] - box[0, 0]) + row.gap
    step = yaw_matrix(row.yaw_deg)[:, 0]  # copies go along the row's (yawed) +x
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    out = []
    for k in range(row.repeat):
        t = np.asarray(row.position) + k * spacing * step
        placed = similarity(seg, row.scale, M, t)
        xy = (corners @ M.T + t)[:, :2]
        out.append((placed, Placement(row.name, k, np.stack([xy.min(0), xy.max(0)]), placed.num)))
    return out


def check_overlaps(placements: list[Placement], policy: str = "error", tolerance: float = 0.02) -> list[str]:
    """Pairs of placed segments whose x-y footprints overlap by more than `tolerance` of the
    smaller one's area: 'error' raises LayoutError, 'warn' warns; returns the messages."""
    problems = []
    for i, a in enumerate(placements):
        for b in placements[i + 1:]:
            lo, hi = np.maximum(a.footprint[0], b.footprint[0]), np.minimum(a.footprint[1], b.footprint[1])
            inter = np.prod(np.maximum(hi - lo, 0.0))
            smaller = min(np.prod(np.ptp(a.footprint, 0)), np.prod(np.ptp(b.footprint, 0)))
            if smaller > 0 and inter > tolerance * smaller:
                problems.append(f"rows {a.row}[{a.copy}] and {b.row}[{b.copy}] overlap "
                                f"({inter / smaller:.0%} of the smaller footprint)")
    if problems and policy == "error":
        raise LayoutError("overlapping rows (set overlap = \"warn\" to allow): " + "; ".join(problems))
    for p in problems:
        warnings.warn(p, stacklevel=2)
    return problems


def _colour_fn(spec: SurfaceSpec, placed_rows: dict[str, list[Surfels]]) -> surfaces.ColourFn:
    if spec.texture is not None:
        return surfaces.texture_colour(spec.texture, spec.texture_size)
    if spec.ground_from is not None:
        from ghsplat_jax.data.ply import load_ply
        from ghsplat_jax.scene.merge import merge

        if spec.ground_from in placed_rows:
            captured = merge(placed_rows[spec.ground_from], policy="truncate")
        else:
            captured = load_ply(spec.ground_from)
        return surfaces.ground_colour(captured, max_height=spec.ground_max_height)
    return surfaces.constant_colour(spec.colour)


def build_surface(spec: SurfaceSpec, placed_rows: dict[str, list[Surfels]]) -> Surfels:
    colour = _colour_fn(spec, placed_rows)
    kw = {} if spec.overlap is None else {"overlap": spec.overlap}
    p = spec.params
    if spec.kind == "box":
        return surfaces.box(p["lo"], p["hi"], spec.spacing, colour, faces=p["faces"], **kw)
    if spec.kind == "plane":
        return surfaces.rectangle(p["center"], p["axis_u"], p["axis_v"], *p["size"], spec.spacing, colour, **kw)
    return surfaces.mesh(surfaces.load_mesh(p["path"]), spec.spacing, colour, **kw)


def compose(layout: Layout) -> Composition:
    """Build the whole scene in memory (see the module docstring)."""
    from ghsplat_jax.scene.markers import Backing, marker_surfels
    from ghsplat_jax.scene.merge import common_degree, load_many, merge, set_sh_degree

    unique = sorted({r.source for r in layout.rows})
    loaded = dict(zip(unique, load_many(unique, layout.allow_3dgs)[0])) if unique else {}
    degree = layout.sh_degree
    if degree is None:
        degree = common_degree([s.sh_degree for s in loaded.values()], layout.sh_policy) if loaded else 0
    parts, names, placements = [], [], []
    placed_rows: dict[str, list[Surfels]] = {}
    for row in layout.rows:
        for placed, placement in place_row(row, loaded[row.source]):
            parts.append(placed)
            names.append(f"row {row.name}[{placement.copy}] ({row.source.name})")
            placements.append(placement)
            placed_rows.setdefault(row.name.split("#")[0], []).append(placed)
    check_overlaps(placements, layout.overlap)
    for i, spec in enumerate(layout.surfaces):
        parts.append(set_sh_degree(build_surface(spec, placed_rows), degree))  # generated: no warning
        names.append(f"surface {i} ({spec.kind})")
    tags = []
    for m in layout.markers:
        backing = None if m.backing is None else Backing(**m.backing)
        s, tag = marker_surfels(m.id, m.size, m.world_from_tag, subdiv=m.subdiv,
                                quiet_zone=m.quiet_zone, backing=backing)
        parts.append(set_sh_degree(s, degree))
        names.append(f"marker {m.id}")
        tags.append(tag)
    if not parts:
        raise LayoutError(f"{layout.path}: the layout has no rows, surfaces or markers")
    scene = merge(parts, layout.sh_policy, names, degree=degree)
    bad = ~edit.finite_mask(scene)
    if bad.any():
        raise LayoutError(f"{layout.path}: composition produced {int(bad.sum())} non-finite surfels")
    return Composition(scene, tags, placements, dict(zip(names, [p.num for p in parts])))
