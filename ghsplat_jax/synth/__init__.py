"""Procedural greenhouse scenes with ground truth, rendered by ray casting a trimesh mesh
(embree through trimesh.ray.ray_pyembree), independent of the project's splat rasterizer.

Python API (names re-exported here, imported lazily: trimesh, cv2 and OpenImageIO load on use):

    from ghsplat_jax import synth
    cfg = synth.load_config("scene.toml")          # or synth.SceneConfig() for the defaults
    scene = synth.generate_scene(cfg)               # -> Scene (mesh, textures, instances, tags, rows)
    cams = synth.capture_path(scene, "handheld", 40, row=0, width=640, height=480)
    views = synth.render_views(scene, cams)         # dict of stacked arrays: rgb, depth, normal,
                                                    #   instance, semantic, face
    synth.write_dataset(scene, cams, "out/row0")    # images, COLMAP text model, transforms.json,
                                                    #   depth/normal EXRs, masks, mesh, tags.json

- `SceneConfig` / `load_config` / `config_to_toml` (config.py): the scene TOML; defaults
  near the paper (4 rows of 10 plants, grow bags, soil, posts, wires, tags at row ends).
  Deterministic from `seed`; `layout.identical_plants = true` repeats one plant mesh.
- `generate_scene` (scene.py): world frame in metres, z up, rows along +x from x = 0 (open
  end toward +x), centred on y = 0. AprilTag 36h11 plates at both ends of each row, facing
  out along the row; exact poses in `scene.tags` (ghsplat_jax.scene.tags.Tag, size = black
  border).
- `render_view` / `render_views` (render.py): any Camera-like object (K, world_to_cam,
  width, height; OpenCV, pixel centres at j + 0.5, i + 0.5). z-depth along the camera axis
  (0: no hit), world normals facing the camera, instance ids (0: background).
- `capture_path` (capture.py): "handheld" walk around a row (slower, so denser, at the
  row ends; height and tilt jitter) or "robot" drives along both aisles at 0.5 m.
- `write_dataset` (dataset.py): the dataset folder layout is in dataset.py's docstring.

Command line: `ghsplat synth --config scene.toml --out DIR [--views N] [--width W --height H]
[--path handheld|robot] [--row R] [--seed S] [--overwrite]`.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "SceneConfig": "config", "load_config": "config", "config_from_dict": "config", "config_to_toml": "config",
    "Scene": "scene", "generate_scene": "scene", "CLASSES": "scene",
    "render_view": "render", "render_views": "render",
    "capture_path": "capture", "PathConfig": "capture", "frame_times": "capture",
    "write_dataset": "dataset",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
