"""Greenhouse layout files (TOML): row segments, floor and wall surfaces, AprilTag markers.

Paths are relative to the layout file. World frame: metres, z up, rows along +x.

    sh_degree = 3                 # output SH degree (default: by sh_policy from the sources)
    sh_policy = "pad"             # "pad" (zero higher bands) or "truncate", when sources differ
    overlap = "error"             # "error" or "warn" when row footprints overlap in x-y
    allow_3dgs = false            # allow mixing 3DGS source files with 2DGS ones
    configuration = "wide"        # optional: apply [configurations.wide]

    [[rows]]
    name = "row1"
    source = "segments/row1_a.ply"
    scale = 1.0                   # or scale_from_length = [measured, true]
    position = [0.0, 0.0, 0.0]    # where the segment's origin goes
    yaw_deg = 0.0                 # about +z, after the mirror
    mirror = false                # true (= "y") or "x"/"y": reflect in the segment frame
    repeat = 1                    # copies along the row's +x
    spacing = 2.5                 # metres between copies (default: the segment's x length)
    crop_box = [[-1, -1, -0.1], [1, 1, 2]]   # optional, source coordinates
    min_opacity = 0.0             # optional

    [[surfaces]]                  # floor, walls
    kind = "box"                  # "box" (min, max, faces), "plane" (center, size, axis_u, axis_v), "mesh" (path)
    min = [-1, -2, -0.02]
    max = [10, 6, 0.0]
    faces = ["+z"]
    spacing = 0.02                # surfel pitch (m)
    colour = [0.35, 0.3, 0.25]    # or texture = "floor.png", texture_size = [1, 1]
                                  # or ground_from = "row1" (a row name or PLY), ground_max_height = 0.05

    [[markers]]
    id = 0
    size = 0.16                   # black border edge (m)
    position = [4.0, 1.0, 0.5]
    facing = [-1, 0, 0]           # direction the printed face looks (default +x), tag y toward
                                  # up = [0, 0, 1]; or euler_deg = [rx, ry, rz] (extrinsic xyz)
    quiet_zone = 1.0              # white border in cells
    backing = true                # or {margin = 0.02, thickness = 0.01, colour = [0.5, 0.5, 0.5]}

    [configurations.wide]         # rearrange rows: order/duplicates, spacing, row length
    rows = ["row1", "row1", "row2"]   # optional; default all rows in file order
    row_spacing = 1.6             # rows at y = y_first + i * row_spacing
    repeat = 3                    # copies per row (row length in segments)
    segment_gap = 0.05            # extra metres between copies
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np


class LayoutError(ValueError):
    """A layout that cannot be built; the message names the file and the entry."""


@dataclasses.dataclass(frozen=True)
class Row:
    name: str
    source: Path
    scale: float = 1.0
    position: tuple = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0
    mirror: str | None = None
    repeat: int = 1
    spacing: float | None = None  # None: the segment's x length plus `gap`
    gap: float = 0.0
    crop_box: tuple | None = None
    min_opacity: float = 0.0


@dataclasses.dataclass(frozen=True)
class SurfaceSpec:
    kind: str
    params: dict
    spacing: float
    colour: tuple | None = None
    texture: Path | None = None
    texture_size: tuple = (1.0, 1.0)
    ground_from: str | None = None
    ground_max_height: float | None = None
    overlap: float | None = None


@dataclasses.dataclass(frozen=True)
class MarkerSpec:
    id: int
    size: float
    world_from_tag: np.ndarray
    quiet_zone: float = 1.0
    subdiv: int = 4
    backing: dict | None = None


@dataclasses.dataclass(frozen=True)
class Layout:
    path: Path
    rows: list
    surfaces: list
    markers: list
    sh_degree: int | None = None
    sh_policy: str = "pad"
    overlap: str = "error"
    allow_3dgs: bool = False


def _vec(ctx: str, value, n: int = 3) -> tuple:
    arr = np.asarray(value, np.float64)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise LayoutError(f"{ctx}: expected {n} finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def _num(ctx: str, value, positive: bool = False) -> float:
    """A finite number (TOML spells nan and inf; neither places anything)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise LayoutError(f"{ctx}: expected a finite number, got {value!r}")
    if positive and not value > 0:
        raise LayoutError(f"{ctx}: must be positive, got {value!r}")
    return float(value)


def _count(ctx: str, value, most: int) -> int:
    """A whole number 1..most: copies and subdivisions multiply memory, so they are bounded."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= most:
        raise LayoutError(f"{ctx}: expected an integer from 1 to {most}, got {value!r}")
    return value


MAX_REPEAT = 10_000  # copies of one segment along a row


def _known(ctx: str, table: dict, keys: set) -> None:
    if not isinstance(table, dict):
        raise LayoutError(f"{ctx}: expected a table, got {table!r}")
    unknown = set(table) - keys
    if unknown:
        raise LayoutError(f"{ctx}: unknown keys {sorted(unknown)} (allowed: {sorted(keys)})")


_ROW_KEYS = {"name", "source", "scale", "scale_from_length", "position", "yaw_deg", "mirror",
             "repeat", "spacing", "crop_box", "min_opacity"}
_SURFACE_KEYS = {"kind", "min", "max", "faces", "center", "size", "axis_u", "axis_v", "path",
                 "spacing", "colour", "color", "texture", "texture_size", "ground_from",
                 "ground_max_height", "overlap", "name"}
_MARKER_KEYS = {"id", "size", "position", "facing", "up", "euler_deg", "quiet_zone", "subdiv", "backing"}
_CONFIG_KEYS = {"rows", "row_spacing", "repeat", "segment_gap"}
_TOP_KEYS = {"sh_degree", "sh_policy", "overlap", "allow_3dgs", "configuration", "rows",
             "surfaces", "markers", "configurations"}


def _list(ctx: str, data: dict, key: str) -> list:
    value = data.get(key, [])
    if not isinstance(value, list):
        raise LayoutError(f"{ctx}: '{key}' must be an array of tables ([[{key}]]), got {value!r}")
    return value


def _row(ctx: str, t: dict, base: Path, index: int) -> Row:
    _known(ctx, t, _ROW_KEYS)
    if not isinstance(t.get("source"), str) or "\0" in t["source"]:
        raise LayoutError(f"{ctx}: 'source' must be a path to a PLY file, got {t.get('source')!r}")
    scale = _num(f"{ctx}.scale", t.get("scale", 1.0))
    if "scale_from_length" in t:
        from ghsplat_jax.scene.transform import scale_from_length

        measured, true = _vec(f"{ctx}.scale_from_length", t["scale_from_length"], 2)
        try:
            scale = scale_from_length(measured, true)
        except ValueError as exc:
            raise LayoutError(f"{ctx}: {exc}") from None
    if not (np.isfinite(scale) and scale > 0):
        raise LayoutError(f"{ctx}: scale must be positive, got {scale}")
    mirror = t.get("mirror", False)
    mirror = "y" if mirror is True else (None if mirror is False else mirror)
    if mirror not in (None, "x", "y"):
        raise LayoutError(f"{ctx}: mirror must be true/false, 'x' or 'y', got {mirror!r}")
    repeat = _count(f"{ctx}.repeat", t.get("repeat", 1), MAX_REPEAT)
    crop = t.get("crop_box")
    if crop is not None:
        if not isinstance(crop, list) or len(crop) != 2:
            raise LayoutError(f"{ctx}.crop_box: expected [[xmin,ymin,zmin],[xmax,ymax,zmax]]")
        crop = (_vec(f"{ctx}.crop_box", crop[0]), _vec(f"{ctx}.crop_box", crop[1]))
    spacing = t.get("spacing")
    return Row(name=str(t.get("name", f"row{index}")), source=(base / t["source"]).resolve(), scale=scale,
               position=_vec(f"{ctx}.position", t.get("position", (0, 0, 0))),
               yaw_deg=_num(f"{ctx}.yaw_deg", t.get("yaw_deg", 0.0)), mirror=mirror, repeat=repeat,
               spacing=None if spacing is None else _num(f"{ctx}.spacing", spacing, positive=True), crop_box=crop,
               min_opacity=_num(f"{ctx}.min_opacity", t.get("min_opacity", 0.0)))


def _surface(ctx: str, t: dict, base: Path) -> SurfaceSpec:
    _known(ctx, t, _SURFACE_KEYS)
    kind = t.get("kind")
    if kind == "box":
        params = {"lo": _vec(f"{ctx}.min", t.get("min")), "hi": _vec(f"{ctx}.max", t.get("max")),
                  "faces": tuple(t.get("faces", ("+x", "-x", "+y", "-y", "+z", "-z")))}
    elif kind == "plane":
        params = {"center": _vec(f"{ctx}.center", t.get("center")),
                  "size": _vec(f"{ctx}.size", t.get("size"), 2),
                  "axis_u": _vec(f"{ctx}.axis_u", t.get("axis_u", (1, 0, 0))),
                  "axis_v": _vec(f"{ctx}.axis_v", t.get("axis_v", (0, 1, 0)))}
    elif kind == "mesh":
        if "path" not in t:
            raise LayoutError(f"{ctx}: mesh surface needs 'path'")
        params = {"path": (base / t["path"]).resolve()}
    else:
        raise LayoutError(f"{ctx}: kind must be 'box', 'plane' or 'mesh', got {kind!r}")
    spacing = _num(f"{ctx}.spacing", t.get("spacing", 0.02), positive=True)
    colour = t.get("colour", t.get("color"))
    sources = [k for k in ("colour", "texture", "ground_from") if (colour if k == "colour" else t.get(k)) is not None]
    if len(sources) > 1:
        raise LayoutError(f"{ctx}: give only one of colour, texture, ground_from (got {sources})")
    return SurfaceSpec(
        kind=kind, params=params, spacing=spacing,
        colour=_vec(f"{ctx}.colour", colour) if colour is not None else (
            None if sources else (0.5, 0.5, 0.5)),
        texture=(base / t["texture"]).resolve() if "texture" in t else None,
        texture_size=_vec(f"{ctx}.texture_size", t.get("texture_size", (1.0, 1.0)), 2),
        ground_from=t.get("ground_from"),
        ground_max_height=None if "ground_max_height" not in t else _num(f"{ctx}.ground_max_height",
                                                                         t["ground_max_height"]),
        overlap=None if "overlap" not in t else _num(f"{ctx}.overlap", t["overlap"]))


def _marker(ctx: str, t: dict) -> MarkerSpec:
    from ghsplat_jax.scene.markers import tag_pose

    _known(ctx, t, _MARKER_KEYS)
    for key in ("id", "size", "position"):
        if key not in t:
            raise LayoutError(f"{ctx}: missing '{key}'")
    if "euler_deg" in t and "facing" in t:
        raise LayoutError(f"{ctx}: give 'facing' or 'euler_deg', not both")
    try:
        optional = {k: _vec(f"{ctx}.{k}", t[k]) for k in ("facing", "up", "euler_deg") if k in t}
        pose = tag_pose(_vec(f"{ctx}.position", t["position"]), facing=optional.get("facing"),
                        up=optional.get("up", (0.0, 0.0, 1.0)), euler_deg=optional.get("euler_deg"))
        if not np.all(np.isfinite(pose)):
            raise ValueError("facing and up must be non-zero and not parallel")
    except ValueError as exc:
        raise LayoutError(f"{ctx}: {exc}") from None
    backing = t.get("backing", False)
    backing = {} if backing is True else (None if backing is False else dict(backing))
    if isinstance(t["id"], bool) or not isinstance(t["id"], int) or not 0 <= t["id"] < 2**31:
        raise LayoutError(f"{ctx}.id: expected a non-negative integer, got {t['id']!r}")
    return MarkerSpec(id=t["id"], size=_num(f"{ctx}.size", t["size"], positive=True), world_from_tag=pose,
                      quiet_zone=_num(f"{ctx}.quiet_zone", t.get("quiet_zone", 1.0)),
                      subdiv=_count(f"{ctx}.subdiv", t.get("subdiv", 4), 64), backing=backing)


def _apply_configuration(ctx: str, rows: list[Row], config: dict) -> list[Row]:
    """Reorder/duplicate rows, set their y spacing, length (repeat) and gap."""
    _known(ctx, config, _CONFIG_KEYS)
    by_name = {r.name: r for r in rows}
    names = config.get("rows", [r.name for r in rows])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise LayoutError(f"{ctx}.rows: expected a list of row names, got {names!r}")
    missing = [n for n in names if n not in by_name]
    if missing:
        raise LayoutError(f"{ctx}: unknown rows {missing} (known: {sorted(by_name)})")
    out = []
    y0 = by_name[names[0]].position[1] if names else 0.0
    for i, name in enumerate(names):
        r = by_name[name]
        changes = {"name": f"{name}#{i}" if names.count(name) > 1 else name}
        if "row_spacing" in config:
            changes["position"] = (r.position[0], y0 + i * _num(f"{ctx}.row_spacing", config["row_spacing"]),
                                   r.position[2])
        if "repeat" in config:
            changes["repeat"] = _count(f"{ctx}.repeat", config["repeat"], MAX_REPEAT)
        if "segment_gap" in config:
            changes["spacing"], changes["gap"] = None, _num(f"{ctx}.segment_gap", config["segment_gap"])
        out.append(dataclasses.replace(r, **changes))
    return out


def load_layout(path: str | os.PathLike, configuration: str | None = None) -> Layout:
    """Parse and validate a layout; every referenced file must exist (all missing ones listed)."""
    import tomllib

    path = Path(path)
    if not path.is_file():
        raise LayoutError(f"{path}: no such layout file")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise LayoutError(f"{path}: invalid TOML ({exc})") from None
    base = path.parent
    ctx = str(path)
    try:
        _known(ctx, data, _TOP_KEYS)
        rows = [_row(f"{ctx} rows[{i}]", t, base, i) for i, t in enumerate(_list(ctx, data, "rows"))]
        names = [r.name for r in rows]
        if len(set(names)) != len(names):
            raise LayoutError(f"{ctx}: duplicate row names {names}")
        surfaces = [_surface(f"{ctx} surfaces[{i}]", t, base) for i, t in enumerate(_list(ctx, data, "surfaces"))]
        markers = [_marker(f"{ctx} markers[{i}]", t) for i, t in enumerate(_list(ctx, data, "markers"))]
        ids = [m.id for m in markers]
        if len(set(ids)) != len(ids):
            raise LayoutError(f"{ctx}: duplicate marker ids {sorted(ids)}")
        configuration = configuration or data.get("configuration")
        if configuration is not None:
            configs = data.get("configurations", {})
            if not isinstance(configs, dict) or not isinstance(configuration, str) or configuration not in configs:
                have = sorted(configs) if isinstance(configs, dict) else configs
                raise LayoutError(f"{ctx}: no configuration {configuration!r} (have {have})")
            rows = _apply_configuration(f"{ctx} configurations.{configuration}", rows, configs[configuration])
        # a ground_from that is not a row name is a PLY path
        surfaces = [dataclasses.replace(s, ground_from=str((base / s.ground_from).resolve()))
                    if s.ground_from is not None and s.ground_from not in names else s for s in surfaces]
        files = [r.source for r in rows] + [s.texture for s in surfaces if s.texture]
        files += [s.params["path"] for s in surfaces if s.kind == "mesh"]
        files += [Path(s.ground_from) for s in surfaces if s.ground_from and s.ground_from not in names]
        missing = sorted({str(f) for f in files if not Path(f).is_file()})
    except LayoutError:
        raise
    except (TypeError, KeyError, ValueError, OverflowError, OSError) as exc:  # OSError: a path too long
        raise LayoutError(f"{ctx}: malformed entry ({exc!r})") from None
    if missing:
        raise LayoutError(f"{ctx}: missing files: {', '.join(missing)}")
    policy = data.get("sh_policy", "pad")
    overlap = data.get("overlap", "error")
    if policy not in ("pad", "truncate") or overlap not in ("error", "warn"):
        raise LayoutError(f"{ctx}: sh_policy must be pad|truncate and overlap error|warn")
    degree = data.get("sh_degree")
    if degree is not None and (isinstance(degree, bool) or degree not in (0, 1, 2, 3)):
        raise LayoutError(f"{ctx}: sh_degree must be 0-3")
    return Layout(path=path, rows=rows, surfaces=surfaces, markers=markers, sh_degree=degree,
                  sh_policy=policy, overlap=overlap, allow_3dgs=bool(data.get("allow_3dgs", False)))
