"""Write a rendered capture as a dataset folder every reader of the project understands.

    out/
      images/00000.png      8-bit RGB
      depth/00000.exr       float32 z-depth (camera z, metres; 0 where nothing is hit)
      normals/00000.exr     float32 world-frame unit normals facing the camera (0: no hit)
      masks/00000.png       uint16 instance ids (0: background), see instances.json
      sparse/0/cameras.txt images.txt points3D.txt   COLMAP text model, exact PINHOLE cameras,
                            points sampled on the visible mesh surface with their tracks,
                            coloured as the photos show them (as COLMAP colours them)
      transforms.json       NeRF convention (camera-to-world, OpenGL axes), same cameras
      mesh.ply              the scene mesh with per-vertex colours
      mesh.glb              the scene mesh with its textures (per-leaf tints not included)
      tags.json             AprilTag poses (ghsplat_jax.scene.tags format)
      instances.json        instance id -> name and class
      scene.toml            the resolved scene config (regenerates the same scene)

Every file is written atomically (temp name in the same folder, then rename).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from ghsplat_jax.core.camera import project_points
from ghsplat_jax.data.images import read_pixels, write_image
from ghsplat_jax.io_utils import atomic_write, write_json
from ghsplat_jax.scene.tags import save_tags
from ghsplat_jax.synth.config import config_to_toml
from ghsplat_jax.synth.render import albedo, camera_arrays, render_view, trace
from ghsplat_jax.synth.scene import CLASSES, Scene

OUTPUT_DIRS = ("images", "depth", "normals", "masks", "sparse")


def qvec_tvec(camera) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP world-to-camera quaternion (w, x, y, z; w >= 0) and translation."""
    from ghsplat_jax.core.quaternions import from_rotation_matrix

    _, w2c, _, _ = camera_arrays(camera)
    return from_rotation_matrix(w2c[:3, :3]), w2c[:3, 3]


def camera_to_world_opengl(camera) -> np.ndarray:
    """NeRF transform_matrix: camera-to-world with OpenGL axes (x right, y up, z back)."""
    _, w2c, _, _ = camera_arrays(camera)
    return np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])


def _intrinsics_key(camera):
    K, _, w, h = camera_arrays(camera)
    return (w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


def sample_visible_points(scene: Scene, faces_seen: np.ndarray, count: int, seed: int):
    """(points (n,3), colours (n,3) uint8): area-uniform samples on the faces seen in any view."""
    rng = np.random.default_rng(seed)
    tri = scene.vertices[scene.faces[faces_seen]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if len(faces_seen) == 0 or area.sum() <= 0 or count <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64)
    pick = rng.choice(len(faces_seen), size=count, p=area / area.sum())
    r1, r2 = rng.uniform(size=(2, count))
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], -1)
    points = np.einsum("nk,nkj->nj", bary, tri[pick])
    colours = np.clip(albedo(scene, faces_seen[pick], bary) * 255 + 0.5, 0, 255).astype(np.uint8)
    return points, colours, faces_seen[pick]


def observations(scene: Scene, camera, points: np.ndarray, point_faces: np.ndarray):
    """(point indices, pixel xy) of the points visible in `camera`: inside the image, in front,
    and not occluded (a ray from the camera centre first hits the point's own surface)."""
    K, w2c, width, height = camera_arrays(camera)
    xy, z = project_points(points, K, w2c)
    inside = (z > 1e-3) & (xy[:, 0] >= 0) & (xy[:, 0] < width) & (xy[:, 1] >= 0) & (xy[:, 1] < height)
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return idx, np.zeros((0, 2))
    centre = -w2c[:3, :3].T @ w2c[:3, 3]
    offset = points[idx] - centre
    dist = np.linalg.norm(offset, axis=1)
    tri, t, _ = trace(scene, np.broadcast_to(centre, offset.shape).copy(), offset / dist[:, None])
    visible = (tri == point_faces[idx]) | ((tri >= 0) & (t >= dist - 1e-4 * (1 + dist)))
    return idx[visible], xy[idx[visible]]


def observed_colours(image_files, tracks, fallback: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 colour of each point as its photos show it: the mean of the pixels its track
    observes (what COLMAP stores, lit and shaded), not its albedo; `fallback` where unobserved."""
    total = np.zeros(fallback.shape, np.float64)
    count = np.zeros(len(fallback))
    for path, (idx, xy) in zip(image_files, tracks):
        rgb = read_pixels(path)[..., :3]
        scale = 255.0 / np.iinfo(rgb.dtype).max if np.issubdtype(rgb.dtype, np.integer) else 255.0
        h, w = rgb.shape[:2]
        col = np.clip(np.floor(xy[:, 0]).astype(int), 0, w - 1)
        row = np.clip(np.floor(xy[:, 1]).astype(int), 0, h - 1)
        np.add.at(total, idx, rgb[row, col].astype(np.float64) * scale)
        np.add.at(count, idx, 1)
    seen = count > 0
    mean = total[seen] / count[seen, None]
    out = fallback.copy()
    out[seen] = np.clip(mean + 0.5, 0, 255).astype(np.uint8)
    return out


def write_colmap_text(folder: Path, cameras, names, points, colours, tracks) -> None:
    """COLMAP text model: PINHOLE cameras (one per distinct intrinsics), images with their
    2D observations, points3D with tracks. `tracks[v]` = (point indices, xy) for view v."""
    keys = {}
    for cam in cameras:
        keys.setdefault(_intrinsics_key(cam), len(keys) + 1)
    point_track = [[] for _ in range(len(points))]
    image_lines = []
    for v, (cam, name, (idx, xy)) in enumerate(zip(cameras, names, tracks)):
        q, t = qvec_tvec(cam)
        image_lines.append(f"{v + 1} {' '.join(repr(float(a)) for a in (*q, *t))} "
                           f"{keys[_intrinsics_key(cam)]} {name}")
        image_lines.append(" ".join(f"{x!r} {y!r} {p + 1}" for (x, y), p in zip(xy.tolist(), idx.tolist())))
        for k, p in enumerate(idx.tolist()):
            point_track[p].append((v + 1, k))
    cam_lines = [f"{cid} PINHOLE {w} {h} {fx!r} {fy!r} {cx!r} {cy!r}" for (w, h, fx, fy, cx, cy), cid in keys.items()]
    with atomic_write(folder / "cameras.txt", "w") as fh:
        fh.write("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        fh.write(f"# Number of cameras: {len(keys)}\n" + "\n".join(cam_lines) + "\n")
    with atomic_write(folder / "images.txt", "w") as fh:
        fh.write("# Image list with two lines of data per image:\n"
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
                 f"# Number of images: {len(cameras)}\n" + "\n".join(image_lines) + "\n")
    with atomic_write(folder / "points3D.txt", "w") as fh:
        fh.write("# 3D point list with one line of data per point:\n"
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                 f"# Number of points: {len(points)}\n")
        for p, (xyz, rgb, track) in enumerate(zip(points.tolist(), colours.tolist(), point_track)):
            fh.write(f"{p + 1} {xyz[0]!r} {xyz[1]!r} {xyz[2]!r} {rgb[0]} {rgb[1]} {rgb[2]} 0.0 "
                     + " ".join(f"{i} {k}" for i, k in track) + "\n")


def transforms_json(cameras, names, times=None, extra_paths=None) -> dict:
    """NeRF transforms.json in nerfstudio's rules: shared intrinsics at the top when all cameras
    agree, else per frame; `applied_transform` (3x4) is identity because the poses are written
    in the scene's own world frame, the one the COLMAP model and tags.json use."""
    keys = [_intrinsics_key(c) for c in cameras]
    fields = ("w", "h", "fl_x", "fl_y", "cx", "cy")
    shared = len(set(keys)) == 1
    out = {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
           "applied_transform": np.eye(4)[:3].tolist()}
    if shared:
        out.update(dict(zip(fields, keys[0])))
    frames = []
    for v, (cam, name) in enumerate(zip(cameras, names)):
        frame = {"file_path": f"images/{name}", "transform_matrix": camera_to_world_opengl(cam).tolist()}
        if not shared:
            frame.update(dict(zip(fields, keys[v])))
        if times is not None:
            frame["time"] = float(times[v])
        for key, fmt in (extra_paths or {}).items():
            frame[key] = fmt.format(stem=Path(name).stem)
        frames.append(frame)
    out["frames"] = frames
    return out


def vertex_colours(scene: Scene) -> np.ndarray:
    """(V,4) uint8 albedo at each vertex (texture at its uv times its face's tint)."""
    face_of = np.zeros(len(scene.vertices), np.int64)
    face_of[scene.faces.ravel()] = np.repeat(np.arange(len(scene.faces)), 3)
    index = np.arange(len(scene.vertices))
    corner = np.zeros((len(index), 3))  # barycentric coordinates of each vertex in its face
    corner[index, (scene.faces[face_of] == index[:, None]).argmax(1)] = 1
    rgb = np.clip(albedo(scene, face_of, corner) * 255 + 0.5, 0, 255).astype(np.uint8)
    return np.column_stack([rgb, np.full(len(rgb), 255, np.uint8)])


def export_meshes(scene: Scene, folder: Path) -> None:
    """mesh.ply (vertex colours) and mesh.glb (one textured mesh per material)."""
    import trimesh
    from PIL import Image

    ply = trimesh.Trimesh(scene.vertices, scene.faces, vertex_colors=vertex_colours(scene), process=False)
    with atomic_write(folder / "mesh.ply", "wb") as fh:
        fh.write(ply.export(file_type="ply"))
    glb = trimesh.Scene()
    for m, material in enumerate(scene.materials):
        faces = scene.faces[scene.face_material == m]
        if len(faces) == 0:
            continue
        used, inverse = np.unique(faces, return_inverse=True)
        image = Image.fromarray(np.clip(material.texture * 255 + 0.5, 0, 255).astype(np.uint8))
        visual = trimesh.visual.TextureVisuals(uv=scene.uv[used], image=image)
        glb.add_geometry(trimesh.Trimesh(scene.vertices[used], inverse.reshape(-1, 3), visual=visual, process=False),
                         geom_name=material.name)
    with atomic_write(folder / "mesh.glb", "wb") as fh:
        fh.write(glb.export(file_type="glb"))


def write_dataset(scene: Scene, cameras, out_dir: str | os.PathLike, *, n_points: int = 20000, fps: float | None = 2.0,
                  meshes: bool = True, overwrite: bool = False, progress: bool = False, **render_kwargs) -> Path:
    """Render every camera and write the dataset folder (see module doc). Returns out_dir."""
    from tqdm import tqdm

    out = Path(out_dir)
    if (out / "transforms.json").exists() or (out / "sparse").exists():
        if not overwrite:
            raise FileExistsError(f"{out}: already holds a dataset (pass overwrite=True / --overwrite)")
        for name in OUTPUT_DIRS:  # only the folders this writer owns: no stale views survive
            shutil.rmtree(out / name, ignore_errors=True)
    cameras = list(cameras)
    if not cameras:
        raise ValueError("write_dataset needs at least one camera")
    out.mkdir(parents=True, exist_ok=True)
    names = [f"{v:05d}.png" for v in range(len(cameras))]
    seen = np.zeros(len(scene.faces), bool)
    for cam, name in tqdm(list(zip(cameras, names)), disable=not progress, desc="render"):
        stem = Path(name).stem
        views = render_view(scene, cam, **render_kwargs)
        write_image(out / "images" / name, views["rgb"])  # floats in [0, 1] -> 8-bit
        write_image(out / "depth" / f"{stem}.exr", views["depth"])
        write_image(out / "normals" / f"{stem}.exr", views["normal"])
        write_image(out / "masks" / f"{stem}.png", views["instance"].astype(np.uint16))
        faces_hit = views["face"]
        seen[faces_hit[faces_hit >= 0]] = True

    points, colours, faces = sample_visible_points(scene, np.flatnonzero(seen), n_points, scene.config.seed)
    tracks = [observations(scene, cam, points, faces) for cam in cameras]
    observed = np.zeros(len(points), bool)
    for idx, _ in tracks:
        observed[idx] = True
    keep = np.flatnonzero(observed)  # drop samples no camera sees (e.g. hidden at a pixel's edge)
    remap = np.full(len(points), -1)
    remap[keep] = np.arange(len(keep))
    tracks = [(remap[idx], xy) for idx, xy in tracks]
    colours = observed_colours([out / "images" / n for n in names], tracks, colours[keep])
    (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    write_colmap_text(out / "sparse" / "0", cameras, names, points[keep], colours, tracks)

    times = None if fps is None else np.arange(len(cameras)) / fps
    write_json(out / "transforms.json", transforms_json(cameras, names, times, {
        "depth_file_path": "depth/{stem}.exr", "normal_file_path": "normals/{stem}.exr",
        "instance_mask_path": "masks/{stem}.png"}))
    save_tags(out / "tags.json", scene.tags)
    write_json(out / "instances.json", {"classes": list(CLASSES), "instances": [
        {"id": i.id, "name": i.name, "class": i.cls} for i in scene.instances]})
    with atomic_write(out / "scene.toml", "w") as fh:
        fh.write(config_to_toml(scene.config))
    if meshes:
        export_meshes(scene, out)
    return out

