"""Scene description: nested frozen dataclasses read from (and written back to) a small TOML.

Every field has a default near the paper (four rows of young cucumbers, ten plants per
row); a TOML file only lists what it changes:

    seed = 3
    [layout]
    rows = 2
    plants_per_row = 6
    [tags]
    size = 0.12

Unknown sections or keys, wrong types and out-of-range values raise ValueError naming
the file and the key.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from pathlib import Path

from ghsplat_jax.config_values import coerce


@dataclasses.dataclass(frozen=True)
class LayoutConfig:
    rows: int = 4                   # number of crop rows (along +x, stacked along y)
    plants_per_row: int = 10        # plants in each row
    plant_spacing: float = 0.4      # metres between plants along a row
    row_spacing: float = 1.6        # metres between row centre lines
    container: str = "bag"          # "bag" (grow bags), "pot" or "none" (plants stand on the ground plane)
    plants_per_bag: int = 3         # plants sharing one grow bag
    identical_plants: bool = False  # every plant the same mesh (a hard case for SfM)


@dataclasses.dataclass(frozen=True)
class PlantConfig:
    height: tuple[float, float] = (0.65, 1.0)      # stem height range, metres above the container
    leaves: tuple[int, int] = (9, 13)             # leaf count range
    leaf_length: tuple[float, float] = (0.14, 0.2)  # largest blade length range, metres
    lobes: int = 5                                # palmate lobes per blade (3-7)
    tendrils: bool = True                         # thin coiled tendrils at some nodes
    flowers: bool = True                          # small yellow flowers at upper nodes
    leaf_textures: int = 4                        # distinct procedural leaf textures
    stem_radius: float = 0.006                    # stem radius at its base, metres (7/12 of it at the top;
    #                                               petioles scale with it)
    leaf_width: float = 1.0                       # blade width relative to the palmate shape (< 1: narrower,
    #                                               e.g. 0.12 gives strap-like leaves a few pixels wide)


@dataclasses.dataclass(frozen=True)
class GroundConfig:
    kind: str = "soil"        # "soil", "cover" (white woven ground cover) or "none" (no ground)
    margin: float = 4.0       # metres of ground beyond the outermost rows and row ends
    texture_tile: float = 1.0  # metres per repeat of the ground texture


@dataclasses.dataclass(frozen=True)
class StructureConfig:
    posts: bool = True          # support posts at both row ends
    post_spacing: float = 0.0   # extra posts along the row every this many metres (0: ends only)
    wires: bool = True          # support wire along each row between its end posts
    wire_height: float = 1.8    # metres


@dataclasses.dataclass(frozen=True)
class TagConfig:
    enabled: bool = True
    size: float = 0.12          # black-border edge, metres
    height: float = 0.9         # tag centre height, metres
    first_id: int = 0           # row r gets ids first_id + 2r (closed end) and + 2r + 1 (open end)


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    sun_elevation_deg: float = 55.0
    sun_azimuth_deg: float = 35.0   # from +x toward +y
    sun_strength: float = 0.95
    sky_strength: float = 0.5
    shadows: bool = True
    shadow_samples: int = 1         # > 1: soft shadows from a sun disc
    sun_radius_deg: float = 2.0     # angular radius of the sun disc (soft shadows)
    supersample: int = 1            # s: s x s colour rays per pixel (anti-aliasing)
    texture_size: int = 256         # side of each procedural texture, pixels
    background: str = "sky"         # what rays that miss show: "sky" (a gradient) or "black"


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    seed: int = 0
    layout: LayoutConfig = LayoutConfig()
    plant: PlantConfig = PlantConfig()
    ground: GroundConfig = GroundConfig()
    structure: StructureConfig = StructureConfig()
    tags: TagConfig = TagConfig()
    render: RenderConfig = RenderConfig()

    def replace(self, **changes) -> "SceneConfig":
        return dataclasses.replace(self, **changes)


_SECTION_TYPES = {"layout": LayoutConfig, "plant": PlantConfig, "ground": GroundConfig,
                  "structure": StructureConfig, "tags": TagConfig, "render": RenderConfig}


def _coerce(value, default, where: str):
    """Generator fields: 2-tuples are [min, max] ranges (one number: a fixed value)."""
    return coerce(value, default, where, ranges=True)


def _validate(cfg: SceneConfig) -> None:
    lay, pl, gr, st, tg, rd = cfg.layout, cfg.plant, cfg.ground, cfg.structure, cfg.tags, cfg.render
    checks = [
        (lay.rows >= 1, "layout.rows must be >= 1"),
        (lay.plants_per_row >= 1, "layout.plants_per_row must be >= 1"),
        (lay.plant_spacing > 0.05, "layout.plant_spacing must be > 0.05 m"),
        (lay.row_spacing > 0.5, "layout.row_spacing must be > 0.5 m"),
        (lay.container in ("bag", "pot", "none"), "layout.container must be 'bag', 'pot' or 'none'"),
        (lay.plants_per_bag >= 1, "layout.plants_per_bag must be >= 1"),
        (pl.height[0] > 0.05, "plant.height must be > 0.05 m"),
        (pl.leaves[0] >= 1, "plant.leaves must be >= 1"),
        (pl.leaf_length[0] > 0.01, "plant.leaf_length must be > 0.01 m"),
        (3 <= pl.lobes <= 7, "plant.lobes must be between 3 and 7"),
        (1 <= pl.leaf_textures <= 16, "plant.leaf_textures must be between 1 and 16"),
        (0.0005 <= pl.stem_radius <= 0.05, "plant.stem_radius must be between 0.0005 and 0.05 m"),
        (0.02 <= pl.leaf_width <= 2.0, "plant.leaf_width must be between 0.02 and 2"),
        (gr.kind in ("soil", "cover", "none"), "ground.kind must be 'soil', 'cover' or 'none'"),
        (gr.margin >= 0, "ground.margin must be >= 0"),
        (gr.texture_tile > 0, "ground.texture_tile must be > 0"),
        (st.post_spacing >= 0, "structure.post_spacing must be >= 0"),
        (st.wire_height > 0.2, "structure.wire_height must be > 0.2 m"),
        (0.01 <= tg.size <= 1.0, "tags.size must be between 0.01 and 1 m"),
        (tg.height > tg.size, "tags.height must exceed tags.size"),
        (tg.first_id >= 0 and tg.first_id + 2 * lay.rows <= 587,
         "tags.first_id + 2 * rows must fit the 587 ids of tag36h11"),
        (0 < rd.sun_elevation_deg <= 90, "render.sun_elevation_deg must be in (0, 90]"),
        (rd.sun_strength >= 0 and rd.sky_strength >= 0, "render strengths must be >= 0"),
        (1 <= rd.shadow_samples <= 64, "render.shadow_samples must be between 1 and 64"),
        (rd.sun_radius_deg >= 0, "render.sun_radius_deg must be >= 0"),
        (1 <= rd.supersample <= 4, "render.supersample must be between 1 and 4"),
        (32 <= rd.texture_size <= 2048, "render.texture_size must be between 32 and 2048"),
        (rd.background in ("sky", "black"), "render.background must be 'sky' or 'black'"),
    ]
    for ok, message in checks:
        if not ok:
            raise ValueError(message)


def config_from_dict(data: dict, source: str = "<dict>") -> SceneConfig:
    """A validated SceneConfig from a TOML-like dict; errors name `source` and the key."""
    try:
        unknown = set(data) - set(_SECTION_TYPES) - {"seed"}
        if unknown:
            raise ValueError(f"unknown key(s) {sorted(unknown)}; known: seed, {', '.join(_SECTION_TYPES)}")
        changes = {}
        if "seed" in data:
            changes["seed"] = _coerce(data["seed"], 0, "seed")
        for name, cls in _SECTION_TYPES.items():
            section = data.get(name, {})
            if not isinstance(section, dict):
                raise ValueError(f"[{name}] must be a table, got {section!r}")
            defaults = cls()
            known = {f.name for f in dataclasses.fields(cls)}
            bad = set(section) - known
            if bad:
                raise ValueError(f"unknown key(s) {sorted(f'{name}.{k}' for k in bad)}; "
                                 f"known in [{name}]: {', '.join(sorted(known))}")
            values = {k: _coerce(v, getattr(defaults, k), f"{name}.{k}") for k, v in section.items()}
            changes[name] = dataclasses.replace(defaults, **values)
        cfg = dataclasses.replace(SceneConfig(), **changes)
        _validate(cfg)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None
    return cfg


# Named scenes (`ghsplat synth --preset NAME`, `preset_config`): a dict as a TOML file would give.
PRESETS = {
    # One thin plant (stems and strap-like leaves 1-2 cm across: a few pixels at 128x96 from
    # half a metre) alone on a black background: no ground, container, posts, wires or tags.
    # The case where a whole-image score hides a model that misses the subject. Its photos are
    # anti-aliased (4 x 4 rays a pixel), as a camera integrates over each pixel: point-sampled,
    # a leaf one or two pixels wide is a hard on/off pattern no band-limited model reproduces,
    # and that alone held 2DGS to 16.9 dB on the plant's own test pixels (23.3 dB anti-aliased;
    # benchmarks/results/stability).
    "thin-plant": {
        "layout": {"rows": 1, "plants_per_row": 1, "container": "none"},
        "plant": {"height": [0.45, 0.55], "leaves": [6, 8], "leaf_length": [0.14, 0.18], "stem_radius": 0.006,
                  "leaf_width": 0.12, "tendrils": False, "flowers": False},
        "ground": {"kind": "none", "margin": 0.0},
        "structure": {"posts": False, "wires": False},
        "tags": {"enabled": False},
        "render": {"background": "black", "shadows": False, "supersample": 4},
    },
}


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def preset_config(name: str, changes: dict | None = None) -> SceneConfig:
    """The named preset (PRESETS), with `changes` (a TOML-like dict) on top."""
    if name not in PRESETS:
        raise ValueError(f"unknown scene preset {name!r} (known: {', '.join(sorted(PRESETS))})")
    return config_from_dict(_merge(PRESETS[name], changes or {}), f"preset {name!r}")


def load_config(path: str | os.PathLike, preset: str | None = None) -> SceneConfig:
    """Read a scene TOML file (over the named preset, when given); clear errors for a missing
    file, bad syntax or bad values."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such scene config file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: invalid TOML ({exc})") from None
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"unknown scene preset {preset!r} (known: {', '.join(sorted(PRESETS))})")
        data = _merge(PRESETS[preset], data)
    return config_from_dict(data, str(path))


def config_to_toml(cfg: SceneConfig) -> str:
    """The full resolved config as TOML text (round-trips through load_config)."""
    import tomli_w

    table = {"seed": cfg.seed} | {name: dataclasses.asdict(getattr(cfg, name)) for name in _SECTION_TYPES}
    return "# Procedural greenhouse scene (ghsplat synth); every value resolved.\n" + tomli_w.dumps(table)
