"""Cleaning edits, statistics, merging and the `ghsplat export` command."""

import json
import warnings

import numpy as np
import pytest

import ghsplat_jax as gs
from ghsplat_jax.cli import main as cli
from ghsplat_jax.data.ply import read_vertices
from ghsplat_jax.scene import edit, merge, stats


def _plane_with_floaters(seed=0):
    """A dense 1 m^2 plane (1600 surfels), 20 far outliers and a small distant cluster of 8."""
    rng = np.random.default_rng(seed)
    g = (np.arange(40) + 0.5) / 40
    plane = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    plane = np.concatenate([plane, rng.normal(0, 0.002, (len(plane), 1))], axis=1)
    outliers = rng.uniform(-3, 4, (20, 3)) + np.array([0, 0, 3.0])
    cluster = np.array([2.5, 2.5, 0.0]) + rng.normal(0, 0.01, (8, 3))
    x = np.concatenate([plane, outliers, cluster])
    return gs.make_surfels(x, opacity_logits=rng.normal(0, 2, len(x)), sh_degree=1).to_numpy(), len(plane)


def test_crops_keep_and_remove_are_complementary():
    s, _ = _plane_with_floaters()
    for mask_fn in (lambda keep: edit.box_mask(s, [0.2, 0.2, -1], [0.6, 0.7, 1], keep),
                    lambda keep: edit.sphere_mask(s, [0.5, 0.5, 0], 0.3, keep),
                    lambda keep: edit.hull_mask(s, [[0, 0, -1], [1, 0, -1], [0, 1, -1], [0, 0, 1], [1, 1, 1]], keep)):
        keep, remove = mask_fn(True), mask_fn(False)
        assert 0 < keep.sum() < s.num and np.array_equal(keep, ~remove)
    out, mask = edit.crop_box(s, [0.2, 0.2, -1], [0.6, 0.7, 1])
    assert out.num == mask.sum() and np.all(out.means[:, 0] <= 0.6) and np.all(out.means[:, 1] >= 0.2)
    inside = edit.sphere_mask(s, [0.5, 0.5, 0], 0.3)
    assert np.all(np.linalg.norm(s.means[inside] - [0.5, 0.5, 0], axis=1) <= 0.3)


def test_empty_result_and_degenerate_hull_are_errors():
    s, _ = _plane_with_floaters()
    with pytest.raises(edit.EmptyResultError, match="removed all"):
        edit.crop_box(s, [10, 10, 10], [11, 11, 11])
    with pytest.raises(ValueError, match="coplanar|degenerate"):
        edit.hull_mask(s, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])


def test_non_finite_and_opacity():
    s, _ = _plane_with_floaters()
    means = s.means.copy()
    means[3, 1] = np.nan
    rest = s.sh_rest.copy()
    rest[7, 0, 2] = np.inf
    bad = gs.Surfels(means, s.quats, s.log_scales, s.opacity_logits, s.sh_dc, rest)
    out, keep = edit.remove_non_finite(bad)
    assert out.num == s.num - 2 and not keep[3] and not keep[7]
    out, keep = edit.threshold_opacity(s, 0.5)
    assert np.all(1 / (1 + np.exp(-out.opacity_logits)) >= 0.5) and keep.sum() == out.num


def test_floater_removal_drops_outliers_and_small_clusters():
    s, n_plane = _plane_with_floaters()
    out, keep = edit.remove_floaters(s)
    assert keep[:n_plane].mean() > 0.99      # the surface stays
    assert not keep[n_plane:].any()          # every outlier and the small cluster go
    assert out.num == keep.sum()


def test_statistics_are_json_ready():
    s, _ = _plane_with_floaters()
    info = stats.statistics(s)
    json.dumps(info, allow_nan=False)
    assert info["count"] == s.num and info["sh_degree"] == 1 and info["non_finite"] == 0
    assert sum(info["opacity"]["histogram"]["counts"]) == s.num
    np.testing.assert_allclose(info["bounds"]["min"], s.means.min(0), atol=1e-6)


def test_merge_pads_or_truncates_with_a_warning():
    a = gs.make_surfels(np.zeros((3, 3)), sh_degree=1).to_numpy()
    b = gs.make_surfels(np.ones((2, 3)), sh_rest=np.ones((2, 15, 3)), sh_degree=3).to_numpy()
    with pytest.warns(UserWarning, match="zero-padded to degree 3"):
        m = merge.merge([a, b], "pad", ["a.ply", "b.ply"])
    assert m.sh_degree == 3 and m.num == 5 and np.all(m.sh_rest[:3, 3:] == 0) and np.all(m.sh_rest[3:] == 1)
    with pytest.warns(UserWarning, match="truncated to degree 1.*b.ply"):
        m = merge.merge([a, b], "truncate", ["a.ply", "b.ply"])
    assert m.sh_degree == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        merge.merge([a, a])  # same degree: silent


def test_3dgs_files_are_not_mixed_silently(tmp_path):
    s = gs.make_surfels(np.random.default_rng(0).normal(size=(10, 3))).to_numpy()
    gs.save_ply(s, tmp_path / "two.ply")
    gs.save_ply(s, tmp_path / "three.ply", viewer_compatible=True)  # has scale_2: a 3DGS file
    with pytest.raises(merge.MixedFormatError, match="three.ply"):
        merge.load_many([tmp_path / "two.ply", tmp_path / "three.ply"])
    with pytest.warns(UserWarning, match="3DGS"):
        parts, _ = merge.load_many([tmp_path / "two.ply", tmp_path / "three.ply"], allow_mixed_3dgs=True)
    assert [p.num for p in parts] == [10, 10]


def test_export_command_cleans_scales_and_rotates(tmp_path, capsys):
    s, n_plane = _plane_with_floaters()
    gs.save_ply(s, tmp_path / "in.ply")
    out = tmp_path / "out.ply"
    rc = cli(["export", str(tmp_path / "in.ply"), "--out", str(out), "--crop-box", "-1", "-1", "-1", "2", "2", "1",
              "--remove-floaters", "--scale-from-length", "0.5", "1.0", "--rotate", "0", "0", "90",
              "--translate", "1", "0", "0", "--viewer-compatible", "--stats", "--sh-degree", "3",
              "--removed-mask", str(tmp_path / "removed.npy")])
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    v = read_vertices(out)
    assert "scale_2" in v.dtype.names and np.allclose(v["scale_2"], np.log(1e-6))
    assert info["count"] == len(v) and info["sh_degree"] == 3 and len(v) >= 0.99 * n_plane
    removed = np.load(tmp_path / "removed.npy")
    assert removed.shape == (s.num,) and removed[n_plane:].all()
    # plane [0,1]^2 scaled by 2, rotated 90 deg about z, moved by +1 in x: x in [-1, 1], y in [0, 2]
    x, y = np.asarray(v["x"]), np.asarray(v["y"])
    assert -1.01 < x.min() and x.max() < 1.01 and -0.01 < y.min() and y.max() < 2.01
    with pytest.warns(UserWarning, match="3DGS"):
        back = gs.load_ply(out)
    np.testing.assert_allclose(back.log_scales, np.log(0.01) + np.log(2.0), atol=1e-5)


def test_export_refuses_bad_inputs_without_writing(tmp_path, capsys):
    s, _ = _plane_with_floaters()
    good = tmp_path / "good.ply"
    gs.save_ply(s, good)
    (tmp_path / "notply.ply").write_text("hello\n")
    data = good.read_bytes()
    (tmp_path / "truncated.ply").write_bytes(data[: len(data) // 2])
    (tmp_path / "missing.ply").write_bytes(data.replace(b"property float opacity\n", b"property float opacityX\n"))
    out = tmp_path / "out.ply"
    for bad, message in [("notply.ply", "not a PLY"), ("truncated.ply", "truncated"),
                         ("missing.ply", "missing properties"), ("nofile.ply", "no such file")]:
        assert cli(["export", str(good), str(tmp_path / bad), "--out", str(out)]) == 2
        assert message in capsys.readouterr().err
    assert cli(["export", str(good), "--out", str(out), "--crop-sphere", "9", "9", "9", "0.1"]) == 2
    assert "removed all" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.glob(".out.ply*"))


def test_export_drops_nan_surfels_with_a_warning(tmp_path, capsys):
    s, _ = _plane_with_floaters()
    gs.save_ply(s, tmp_path / "in.ply")
    v = read_vertices(tmp_path / "in.ply")
    v["x"][5] = np.nan
    header = (tmp_path / "in.ply").read_bytes().split(b"end_header\n")[0] + b"end_header\n"
    (tmp_path / "nan.ply").write_bytes(header + v.tobytes())
    assert cli(["export", str(tmp_path / "nan.ply"), "--out", str(tmp_path / "out.ply")]) == 0
    assert "non-finite" in capsys.readouterr().err
    assert len(read_vertices(tmp_path / "out.ply")) == s.num - 1
