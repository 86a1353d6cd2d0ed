"""Properties of the one rotation module (core.quaternions): round trips, composition,
jnp and NumPy agreeing, and agreement with scipy's Rotation (which is x-y-z-w)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from ghsplat_jax.core import quaternions as q
from ghsplat_jax.sim import frames

# Quaternions of any scale away from zero (files and training keep them unnormalised).
finite = st.floats(-10.0, 10.0, allow_nan=False, width=64)
quats = arrays(np.float64, 4, elements=finite).filter(lambda v: np.linalg.norm(v) > 1e-3)
angles = arrays(np.float64, 3, elements=st.floats(-np.pi, np.pi, width=64))
CHECKS = settings(max_examples=200, deadline=None)


def unit(v):
    return v / np.linalg.norm(v)


def same_rotation(a, b):
    """Unit quaternions a and b describe one rotation (q and -q do)."""
    return np.isclose(abs(np.dot(unit(a), unit(b))), 1.0, atol=1e-9)


@CHECKS
@given(quats)
def test_quaternion_matrix_round_trip(v):
    R = q.to_rotation_matrix_np(v)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    back = q.from_rotation_matrix(R)
    assert back[0] >= 0 and np.isclose(np.linalg.norm(back), 1.0)
    assert same_rotation(back, v)
    np.testing.assert_allclose(q.to_rotation_matrix_np(back), R, atol=1e-12)


@CHECKS
@given(quats, quats)
def test_product_composes_rotations(a, b):
    np.testing.assert_allclose(q.to_rotation_matrix_np(q.multiply_np(a, b)),
                               q.to_rotation_matrix_np(a) @ q.to_rotation_matrix_np(b), atol=1e-10)
    np.testing.assert_allclose(np.asarray(q.multiply(jnp.asarray(unit(a), jnp.float32), jnp.asarray(unit(b),
                                                                                                     jnp.float32))),
                               q.multiply_np(unit(a), unit(b)), atol=1e-5)


@CHECKS
@given(quats)
def test_jnp_and_numpy_agree(v):
    np.testing.assert_allclose(np.asarray(q.to_rotation_matrix(jnp.asarray(unit(v), jnp.float32))),
                               q.to_rotation_matrix_np(v), atol=1e-5)


@CHECKS
@given(quats)
def test_agrees_with_scipy_in_its_order(v):
    """scipy is x-y-z-w: the boundary conversions are what make the two agree."""
    theirs = Rotation.from_quat(q.wxyz_to_xyzw(v))
    np.testing.assert_allclose(q.to_rotation_matrix_np(v), theirs.as_matrix(), atol=1e-12)
    R = theirs.as_matrix()
    assert same_rotation(q.xyzw_to_wxyz(Rotation.from_matrix(R).as_quat()), q.from_rotation_matrix(R))
    np.testing.assert_array_equal(q.xyzw_to_wxyz(q.wxyz_to_xyzw(v)), v)


@CHECKS
@given(angles)
def test_euler_matches_scipy_extrinsic_xyz(a):
    np.testing.assert_allclose(q.from_euler_xyz(a), Rotation.from_euler("xyz", a).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(q.from_euler_xyz(np.degrees(a), degrees=True), q.from_euler_xyz(a), atol=1e-12)


@CHECKS
@given(quats, arrays(np.float64, 3, elements=finite))
def test_ros_pose_round_trip_names_its_order(v, position):
    """sim.frames speaks ROS's x-y-z-w; a pose survives matrix -> message quaternion -> matrix."""
    T = frames.make_transform(q.to_rotation_matrix_np(v), position)
    xyzw = frames.quat_xyzw(T)
    assert same_rotation(q.xyzw_to_wxyz(xyzw), v) and xyzw[3] >= 0
    np.testing.assert_allclose(frames.from_pose(position, xyzw), T, atol=1e-12)


def test_batched_shapes_and_edge_rotations():
    half_turns = np.array([[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0]], float)  # w = 0 cases
    R = q.to_rotation_matrix_np(half_turns.reshape(2, 2, 4))
    assert R.shape == (2, 2, 3, 3)
    back = q.from_rotation_matrix(R).reshape(4, 4)
    np.testing.assert_allclose(np.abs(back), np.abs(half_turns), atol=1e-12)
    np.testing.assert_allclose(np.diagonal(R.reshape(4, 3, 3), axis1=1, axis2=2),
                               [[1, -1, -1], [-1, 1, -1], [-1, -1, 1], [1, 1, 1]], atol=1e-12)
