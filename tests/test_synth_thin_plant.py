"""The thin-plant scene preset (synth PRESETS["thin-plant"]): one plant with stems and leaves a
few pixels wide on a black background, written as cameras without points."""

import numpy as np
import pytest

from ghsplat_jax.data.images import read_pixels
from ghsplat_jax.synth import capture, config, dataset, render, scene


@pytest.fixture(scope="module")
def thin():
    return scene.generate_scene(config.preset_config("thin-plant"))


def _cams(world, n=4):
    path = capture.PathConfig(orbit_radius=0.5, height=0.8, target_height=0.3)
    return capture.capture_path(world, "orbit", n, width=128, height=96, config=path)


def _runs(mask: np.ndarray) -> list[int]:
    """Lengths of the runs of True along each row of `mask`."""
    out = []
    for row in mask:
        d = np.diff(np.concatenate([[0], row.astype(int), [0]]))
        out += list(np.flatnonzero(d == -1) - np.flatnonzero(d == 1))
    return out


def test_only_the_plant_on_black(thin):
    assert [i.cls for i in thin.instances] == ["plant"]
    view = render.render_view(thin, _cams(thin)[0], supersample=1)  # each pixel the plant's or the background's
    empty = view["instance"] == 0
    assert 0.005 < (~empty).mean() < 0.1  # a thin subject: a few % of the image
    assert np.all(view["rgb"][empty] == 0)  # a black background, not the sky
    assert view["rgb"][~empty].mean() > 0.05


def test_photos_are_anti_aliased_as_a_camera_integrates_each_pixel(thin):
    """A leaf edge that crosses a pixel off its centre still tints it: without that, leaves a
    pixel or two wide are an on/off pattern that no band-limited model can fit."""
    cam = _cams(thin)[0]
    smooth, sampled = render.render_view(thin, cam), render.render_view(thin, cam, supersample=1)
    empty = smooth["instance"] == 0
    assert thin.config.render.supersample > 1
    assert np.all(sampled["rgb"][empty] == 0)  # point-sampled: a pixel is the plant's or black
    tinted = empty & (smooth["rgb"].max(-1) > 0.01)
    assert tinted.sum() > 0.2 * (~empty).sum()  # partly covered pixels all along the thin edges


def test_stems_and_leaves_are_a_few_pixels_wide(thin):
    widths = []
    for cam in _cams(thin):
        widths += _runs(render.render_view(thin, cam)["instance"] > 0)
    # horizontal runs across a mostly upright plant: the stem's and leaves' widths in pixels
    assert 1 <= np.median(widths) <= 4
    assert np.percentile(widths, 90) <= 8
    # the default plant is far wider at the same size and distance
    default = config.preset_config("thin-plant", {"plant": {"leaf_width": 1.0, "stem_radius": 0.006}})
    wide = scene.generate_scene(default)
    assert np.percentile(_runs(render.render_view(wide, _cams(wide)[0])["instance"] > 0), 90) > 10


def test_defaults_are_unchanged_by_the_new_fields():
    cfg = config.SceneConfig()
    assert (cfg.plant.stem_radius, cfg.plant.leaf_width, cfg.render.background) == (0.006, 1.0, "sky")
    with pytest.raises(ValueError, match="render.background"):
        config.config_from_dict({"render": {"background": "grey"}})
    with pytest.raises(ValueError, match="unknown scene preset"):
        config.preset_config("no-such-preset")


def test_dataset_with_cameras_and_no_points(thin, tmp_path):
    from ghsplat_jax.data.dataset import load_dataset

    cams = _cams(thin, 6)
    out = dataset.write_dataset(thin, cams, tmp_path / "thin", n_points=0, meshes=False)
    text = (out / "sparse" / "0" / "points3D.txt").read_text()
    assert "# Number of points: 0" in text and not [ln for ln in text.splitlines() if not ln.startswith("#")]
    mask = read_pixels(out / "masks" / "00000.png").reshape(96, 128)
    assert 0 < (mask > 0).mean() < 0.1  # the foreground mask the study scores the plant's pixels with
    ds = load_dataset(out)
    assert len(ds.train) + len(ds.test) == 6 and (ds.points is None or len(ds.points) == 0)
