"""AprilTag localization on rendered frames and the `ghsplat localize` report."""

import json

import numpy as np
import pytest

pytest.importorskip("cv2")

from ghsplat_jax.data.ply import save_ply
from ghsplat_jax.localize import apriltag as localize
from ghsplat_jax.localize import report
from ghsplat_jax.scene import markers, surfaces
from ghsplat_jax.scene.merge import merge
from ghsplat_jax.scene.tags import save_tags
from ghsplat_jax.sim import robot


@pytest.fixture(scope="module")
def tag_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("tags")
    parts = [surfaces.box((-1, -1.5, -0.02), (4, 1.5, 0.0), 0.1, surfaces.constant_colour((0.5, 0.45, 0.4)),
                          faces=("+z",))]
    tags = []
    for i, y in enumerate((-0.3, 0.3)):
        s, t = markers.marker_surfels(i, 0.2, markers.tag_pose((3.0, y, 0.45), facing=(-1, 0, 0)), subdiv=3)
        parts.append(s)
        tags.append(t)
    save_ply(merge(parts), d / "scene.ply")
    save_tags(d / "scene.tags.json", tags)
    (d / "line.csv").write_text("x,y\n1.4,0.05\n1.9,0.05\n")
    return d


def test_detect_and_localize_rendered_tags(tag_scene):
    from ghsplat_jax.sim import scene_io
    from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer

    sc = scene_io.load_scene(tag_scene / "scene.ply")
    tags = {t.id: t for t in sc.tags}
    r = robot.Robot()
    cam = CameraModel.from_fov(r.optical_frame, 320, 240, 60)
    gt = (1.5, 0.05, 0.1)
    frame = CameraRenderer().render(sc.surfels, cam, r.map_from_optical(*gt))
    dets = localize.detect_tags(frame.rgb, cam.matrix, tags)
    assert sorted(d.tag_id for d in dets) == [0, 1]
    assert all(d.reprojection_px < 1.0 for d in dets)
    x, y, yaw = localize.robot_pose(localize.camera_pose(dets, tags, cam.matrix), r)
    assert np.hypot(x - gt[0], y - gt[1]) < 0.05 and abs(np.degrees(yaw - gt[2])) < 2.0
    cands = localize.visible_candidates(tags, frame.map_from_optical, cam.matrix, 320, 240, frame.depth)
    assert sorted(c["id"] for c in cands) == [0, 1] and all(1.3 < c["distance"] < 1.7 for c in cands)
    # turned away: nothing visible, nothing detected
    away = CameraRenderer().render(sc.surfels, cam, r.map_from_optical(1.5, 0.0, np.pi))
    assert localize.detect_tags(away.rgb, cam.matrix, tags) == []
    assert localize.visible_candidates(tags, away.map_from_optical, cam.matrix, 320, 240, away.depth) == []


def test_localize_command_report(tag_scene, tmp_path):
    from ghsplat_jax.cli import main

    out = tmp_path / "loc"
    rc = main(["localize", str(tag_scene / "scene.ply"), "--trajectory", str(tag_scene / "line.csv"), "--out", str(out),
               "--width", "320", "--height", "240", "--fov", "60", "--rate", "2", "--max-frames", "2"])
    assert rc == 0
    res = json.loads((out / "localization.json").read_text())
    s = res["summary"]
    assert s["frames"] == 2 and s["availability"] == 1.0 and s["detection_rate"] == 1.0
    assert s["position_error_m"]["max"] < 0.05
    assert (out / "localization.png").stat().st_size > 1000
    # the chart's data: what it draws is what localization.json says
    series = report.plot_series(res)
    assert series["t"] == [f["t"] for f in res["frames"]] and len(series["t"]) == 2
    np.testing.assert_allclose(series["position_error"], [f["position_error"] for f in res["frames"]])
    assert series["rate_vs_distance"]["rate"] == [r["detection_rate"] for r in s["rate_vs_distance"]] == [1.0]
    fig = report.plot_figure(series)
    drawn = fig.axes[2].lines[0].get_xydata()
    np.testing.assert_allclose(drawn, np.c_[series["t"], series["position_error"]])
    assert [bar.get_height() for bar in fig.axes[0].patches] == series["rate_vs_distance"]["rate"]
    assert "Detection rate against distance" in (out / "report.md").read_text()


def test_localize_command_without_tags_fails_cleanly(tmp_path, capsys):
    from ghsplat_jax.cli import main

    ply = tmp_path / "bare.ply"
    save_ply(surfaces.box((0, 0, 0), (1, 1, 1), 0.25, surfaces.constant_colour((1, 1, 1))), ply)
    assert main(["localize", str(ply), "--out", str(tmp_path / "o")]) == 2
    assert "no tags" in capsys.readouterr().err and not (tmp_path / "o").exists()
