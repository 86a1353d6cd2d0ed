"""The viser viewer serves on loopback and takes the simulation stream."""

import socket
import urllib.request

import numpy as np
import pytest

pytest.importorskip("viser")

from ghsplat_jax.scene import surfaces
from ghsplat_jax.sim import robot
from ghsplat_jax.sim.camera_sensor import CameraFrame, CameraModel
from ghsplat_jax.sim.scene_io import SimScene
from ghsplat_jax.transport import viewer


def test_viewer_serves_and_updates():
    s = surfaces.box((0, 0, 0), (1, 1, 1), 0.25, surfaces.constant_colour((0.2, 0.7, 0.2)))
    splats = viewer.surfel_splats(s)
    assert splats["covariances"].shape == (s.num, 3, 3) and np.all(splats["opacities"] > 0)
    # covariance is flat along each surfel's normal
    assert np.allclose(np.linalg.eigvalsh(splats["covariances"][0])[0], 1e-6, rtol=1e-3)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    r = robot.Robot()
    v = viewer.SimViewer(SimScene(None, s, [], None), r, port=port)
    try:
        model = CameraModel.from_fov(r.optical_frame, 32, 24, 60)
        v.sink("/tf", None, 1.0, r.base_transform(1.0, 0.5, 0.3, 1.0))
        assert np.allclose(v.base.position, [1.0, 0.5, 0.0])
        v.sink("/render", None, 1.0, CameraFrame(1.0, model, np.eye(4), np.random.rand(24, 32, 3).astype(np.float32),
                                                 np.ones((24, 32)), np.ones((24, 32)), np.zeros((24, 32, 3))))
        v.set_cloud(np.r_[np.random.rand(50, 3), np.full((3, 3), np.nan)])
        assert v.counts == {"images": 1, "clouds": 1, "poses": 1}
        html = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10).read()
        assert b"<html" in html.lower()
    finally:
        v.close()


def _chromium():
    import shutil

    return next((shutil.which(n) for n in ("chromium-headless-shell", "chromium", "chromium-browser")
                 if shutil.which(n)), None)


@pytest.mark.slow  # starts a headless browser
@pytest.mark.skipif(_chromium() is None, reason="no headless Chromium (make install adds chromium-headless-shell)")
def test_viewer_screenshot_in_headless_chromium(tmp_path):
    """A real browser renders the page: the surfel box and the LiDAR points are on screen."""
    import subprocess

    from ghsplat_jax.data.images import read_image

    s = surfaces.box((0, 0, 0), (1, 1, 1), 0.1, surfaces.constant_colour((0.2, 0.7, 0.2)))
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    v = viewer.SimViewer(SimScene(None, s, [], None), robot.Robot(), port=port)
    try:
        v.set_cloud(np.random.default_rng(0).random((500, 3)) * 2)
        # The page builds its scene over a websocket, which virtual time does not wait for; a loaded
        # machine can leave the first screenshot blank, so try again with more time before judging.
        for attempt, budget_ms in enumerate((15000, 30000, 60000, 120000)):
            shot = tmp_path / f"viewer{attempt}.png"
            subprocess.run([_chromium(), "--no-sandbox", "--headless", "--disable-gpu", "--enable-unsafe-swiftshader",
                            "--use-angle=swiftshader", "--window-size=800,600", f"--virtual-time-budget={budget_ms}",
                            f"--screenshot={shot}", f"http://127.0.0.1:{port}/"],
                           capture_output=True, timeout=180, check=True)
            rgb, _ = read_image(shot)
            green = (rgb[..., 1] > rgb[..., 0] + 0.2) & (rgb[..., 1] > rgb[..., 2] + 0.2)
            if green.sum() > 2000:
                break
    finally:
        v.close()
    assert rgb.std() > 0.05  # not blank
    assert green.sum() > 2000  # the splatted surfel box is drawn
