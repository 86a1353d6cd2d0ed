import jax
import jax.numpy as jnp
import numpy as np

import ghsplat_jax as gs
from ghsplat_jax.core import quaternions, sh


def test_quaternion_matrix_round_trip_and_product():
    r = np.random.default_rng(0)
    q = r.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    R = np.asarray(quaternions.to_rotation_matrix(jnp.asarray(q)), np.float64)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
    np.testing.assert_allclose(quaternions.from_rotation_matrix(R), q, atol=1e-5)
    ab = quaternions.multiply(jnp.asarray(q[:-1]), jnp.asarray(q[1:]))
    np.testing.assert_allclose(quaternions.to_rotation_matrix(ab), R[:-1] @ R[1:], atol=1e-5)


def test_safe_normalize_zero_and_nan_have_finite_gradients():
    q = jnp.array([[0.0, 0, 0, 0], [2.0, 0, 0, 0], [jnp.nan, 1, 0, 0]])
    unit, ok = quaternions.safe_normalize(q)
    assert ok.tolist() == [False, True, False]
    assert bool(jnp.all(jnp.isfinite(unit)))
    g = jax.grad(lambda q: jnp.sum(quaternions.safe_normalize(q)[0]))(q.at[2, 0].set(1.0))
    assert bool(jnp.all(jnp.isfinite(g)))


def test_sh_dc_only_colour_and_basis_orthonormality():
    np.testing.assert_allclose(sh.evaluate(sh.rgb_to_dc(jnp.array([0.2, 0.5, 0.9])), jnp.zeros((0, 3)),
                                           jnp.array([0.0, 0, 1]), 0), [0.2, 0.5, 0.9], atol=1e-6)
    # Monte-Carlo check that the 16 basis functions are orthonormal on the sphere.
    d = np.random.default_rng(1).normal(size=(200000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    B = np.asarray(sh.basis(jnp.asarray(d), 3), np.float64)
    gram = 4 * np.pi * B.T @ B / len(d)
    np.testing.assert_allclose(gram, np.eye(16), atol=0.03)


def test_sh_colour_and_gradients_match_the_basis_contraction():
    """The planes-and-hand-written-gradient colour equals basis . coefficients, with autodiff's
    gradients, at every degree and with unused higher bands in sh_rest."""
    r = np.random.default_rng(2)
    dc = jnp.asarray(r.normal(size=(2, 7, 3)), jnp.float32)
    rest = jnp.asarray(r.normal(size=(2, 7, 15, 3)), jnp.float32)
    d = r.normal(size=(2, 7, 3))
    dirs = jnp.asarray(d / np.linalg.norm(d, axis=-1, keepdims=True), jnp.float32)
    g = jnp.asarray(r.normal(size=(2, 7, 3)), jnp.float32)

    def contraction(dc, rest, dirs, degree):
        k = (degree + 1) ** 2
        coeffs = jnp.concatenate([dc[..., None, :], rest[..., : k - 1, :]], axis=-2)
        return jnp.maximum(jnp.einsum("...k,...kc->...c", sh.basis(dirs, degree), coeffs) + 0.5, 0.0)

    for degree in range(4):
        ours, pull = jax.vjp(lambda *a: sh.evaluate(*a, degree), dc, rest, dirs)
        want, pull_want = jax.vjp(lambda *a: contraction(*a, degree), dc, rest, dirs)
        np.testing.assert_allclose(ours, want, atol=1e-5)
        for got, expected in zip(pull(g), pull_want(g)):
            np.testing.assert_allclose(got, expected, atol=1e-5)


def test_camera_look_at_and_centre():
    w2c = gs.look_at([1.0, -2.0, 0.5], [0.0, 0.0, 0.5])
    cam = gs.Camera(K=gs.intrinsics(64, 48, 90), world_to_cam=w2c, width=64, height=48)
    np.testing.assert_allclose(cam.center, [1.0, -2.0, 0.5], atol=1e-6)
    # The target projects to the principal point; world up points to image up (-y).
    target = w2c[:3, :3] @ [0.0, 0, 0.5] + w2c[:3, 3]
    np.testing.assert_allclose(target[:2], 0, atol=1e-6)
    up = w2c[:3, :3] @ [0.0, 0, 1]
    assert up[1] < -0.99
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (32, 24)
    np.testing.assert_allclose(half.K[0, 2], 16.0)


def test_project_points_lands_the_target_on_the_principal_point_and_keeps_z_finite():
    from ghsplat_jax.core.camera import project_points

    w2c = gs.look_at([1.0, -2.0, 0.5], [0.0, 0.0, 0.5])
    K = gs.intrinsics(64, 48, 90)
    xy, z = project_points([[0.0, 0.0, 0.5], [1.0, -2.0, 1.5]], K, w2c)
    np.testing.assert_allclose(xy[0], K[:2, 2], atol=1e-5)
    np.testing.assert_allclose(z[0], np.sqrt(5.0), rtol=1e-6)  # the target's distance along the axis
    assert xy[1, 1] < 0  # straight above the camera: towards the image's top
    xy, z = project_points([[0.3, 0.2, 0.0]], K, np.eye(4))
    assert z[0] == 0 and np.isfinite(xy).all()  # in the camera's plane: finite, never NaN
