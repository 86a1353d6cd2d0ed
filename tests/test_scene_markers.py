"""AprilTag 36h11 markers made of surfels: bits, layout, and detection in renders."""

import numpy as np
import pytest

import ghsplat_jax as gs
from ghsplat_jax.core import sh
from ghsplat_jax.scene import markers
from ghsplat_jax.scene.views import render_stable

cv2 = pytest.importorskip("cv2")

CFG = gs.RasterConfig(background=(0.3, 0.3, 0.3), pair_capacity=1 << 14)
NUM, SIZE = 8192, 128


def test_bits_have_a_black_border_and_match_the_dictionary():
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    for tag_id in (0, 7, 586):
        bits = markers.tag_bits(tag_id)
        assert bits.shape == (8, 8)
        assert not bits[0].any() and not bits[-1].any() and not bits[:, 0].any() and not bits[:, -1].any()
        # the 6x6 data bits identify the marker in cv2's own dictionary
        found, idx, rotation = d.identify(bits[1:-1, 1:-1].astype(np.uint8), 0.0)
        assert found and idx == tag_id and rotation == 0
    with pytest.raises(ValueError, match="0..586"):
        markers.tag_bits(587)


def test_surfel_layout_matches_the_size_convention():
    size, subdiv = 0.2, 4
    s = markers.marker_surfels_tag_frame(5, size, subdiv=subdiv, quiet_zone=1.0)
    cell = size / 8
    assert s.num == (10 * subdiv) ** 2
    half = 5 * cell  # black border edge/2 plus one quiet-zone cell
    pitch = cell / subdiv
    np.testing.assert_allclose(np.abs(s.means[:, :2]).max(), half - pitch / 2, atol=1e-6)
    assert np.all(s.means[:, 2] == 0)
    rgb = s.sh_dc * sh.C0 + 0.5
    border = (np.abs(s.means[:, :2]).max(1) > 3 * cell) & (np.abs(s.means[:, :2]).max(1) < 4 * cell)
    quiet = np.abs(s.means[:, :2]).max(1) > 4 * cell
    assert np.allclose(rgb[border], 0.0, atol=1e-6) and np.allclose(rgb[quiet], 1.0, atol=1e-6)
    assert np.all(1 / (1 + np.exp(-s.opacity_logits)) > 0.98)
    plated = markers.marker_surfels_tag_frame(5, size, backing=markers.Backing(margin=0.02, thickness=0.01))
    assert plated.num > s.num and plated.means[:, 2].min() == pytest.approx(-0.01, abs=1e-4)


def test_tag_pose_faces_the_given_direction():
    T = markers.tag_pose([1, 2, 3], facing=[-1, 0, 0])
    np.testing.assert_allclose(T[:3, 2], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 1], [0, 0, 1], atol=1e-12)  # tag y is up
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="parallel"):
        markers.tag_pose([0, 0, 0], facing=[0, 0, 1])


def _detect(gray):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)
    corners, ids, _ = detector.detectMarkers(gray)
    return corners, ids


@pytest.mark.parametrize("tag_id, backing", [(0, False), (42, True)])
def test_rendered_markers_are_detected_with_accurate_pose(tag_id, backing):
    """Fronto-parallel and 45 degrees, 0.6 m away: ID recovered and solvePnP (IPPE_SQUARE)
    position error under 1% of the distance."""
    world_from_tag = markers.tag_pose([0.5, 1.0, 0.4], facing=[-1.0, 0.0, 0.0])
    s, tag = markers.marker_surfels(tag_id, 0.16, world_from_tag,
                                    backing=markers.Backing() if backing else None)
    K = gs.intrinsics(SIZE, SIZE, 40)
    centre, normal, right = world_from_tag[:3, 3], world_from_tag[:3, 2], world_from_tag[:3, 0]
    for angle in (0.0, 45.0):
        a = np.deg2rad(angle)
        eye = centre + 0.6 * (np.cos(a) * normal + np.sin(a) * right)
        w2c = gs.look_at(eye, centre)
        rgb = np.asarray(render_stable(s, gs.Camera(K, w2c, SIZE, SIZE), CFG, NUM).rgb)
        gray = cv2.cvtColor((np.clip(rgb, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        corners, ids = _detect(gray)
        assert ids is not None and ids.ravel().tolist() == [tag_id], (angle, ids)
        # OpenCV puts pixel centres at integers, this project at +0.5
        image_points = corners[0].reshape(4, 2).astype(np.float64) + 0.5
        ok, rvec, tvec = cv2.solvePnP(tag.corners_tag(), image_points, np.asarray(K, np.float64), None,
                                      flags=cv2.SOLVEPNP_IPPE_SQUARE)
        truth = np.asarray(w2c, np.float64) @ tag.world_from_tag
        error = np.linalg.norm(tvec.ravel() - truth[:3, 3]) / np.linalg.norm(truth[:3, 3])
        assert ok and error < 0.01, (angle, error)
        R = cv2.Rodrigues(rvec)[0]
        rot_error = np.degrees(np.arccos(np.clip((np.trace(R.T @ truth[:3, :3]) - 1) / 2, -1, 1)))
        print(f"tag {tag_id} at {angle:.0f} deg: position error {100 * error:.2f}% of distance, "
              f"rotation {rot_error:.1f} deg")
        assert rot_error < 10.0  # loose: the tilt of a small planar tag seen head-on is ill-conditioned
