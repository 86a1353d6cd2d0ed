"""Layout parsing and greenhouse composition (`ghsplat compose`), floor surfels."""

import json
import re
import textwrap

import numpy as np
import pytest

import ghsplat_jax as gs
from ghsplat_jax.cli import main as cli
from ghsplat_jax.core.sh import rgb_to_dc
from ghsplat_jax.scene import surfaces
from ghsplat_jax.scene.compose import compose
from ghsplat_jax.scene.layout import LayoutError, load_layout
from ghsplat_jax.scene.tags import load_tags
from ghsplat_jax.scene.views import render_stable

CFG = gs.RasterConfig(background=(0.3, 0.3, 0.3), pair_capacity=1 << 14)
NUM, SIZE = 8192, 128


@pytest.fixture()
def segments(tmp_path):
    """A 2 m row segment (x in [0, 2], y in +-0.3) at SH degree 3 and a small degree-1 one."""
    rng = np.random.default_rng(0)
    n = 600
    x = np.stack([rng.uniform(0, 2, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0, 1, n)], 1)
    x[0] = [1.0, 0.29, 0.5]  # a point to follow through the mirror
    gs.save_ply(gs.make_surfels(x, sh_dc=rng.normal(0, 0.3, (n, 3)), sh_rest=rng.normal(0, 0.1, (n, 15, 3)),
                                sh_degree=3), tmp_path / "seg.ply")
    gs.save_ply(gs.make_surfels(x[:200] * 0.5, sh_degree=1), tmp_path / "small.ply")
    return tmp_path


def _write(tmp_path, text, name="layout.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


LAYOUT = """
    [[rows]]
    name = "a"
    source = "seg.ply"
    repeat = 2

    [[rows]]
    name = "b"
    source = "small.ply"
    scale = 2.0
    position = [0.0, 1.5, 0.0]
    mirror = true

    [[surfaces]]
    kind = "box"
    min = [-0.5, -1.0, -0.02]
    max = [4.5, 2.5, 0.0]
    faces = ["+z"]
    spacing = 0.1
    colour = [0.4, 0.3, 0.2]

    [[markers]]
    id = 3
    size = 0.16
    position = [4.3, 0.75, 0.4]
    facing = [-1, 0, 0]
    backing = true

    [configurations.wide]
    rows = ["a", "b", "a"]
    row_spacing = 2.0
    repeat = 1
"""


def test_compose_places_rows_surfaces_and_markers(segments):
    layout = load_layout(_write(segments, LAYOUT))
    with pytest.warns(UserWarning, match="zero-padded to degree 3.*small.ply"):
        result = compose(layout)
    s = result.surfels
    assert s.sh_degree == 3 and np.all(np.isfinite(s.means))
    parts = result.parts
    assert parts["row a[0] (seg.ply)"] == parts["row a[1] (seg.ply)"] == 600
    # the second copy follows the first along +x, one segment length later
    fp = {(p.row, p.copy): p.footprint for p in result.placements}
    assert fp[("a", 1)][0, 0] == pytest.approx(fp[("a", 0)][1, 0], abs=0.05)
    # mirror = true reflects y in the segment frame: (0.5, 0.145, 0.25) x2 -> y = 1.5 - 0.29
    b = s.means[1200:1400]
    assert np.any(np.all(np.abs(b - [1.0, 1.5 - 0.29, 0.5]) < 1e-4, axis=1))
    assert [t.id for t in result.tags] == [3]
    np.testing.assert_allclose(result.tags[0].world_from_tag[:3, 3], [4.3, 0.75, 0.4])


def test_configuration_rearranges_rows(segments):
    with pytest.warns(UserWarning, match="zero-padded"):
        result = compose(load_layout(_write(segments, LAYOUT), configuration="wide"))
    rows = [(p.row, p.copy) for p in result.placements]
    assert rows == [("a#0", 0), ("b", 0), ("a#2", 0)]
    centres_y = [p.footprint[:, 1].mean() for p in result.placements]
    np.testing.assert_allclose(centres_y, [0.0, 2.0, 4.0], atol=0.1)


def test_compose_command_writes_scene_and_tags(segments, capsys):
    out = segments / "scene.ply"
    assert cli(["compose", str(_write(segments, LAYOUT)), "--out", str(out), "--summary"]) == 0
    summary = json.loads(capsys.readouterr().out)
    loaded = gs.load_ply(out)
    assert loaded.num == summary["count"] and loaded.sh_degree == 3
    family, tags = load_tags(segments / "scene.tags.json")
    assert family == "tag36h11" and tags[0].id == 3 and tags[0].size == pytest.approx(0.16)


@pytest.mark.parametrize("text, message", [
    ("[[rows]]\nsource = 'nothere.ply'\n[[rows]]\nname='x'\nsource = 'gone.ply'\n",
     "missing files.*gone.ply.*nothere.ply"),
    ("[[rows]]\nname='a'\nsource='seg.ply'\n[[rows]]\nname='b'\nsource='seg.ply'\nposition=[1.0, 0.1, 0.0]\n",
     "overlap"),
    ("[[rows]]\nsource='seg.ply'\nscale=-1\n", "scale must be positive"),
    ("[[rows]]\nsource='seg.ply'\ncolour=[1,2,3]\n", "unknown keys"),
    ("[[markers]]\nid=1\nsize=0.1\nposition=[0,0,0]\n[[markers]]\nid=1\nsize=0.1\nposition=[1,0,0]\n",
     "duplicate marker"),
    ("[[rows]]\nsource='seg.ply'\ncrop_box=[[5,5,5],[6,6,6]]\n", "removed all"),
    ("rows = [\n", "invalid TOML"),
])
def test_bad_layouts_fail_clearly_without_output(segments, capsys, text, message):
    out = segments / "scene.ply"
    assert cli(["compose", str(_write(segments, text)), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "error" in err and re.search(message, err), err
    assert not out.exists() and not list(segments.glob("*.tags.json"))


def test_overlap_can_be_a_warning(segments):
    rows = "[[rows]]\nname='a'\nsource='seg.ply'\n[[rows]]\nname='b'\nsource='seg.ply'\nposition=[1.0, 0.1, 0.0]\n"
    with pytest.raises(LayoutError, match=r"rows a\[0\] and b\[0\] overlap"):
        compose(load_layout(_write(segments, rows)))
    text = "overlap = 'warn'\n" + rows
    with pytest.warns(UserWarning, match="overlap"):
        result = compose(load_layout(_write(segments, text)))
    assert result.surfels.num == 1200


def test_texture_and_ground_colours(tmp_path):
    img = np.zeros((2, 2, 3))
    img[0, 0] = img[1, 1] = 1.0  # a checkerboard, row 0 at the tile's top (high v)
    tex = surfaces.texture_colour(img, tile_size=(2.0, 2.0))
    c = tex(np.zeros((2, 3)), np.array([[0.5, 1.5], [1.5, 1.5]]))  # top-left and top-right cells
    np.testing.assert_allclose(c, [[1, 1, 1], [0, 0, 0]], atol=1e-9)
    captured = gs.make_surfels([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
                               sh_dc=rgb_to_dc(np.array([[1.0, 0, 0], [0, 0, 1.0]])))
    colour = surfaces.ground_colour(captured, k=1)(np.array([[0.1, 0.0, 0.0], [0.9, 0.2, 0.0]]), None)
    np.testing.assert_allclose(colour, [[1, 0, 0], [0, 0, 1]], atol=1e-6)


def test_floor_has_no_gaps_from_robot_height():
    """A floor box seen by a camera 0.4 m up, pitched down 20 deg: every floor pixel opaque."""
    floor = surfaces.box([-0.5, -2.0, -0.02], [4.5, 2.0, 0.0], 0.06, surfaces.constant_colour([0.5, 0.4, 0.3]),
                         faces=("+z",))
    assert floor.num < NUM
    eye = np.array([0.0, 0.0, 0.4])
    target = eye + [np.cos(np.deg2rad(20)), 0.0, -np.sin(np.deg2rad(20))]
    cam = gs.Camera(gs.intrinsics(SIZE, SIZE, 70), gs.look_at(eye, target), SIZE, SIZE)
    alpha = np.asarray(render_stable(floor, cam, CFG, NUM).alpha)
    # rows whose pixel rays hit the floor box inside its extent (below the horizon, in range)
    K, R = np.asarray(cam.K, np.float64), np.asarray(cam.world_to_cam, np.float64)[:3, :3]
    i, j = np.mgrid[0:SIZE, 0:SIZE]
    rays = np.stack([(j + 0.5 - K[0, 2]) / K[0, 0], (i + 0.5 - K[1, 2]) / K[1, 1], np.ones(i.shape)], -1) @ R
    t = -eye[2] / np.where(rays[..., 2] < 0, rays[..., 2], -1e-9)
    hit = eye + t[..., None] * rays
    on_floor = (rays[..., 2] < -0.05) & (hit[..., 0] < 4.4) & (np.abs(hit[..., 1]) < 1.9)
    assert on_floor.mean() > 0.4
    assert alpha[on_floor].min() > 0.98, alpha[on_floor].min()


def test_texture_file_and_mesh_surfaces_from_a_layout(tmp_path):
    import OpenImageIO as oiio
    import trimesh

    tex = np.zeros((4, 4, 3), np.float32)
    tex[:, :2] = [1.0, 0.0, 0.0]  # left half red, right half blue
    tex[:, 2:] = [0.0, 0.0, 1.0]
    out = oiio.ImageOutput.create(str(tmp_path / "tex.png"))
    out.open(str(tmp_path / "tex.png"), oiio.ImageSpec(4, 4, 3, "uint8"))
    out.write_image(tex)
    out.close()
    trimesh.creation.box(extents=[0.5, 0.5, 0.5]).export(tmp_path / "crate.obj")
    text = """
        [[surfaces]]
        kind = "plane"
        center = [1.0, 0.5, 0.0]
        size = [2.0, 1.0]
        spacing = 0.05
        texture = "tex.png"
        texture_size = [2.0, 1.0]

        [[surfaces]]
        kind = "mesh"
        path = "crate.obj"
        spacing = 0.05
        colour = [0.2, 0.6, 0.2]
    """
    result = compose(load_layout(_write(tmp_path, text)))
    s = result.surfels
    rgb = s.sh_dc * 0.28209479177387814 + 0.5
    plane = s.means[:, 2] == 0
    x = s.means[:, 0]  # texel centres (bilinear, wrapping: stay away from the texel edges)
    left, right = plane & (x > 0.3) & (x < 0.7), plane & (x > 1.3) & (x < 1.7)
    np.testing.assert_allclose(rgb[left].mean(0), [1, 0, 0], atol=0.05)
    np.testing.assert_allclose(rgb[right].mean(0), [0, 0, 1], atol=0.05)
    crate = s.take(np.flatnonzero(~plane))
    assert crate.num > 0.7 * 6 * 0.25 / 0.05 ** 2
    # on the cube surface, normals (third rotation column) along the face normal
    assert np.all(np.abs(np.abs(crate.means).max(1) - 0.25) < 1e-4)
    from ghsplat_jax.core.quaternions import to_rotation_matrix_np

    n = to_rotation_matrix_np(crate.quats.astype(np.float64))[..., 2]
    axis = np.argmax(np.abs(crate.means), axis=1)
    np.testing.assert_allclose(np.abs(n[np.arange(crate.num), axis]), 1.0, atol=1e-5)


def test_floor_colour_sampled_from_a_captured_row(segments):
    text = """
        [[rows]]
        name = "a"
        source = "seg.ply"

        [[surfaces]]
        kind = "plane"
        center = [1.0, 0.0, -0.01]
        size = [1.8, 0.5]
        spacing = 0.1
        ground_from = "a"
        ground_max_height = 0.2
    """
    result = compose(load_layout(_write(segments, text)))
    seg = gs.load_ply(segments / "seg.ply")
    low = seg.means[:, 2] <= 0.2
    floor = result.surfels.take(np.arange(600, result.surfels.num))
    # every floor colour is a blend of the captured low surfels' colours
    lo, hi = seg.sh_dc[low].min(0), seg.sh_dc[low].max(0)
    assert np.all((floor.sh_dc >= lo - 1e-5) & (floor.sh_dc <= hi + 1e-5))
    assert floor.sh_dc.std(0).min() > 0.01  # varies like the ground it came from
