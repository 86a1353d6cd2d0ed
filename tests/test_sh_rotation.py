"""Real-SH rotation and reflection (degrees 1-3) in the 3DGS basis."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ghsplat_jax.core import sh
from ghsplat_jax.core.sh_rotation import band_matrices, rotate_sh_rest, transform_sh_rest


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("degree", [1, 2, 3])
@pytest.mark.parametrize("reflect", [False, True])
def test_evaluation_is_invariant(degree, reflect):
    rng = np.random.default_rng(degree + 10 * reflect)
    M = Rotation.random(random_state=degree).as_matrix()
    if reflect:
        M = M @ np.diag([1.0, -1.0, 1.0])
    k = (degree + 1) ** 2 - 1
    dc, rest = rng.normal(size=(64, 3)), rng.normal(size=(64, k, 3))
    new = transform_sh_rest(rest, M)
    d = _unit(rng, 64)
    before = np.asarray(sh.evaluate(dc, rest, d, degree))
    after = np.asarray(sh.evaluate(dc, new, d @ M.T, degree))
    # the colours clamp at zero; compare raw SH too so the clamp cannot hide errors
    assert np.abs(before - after).max() < 1e-5
    raw = lambda c, r, dirs: np.einsum("nk,nkc->nc", np.asarray(sh.basis(dirs, degree)),
                                       np.concatenate([c[:, None], r], axis=1))
    assert np.abs(raw(dc, rest, d) - raw(dc, new, d @ M.T)).max() < 1e-5
    assert np.abs(new - rest).max() > 0.1  # it did rotate something


def test_band1_matches_the_3dgs_sign_convention():
    # band 1 is C1 * (-y, z, -x) . c, i.e. a linear function a . d with a = (-c2, -c0, c1);
    # rotating the function rotates a: a' = R a. Checked without the fitted matrices.
    R = Rotation.from_euler("xyz", [30, -50, 70], degrees=True).as_matrix()
    c = np.array([0.3, -0.7, 0.2])
    a = np.array([-c[2], -c[0], c[1]])
    a_new = R @ a
    expected = np.array([-a_new[1], a_new[2], -a_new[0]])
    got = rotate_sh_rest(np.repeat(c[None, :, None], 3, axis=2), R)[0, :, 0]
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_band_matrices_compose_and_are_orthogonal():
    R1 = Rotation.random(random_state=1).as_matrix()
    R2 = Rotation.random(random_state=2).as_matrix()
    for D12, D1, D2 in zip(band_matrices(R1 @ R2, 3), band_matrices(R1, 3), band_matrices(R2, 3)):
        np.testing.assert_allclose(D12, D1 @ D2, atol=1e-9)
        np.testing.assert_allclose(D1 @ D1.T, np.eye(len(D1)), atol=1e-9)
    for D in band_matrices(np.eye(3), 3):
        np.testing.assert_allclose(D, np.eye(len(D)), atol=1e-9)


def test_bad_inputs():
    with pytest.raises(ValueError, match="orthogonal"):
        band_matrices(np.diag([1.0, 2.0, 1.0]), 2)
    with pytest.raises(ValueError, match="reflection"):
        rotate_sh_rest(np.zeros((1, 3, 3)), np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="degree"):
        transform_sh_rest(np.zeros((1, 5, 3)), np.eye(3))
    assert transform_sh_rest(np.zeros((2, 0, 3)), np.eye(3)).shape == (2, 0, 3)
