"""Rescale, rigid transform and mirror of surfels, SH included; render invariance."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import ghsplat_jax as gs
from ghsplat_jax.core.quaternions import to_rotation_matrix_np
from ghsplat_jax.scene import transform
from ghsplat_jax.scene.views import render_stable

SIZE = 128
CFG = gs.RasterConfig(background=(0.3, 0.3, 0.3), pair_capacity=1 << 14)  # shared by scene tests
NUM = 8192


def _random_scene(n=300, seed=0):
    rng = np.random.default_rng(seed)
    return gs.make_surfels(
        rng.uniform(-0.5, 0.5, (n, 3)), quats=rng.normal(size=(n, 4)),
        log_scales=np.log(rng.uniform(0.015, 0.06, (n, 2))), opacity_logits=rng.normal(1.0, 1.0, n),
        sh_dc=rng.normal(0, 0.5, (n, 3)), sh_rest=rng.normal(0, 0.3, (n, 15, 3)), sh_degree=3).to_numpy()


def _psnr(a, b):
    return float(-10 * np.log10(max(np.mean((np.asarray(a) - np.asarray(b)) ** 2), 1e-20)))


def test_rescale_only_touches_positions_and_scales():
    s = _random_scene(50)
    out = transform.rescale(s, 2.5)
    np.testing.assert_allclose(out.means, s.means * 2.5, rtol=1e-6)
    np.testing.assert_allclose(out.log_scales, s.log_scales + np.log(2.5), atol=1e-6)
    for f in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
        np.testing.assert_allclose(getattr(out, f), getattr(s, f), atol=1e-6)
    centred = transform.rescale(s, 2.0, center=[1.0, 0.0, 0.0])
    np.testing.assert_allclose(centred.means, (s.means - [1, 0, 0]) * 2 + [1, 0, 0], atol=1e-5)
    with pytest.raises(ValueError):
        transform.rescale(s, -1.0)


def test_scale_from_lengths():
    assert transform.scale_from_length(0.4, 0.8) == pytest.approx(2.0)
    # segment B's row width measured 0.5 where the reference (scale 2) measured 0.6
    assert transform.scale_from_segments(0.5, 0.6, reference_scale=2.0) == pytest.approx(2.4)
    with pytest.raises(ValueError):
        transform.scale_from_length(0.0, 1.0)


def test_rigid_transform_frames():
    s = _random_scene(40)
    R = Rotation.from_euler("xyz", [37, -21, 113], degrees=True).as_matrix()
    out = transform.rigid_transform(s, R, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(out.means, s.means @ R.T + [1, 2, 3], atol=1e-5)
    np.testing.assert_allclose(to_rotation_matrix_np(out.quats.astype(np.float64)),
                               R @ to_rotation_matrix_np(s.quats.astype(np.float64)), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(out.quats, axis=1), np.linalg.norm(s.quats, axis=1), rtol=1e-5)
    with pytest.raises(ValueError, match="reflection"):
        transform.rigid_transform(s, np.diag([1.0, -1.0, 1.0]))


def test_mirror_keeps_a_proper_frame():
    s = _random_scene(40)
    out = transform.mirror(s, "y", origin=[0.0, 1.0, 0.0])
    M = np.diag([1.0, -1.0, 1.0])
    np.testing.assert_allclose(out.means, s.means @ M + [0, 2, 0], atol=1e-5)
    old, new = to_rotation_matrix_np(s.quats.astype(np.float64)), to_rotation_matrix_np(out.quats.astype(np.float64))
    assert np.allclose(np.linalg.det(new), 1.0, atol=1e-5)
    # tangent roles swap (and their scales), the normal is reflected
    np.testing.assert_allclose(new[..., 0], old[..., 1] @ M, atol=1e-5)
    np.testing.assert_allclose(new[..., 1], old[..., 0] @ M, atol=1e-5)
    np.testing.assert_allclose(new[..., 2], old[..., 2] @ M, atol=1e-5)
    np.testing.assert_allclose(out.log_scales, s.log_scales[:, ::-1])


@pytest.mark.parametrize("reflect", [False, True])
def test_render_of_transformed_scene_matches(reflect):
    """The scene moved by an arbitrary similarity, seen from the moved camera, renders the
    same image (mirrored left-right for a reflection): PSNR >= 45 dB. Without rotating the
    SH it does not, so the test does measure the SH rotation."""
    s = _random_scene()
    K = gs.intrinsics(SIZE, SIZE, 60)
    w2c = gs.look_at([0.3, -2.0, 0.8], [0.0, 0.0, 0.0])
    M = Rotation.from_euler("xyz", [37, -21, 113], degrees=True).as_matrix()
    if reflect:
        M = M @ np.diag([1.0, -1.0, 1.0])
    scale, t = 1.7, np.array([1.5, -0.3, 2.0])
    moved = transform.similarity(s, scale, M, t)
    cam2 = gs.Camera(K, transform.transform_camera(w2c, scale, M, t), SIZE, SIZE)
    ref = np.asarray(render_stable(s, gs.Camera(K, w2c, SIZE, SIZE), CFG, NUM).rgb)
    flip = (lambda im: im[:, ::-1]) if reflect else (lambda im: im)
    got = flip(np.asarray(render_stable(moved, cam2, CFG, NUM).rgb))
    assert ref.std() > 0.05  # a real image, not an empty frame
    psnr = _psnr(ref, got)
    assert psnr >= 45.0, psnr
    unrotated = gs.Surfels(moved.means, moved.quats, moved.log_scales, moved.opacity_logits,
                           moved.sh_dc, s.sh_rest)
    assert _psnr(ref, flip(np.asarray(render_stable(unrotated, cam2, CFG, NUM).rgb))) < 35.0
