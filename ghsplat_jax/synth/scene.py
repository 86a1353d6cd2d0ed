"""Procedural greenhouse scenes: rows of young cucumber-like plants in grow bags or pots,
textured ground, posts, wires and AprilTags, all deterministic from a SceneConfig.

`generate_scene(config) -> Scene`: one triangle mesh in the world frame (metres, z up,
rows along +x from x = 0, open end toward +x, rows centred on y = 0) with per-face
material, instance and colour tint, the textures, the instance table and the tags.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ghsplat_jax.scene.tags import Tag
from ghsplat_jax.synth import geometry as geo
from ghsplat_jax.synth import textures as tex
from ghsplat_jax.synth.config import SceneConfig

# Semantic classes of instances (and of pixels, through the instance table).
CLASSES = ("background", "ground", "plant", "container", "post", "wire", "tag")

BAG_SIZE = (0.22, 0.11)       # grow bag width, height (metres)
POT_SIZE = (0.09, 0.12, 0.2)  # pot bottom radius, top radius, height
POST_WIDTH = 0.05


@dataclasses.dataclass(frozen=True)
class Material:
    name: str
    texture: np.ndarray      # (S, S, 3) float32 in [0, 1]
    nearest: bool = False    # nearest-texel lookup (crisp tags) instead of bilinear
    translucent: bool = False  # thin foliage: lit through from behind


@dataclasses.dataclass(frozen=True)
class Instance:
    id: int                  # pixel value in instance masks (0 is background)
    name: str
    cls: str                 # one of CLASSES


@dataclasses.dataclass(frozen=True)
class Row:
    index: int
    y: float                 # row centre line
    x0: float                # first and last plant extent along x
    x1: float


@dataclasses.dataclass(eq=False)
class Scene:
    config: SceneConfig
    vertices: np.ndarray        # (V,3) float64, world frame
    faces: np.ndarray           # (F,3) int64
    uv: np.ndarray              # (V,2) float64, texture coordinates (wrap around)
    face_material: np.ndarray   # (F,) int32 index into materials
    face_instance: np.ndarray   # (F,) int32 instance id (>= 1)
    face_tint: np.ndarray       # (F,3) float32 colour multiplier (per-leaf variation)
    materials: list[Material]
    instances: list[Instance]
    tags: list[Tag]
    rows: list[Row]

    @functools.cached_property
    def mesh(self):
        """The trimesh.Trimesh of all faces (unprocessed: face order kept)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False, validate=False)

    @functools.cached_property
    def intersector(self):
        """Embree ray intersector (trimesh.ray.ray_pyembree), built once per scene."""
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(self.mesh)

    @functools.cached_property
    def face_normals(self) -> np.ndarray:
        """(F,3) unit geometric normals in float64 (zero for degenerate faces)."""
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.where(length > 0, n / np.maximum(length, 1e-300), 0.0)

    @property
    def instance_classes(self) -> np.ndarray:
        """(max_id + 1,) uint8 class index per instance id (0: background)."""
        out = np.zeros(max(i.id for i in self.instances) + 1, np.uint8)
        for inst in self.instances:
            out[inst.id] = CLASSES.index(inst.cls)
        return out

    def bounds(self) -> np.ndarray:
        return np.stack([self.vertices.min(0), self.vertices.max(0)])


class _Builder:
    """Collects parts (mesh + material + instance + tint) and assembles the Scene."""

    def __init__(self):
        self.parts = []
        self.materials: dict[str, Material] = {}
        self.instances: list[Instance] = []

    def material(self, name: str, make, **flags) -> str:
        if name not in self.materials:
            self.materials[name] = Material(name, make(), **flags)
        return name

    def instance(self, name: str, cls: str) -> int:
        self.instances.append(Instance(len(self.instances) + 1, name, cls))
        return len(self.instances)

    def add(self, mesh: geo.Mesh, material: str, instance: int, tint=(1.0, 1.0, 1.0)):
        self.parts.append((mesh, material, instance, np.asarray(tint, np.float32)))

    def build(self, config, tags, rows) -> Scene:
        names = list(self.materials)
        v, f, uv = geo.merge([p[0] for p in self.parts])
        counts = [len(p[0][1]) for p in self.parts]
        rep = lambda values: np.repeat(np.asarray(values), counts, axis=0)  # noqa: E731
        return Scene(
            config=config, vertices=v.astype(np.float64), faces=f.astype(np.int64), uv=uv,
            face_material=rep([names.index(p[1]) for p in self.parts]).astype(np.int32),
            face_instance=rep([p[2] for p in self.parts]).astype(np.int32),
            face_tint=rep(np.stack([p[3] for p in self.parts])).astype(np.float32),
            materials=[self.materials[n] for n in names], instances=self.instances,
            tags=tags, rows=rows)


def _plant(rng: np.random.Generator, cfg: SceneConfig, leaf_materials: list[str]) -> list:
    """One plant in its local frame (stem base at the origin): [(mesh, material, tint)]."""
    pc = cfg.plant
    parts = []
    height = rng.uniform(*pc.height)
    n_leaves = int(rng.integers(pc.leaves[0], pc.leaves[1] + 1))
    leaf_max = rng.uniform(*pc.leaf_length)

    # stem: a gently wandering polyline, thinning toward the top
    k = 12
    t = np.linspace(0, 1, k)
    lean = rng.normal(0, 0.03, 2)
    wobble = np.cumsum(rng.normal(0, 0.008, (k, 2)), axis=0)
    stem = np.column_stack([lean[0] * t + wobble[:, 0], lean[1] * t + wobble[:, 1], height * t])
    r = pc.stem_radius
    parts.append((geo.tube(stem, np.linspace(r, r * 7 / 12, k), sides=6, uv_scale=4.0), "stem", (1, 1, 1)))

    def stem_at(s):
        return np.array([np.interp(s, t, stem[:, i]) for i in range(3)])

    azimuth = rng.uniform(0, 2 * np.pi)
    for i in range(n_leaves):
        s = 0.12 + 0.85 * ((i + 1) / n_leaves) ** 0.85  # internodes shorten toward the top
        azimuth += np.pi + rng.normal(0, 0.35)  # alternate leaves
        node = stem_at(s)
        size = leaf_max * (1 - 0.55 * s ** 3) * rng.uniform(0.85, 1.1) * (0.75 if i == 0 else 1)
        # petiole: up and out, arching over
        rise = np.deg2rad(rng.uniform(35, 60))
        plen = size * rng.uniform(0.6, 0.9)
        out = np.array([np.cos(azimuth), np.sin(azimuth), 0])
        tp = np.linspace(0, 1, 5)[:, None]
        petiole = node + plen * (out * np.cos(rise) * tp + np.array([0, 0, np.sin(rise)]) * (tp - 0.45 * tp ** 2))
        parts.append((geo.tube(petiole, np.linspace(r * 0.0028 / 0.006, r / 3, 5), sides=4, uv_scale=4.0), "stem",
                      (1, 1, 1)))
        # blade: tip pointing outward (local +y -> out), pitched down, slight roll
        blade = geo.leaf_blade(size, cfg.plant.lobes, rng.uniform(0.08, 0.22), cup=rng.uniform(0.1, 0.45),
                               droop=rng.uniform(0.1, 0.5), wave=rng.uniform(0.0, 0.03), width=pc.leaf_width)
        rot = (geo.rotation_z(azimuth - np.pi / 2) @ geo.rotation_x(-np.deg2rad(rng.uniform(-5, 35)))
               @ geo.rotation_y(rng.normal(0, 0.2)))
        tint = np.clip(rng.normal(1.0, 0.07, 3) * [1.0, 1.0 + rng.normal(0, 0.04), 1.0], 0.7, 1.3)
        tint *= 1 + 0.12 * (1 - s)  # older, lower leaves slightly lighter and yellower
        material = leaf_materials[int(rng.integers(len(leaf_materials)))]
        parts.append((geo.transform(blade, rot, petiole[-1]), material, tint))

        if pc.tendrils and i > 1 and rng.uniform() < 0.45:
            a = azimuth + np.pi / 2 + rng.normal(0, 0.4)
            turns = np.linspace(0, 1, 24)[:, None]
            direction = np.array([np.cos(a), np.sin(a), 0.6])
            side = np.array([-np.sin(a), np.cos(a), 0])
            helix = node + direction * 0.12 * turns + 0.012 * turns * (
                side * np.cos(18 * turns) + np.array([0, 0, 1.0]) * np.sin(18 * turns))
            parts.append((geo.tube(helix, 0.0009, sides=3, uv_scale=4.0), "stem", (1.1, 1.1, 0.9)))
        if pc.flowers and s > 0.55 and rng.uniform() < 0.35:
            a = azimuth - np.pi / 2 + rng.normal(0, 0.5)
            centre = node + np.array([np.cos(a) * 0.03, np.sin(a) * 0.03, 0.015])
            flower = geo.disc([0, 0, 0], 0.018, petals=5, petal_depth=0.45, segments=20)
            tilt = geo.rotation_z(a) @ geo.rotation_y(np.deg2rad(50))
            parts.append((geo.transform(flower, tilt, centre), "flower", (1, 1, 1)))
    return parts


def _tag_parts(builder: _Builder, tag: Tag, name: str) -> None:
    """Printed tag plate: black border of tag.size plus a white quiet zone, at the tag pose."""
    half = tag.size * tex.TAG_PLATE_RATIO / 2
    R, t = tag.world_from_tag[:3, :3], tag.world_from_tag[:3, 3]
    mat = builder.material(f"tag{tag.id}", lambda: tex.tag_texture(tag.id), nearest=True)
    builder.add(geo.quad(t, R[:, 0], R[:, 1], half, half), mat, builder.instance(name, "tag"))


def generate_scene(config: SceneConfig | None = None) -> Scene:
    """Build the whole greenhouse from `config` (defaults: four rows of ten plants)."""
    cfg = config or SceneConfig()
    lay, st, rc = cfg.layout, cfg.structure, cfg.render
    # independent streams: textures and plants do not shift when the other changes
    rng_tex, rng_plants = (np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(2))
    size = rc.texture_size
    b = _Builder()

    leaf_mats = [b.material(f"leaf{i}", lambda: tex.leaf_texture(rng_tex, size, cfg.plant.lobes), translucent=True)
                 for i in range(cfg.plant.leaf_textures)]
    b.material("stem", lambda: tex.stem_texture(rng_tex, size // 2), translucent=True)
    b.material("flower", lambda: tex.flower_texture(rng_tex, size // 4), translucent=True)

    row_len = lay.plants_per_row * lay.plant_spacing
    ys = (np.arange(lay.rows) - (lay.rows - 1) / 2) * lay.row_spacing
    rows = [Row(r, float(y), 0.0, float(row_len)) for r, y in enumerate(ys)]

    # ground
    m = cfg.ground.margin
    make_ground = tex.soil_texture if cfg.ground.kind == "soil" else tex.cover_texture
    if cfg.ground.kind != "none":
        ground_mat = b.material("ground", lambda: make_ground(rng_tex, size * 2))
        lo = np.array([-m - 0.5, ys[0] - lay.row_spacing / 2 - m])
        hi = np.array([row_len + m + 0.5, ys[-1] + lay.row_spacing / 2 + m])
        b.add(geo.ground_grid(lo, hi, 0.5, cfg.ground.texture_tile), ground_mat, b.instance("ground", "ground"))

    # plants: one rng per plant from the plant stream (or a single one when identical)
    plant_seeds = np.random.SeedSequence(int(rng_plants.integers(2 ** 32))).spawn(lay.rows * lay.plants_per_row)
    template = None
    container_top = {"bag": BAG_SIZE[1], "pot": POT_SIZE[2] - 0.02}.get(lay.container, 0.0)
    for row in rows:
        for p in range(lay.plants_per_row):
            if lay.identical_plants:
                template = template or _plant(np.random.default_rng(plant_seeds[0]), cfg, leaf_mats)
                parts = template
            else:
                parts = _plant(np.random.default_rng(plant_seeds[row.index * lay.plants_per_row + p]), cfg, leaf_mats)
            base = np.array([(p + 0.5) * lay.plant_spacing, row.y, container_top])
            inst = b.instance(f"plant_r{row.index}_p{p}", "plant")
            for mesh, mat, tint in parts:
                b.add(geo.transform(mesh, np.eye(3), base), mat, inst, tint)

    # containers
    if lay.container == "bag":
        b.material("bag", lambda: tex.plastic_texture(rng_tex, size, [0.74, 0.75, 0.73]))
        b.material("substrate", lambda: tex.soil_texture(rng_tex, size))
        per = lay.plants_per_bag
        for row in rows:
            for k, first in enumerate(range(0, lay.plants_per_row, per)):
                n = min(per, lay.plants_per_row - first)
                length = n * lay.plant_spacing - 0.04
                cx = (first + n / 2) * lay.plant_spacing
                inst = b.instance(f"bag_r{row.index}_{k}", "container")
                b.add(geo.box([cx, row.y, BAG_SIZE[1] / 2], [length, BAG_SIZE[0], BAG_SIZE[1]], uv_scale=2.0),
                      "bag", inst)
                for j in range(n):  # planting holes showing the substrate
                    hx = (first + j + 0.5) * lay.plant_spacing
                    b.add(geo.disc([hx, row.y, BAG_SIZE[1] + 0.001], 0.045, segments=12), "substrate", inst)
    elif lay.container == "pot":
        b.material("pot", lambda: tex.plastic_texture(rng_tex, size, [0.16, 0.16, 0.17]))
        b.material("substrate", lambda: tex.soil_texture(rng_tex, size))
        r0, r1, h = POT_SIZE
        for row in rows:
            for p in range(lay.plants_per_row):
                x = (p + 0.5) * lay.plant_spacing
                inst = b.instance(f"pot_r{row.index}_p{p}", "container")
                b.add(geo.frustum([x, row.y, 0.0], r0, r1, h), "pot", inst)
                b.add(geo.disc([x, row.y, h - 0.02], r1 * 0.97, segments=16), "substrate", inst)

    # posts, wires and tags at the row ends
    tags = []
    post_h = st.wire_height + 0.1
    ends = (-0.15, row_len + 0.15)
    for row in rows:
        if st.posts:
            b.material("metal", lambda: tex.metal_texture(rng_tex, size // 2))
            xs = list(ends)
            if st.post_spacing > 0:
                xs += list(np.arange(st.post_spacing, row_len, st.post_spacing))
            for k, x in enumerate(xs):
                b.add(geo.box([x, row.y, post_h / 2], [POST_WIDTH, POST_WIDTH, post_h], uv_scale=2.0),
                      "metal", b.instance(f"post_r{row.index}_{k}", "post"))
        if st.wires:
            b.material("metal", lambda: tex.metal_texture(rng_tex, size // 2))
            wire = np.array([[ends[0], row.y, st.wire_height], [ends[1], row.y, st.wire_height]])
            b.add(geo.tube(wire, 0.003, sides=4), "metal", b.instance(f"wire_r{row.index}", "wire"))
        if cfg.tags.enabled:
            for e, (x, outward) in enumerate(zip(ends, (-1.0, 1.0))):
                # tag frame: z out of the face (along the row axis, away from the row),
                # y up, x right as seen by a viewer facing the tag
                z_axis = np.array([outward, 0, 0])
                y_axis = np.array([0, 0, 1.0])
                x_axis = np.cross(y_axis, z_axis)
                pose = np.eye(4)
                pose[:3, :3] = np.column_stack([x_axis, y_axis, z_axis])
                offset = (POST_WIDTH / 2 + 0.002) if st.posts else 0.0
                pose[:3, 3] = [x + outward * offset, row.y, cfg.tags.height]
                tag = Tag(cfg.tags.first_id + 2 * row.index + e, cfg.tags.size, pose)
                tags.append(tag)
                _tag_parts(b, tag, f"tag{tag.id}")
    return b.build(cfg, tags, rows)
