"""benchmarks/background_coverage.py: rendered alpha over an RGBA image's empty background."""

import numpy as np
import pytest

from benchmark_scripts import load_benchmark


def test_coverage_counts_only_the_pixels_the_image_leaves_empty():
    import ghsplat_jax as gs
    from ghsplat_jax.data.dataset import View

    bc = load_benchmark("background_coverage")
    cam = gs.Camera(gs.intrinsics(8, 4, 10), gs.look_at([0, -4, 0], [0, 0, 0]), 8, 4)
    image_alpha = np.zeros((4, 8), np.float32)
    image_alpha[:, :4] = 1.0  # the object fills the left half
    view = View("v", cam, np.ones((4, 8, 3), np.float32), image_alpha)
    rendered_alpha = np.zeros((4, 8), np.float32)
    rendered_alpha[:, :4] = 1.0
    rendered_alpha[0, 4:] = 0.5  # one background row half covered
    rendered_alpha[1, 4:] = 0.02  # one below the visible threshold
    rgb = np.ones((4, 8, 3), np.float32)
    rgb[0, 0] = 0.0  # one wrong pixel: mse 3/96 -> 15.05 dB
    m = bc.view_coverage(rgb, rendered_alpha, view)
    assert m["background_fraction"] == 0.5
    assert m["background_covered"] == 0.25
    assert m["background_alpha_mean"] == pytest.approx((0.5 * 4 + 0.02 * 4) / 16)
    assert m["psnr"] == pytest.approx(-10 * np.log10(3 / 96))
