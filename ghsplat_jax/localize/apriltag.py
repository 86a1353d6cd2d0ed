"""AprilTag localization on rendered frames (proof of concept).

Detection: cv2.aruco.ArucoDetector, DICT_APRILTAG_36h11, AprilTag corner refinement.
Per tag: SOLVEPNP_IPPE_SQUARE on the four corners (tag frame of scene/tags.py = ArUco
object points) gives optical_from_tag, both of its solutions kept (small or frontal tags
are ambiguous). The camera pose: the single-tag solution that leaves the robot level
(a ground-robot prior; without a robot, the lowest reprojection error), refined on all
detected corners at once (Levenberg-Marquardt, world corners from the tags file). The
robot pose is the camera pose composed with the inverse of the mount.

Evaluation along a trajectory: for every frame, each tag that should be visible (in
front of the camera, facing it, its centre inside the image and not hidden behind other
geometry according to the rendered depth) is a candidate; detection rate is reported
against distance and viewing angle; position and yaw errors of the robot against ground
truth; availability = fraction of frames with at least one tag detected (frames_along gives
the frames of a trajectory; report.py writes the report).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.sim import frames


@dataclasses.dataclass
class Detection:
    tag_id: int
    corners: np.ndarray        # (4,2) pixels, OpenCV order
    optical_from_tag: np.ndarray
    reprojection_px: float
    alternatives: list = dataclasses.field(default_factory=list)  # every IPPE solution (4x4)


def make_detector():
    import cv2

    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)


def _to_gray(rgb: np.ndarray) -> np.ndarray:
    import cv2

    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        a = np.clip(np.round(np.nan_to_num(a) * 255), 0, 255).astype(np.uint8)
    return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a


def detect_tags(rgb: np.ndarray, K: np.ndarray, tags: dict, detector=None) -> list[Detection]:
    """Detections of known tags (`tags`: id -> scene.tags.Tag) with single-tag poses."""
    import cv2

    detector = detector or make_detector()
    corners, ids, _ = detector.detectMarkers(_to_gray(rgb))
    out = []
    if ids is None:
        return out
    K = np.asarray(K, np.float64)
    for c, i in zip(corners, ids.ravel()):
        tag = tags.get(int(i))
        if tag is None:
            continue
        img = c.reshape(4, 2).astype(np.float64)
        obj = tag.corners_tag()
        # A small or frontal tag is ambiguous (two poses reproject almost equally well):
        # keep both IPPE solutions, best first, for a prior to choose between.
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if not n:
            continue
        sols = [frames.make_transform(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs)]
        errs = np.asarray(errs, np.float64).ravel()
        order = np.argsort(errs)
        out.append(Detection(int(i), img, sols[order[0]], float(errs[order[0]]), [sols[k] for k in order]))
    return out


def _tilt(map_from_opt: np.ndarray, robot) -> float:
    """How far the implied base_link is from level (radians): a ground robot's is ~0."""
    base_from_optical = robot.camera.matrix() @ frames.make_transform(frames.LINK_FROM_OPTICAL_R)
    z = (map_from_opt @ frames.invert(base_from_optical))[:3, 2]
    return float(np.arccos(np.clip(z[2], -1.0, 1.0)))


def camera_pose(detections: list[Detection], tags: dict, K: np.ndarray, robot=None) -> np.ndarray | None:
    """map_from_optical from every detected tag's corners (None without detections).

    With a `robot`, the ground-robot prior picks among each tag's IPPE solutions the one
    that leaves base_link level (it resolves the flip of small, frontal tags)."""
    import cv2

    if not detections:
        return None
    candidates = []
    for d in detections:
        for k, sol in enumerate(d.alternatives or [d.optical_from_tag]):
            T = tags[d.tag_id].world_from_tag @ frames.invert(sol)
            score = _tilt(T, robot) if robot is not None else d.reprojection_px + k
            candidates.append((score, d.reprojection_px, T))
    map_from_opt = min(candidates, key=lambda c: (c[0], c[1]))[2]
    if len(detections) == 1:
        return map_from_opt
    obj = np.concatenate([tags[d.tag_id].corners_world() for d in detections])
    img = np.concatenate([d.corners for d in detections])
    opt_from_map = frames.invert(map_from_opt)
    rvec, _ = cv2.Rodrigues(opt_from_map[:3, :3])
    tvec = opt_from_map[:3, 3].reshape(3, 1).copy()
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, np.asarray(K, np.float64), None, rvec, tvec)
    return frames.invert(frames.make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel()))


def robot_pose(map_from_optical: np.ndarray, robot) -> tuple[float, float, float]:
    """(x, y, yaw) of base_link from the camera pose and the robot's mount."""
    base_from_optical = robot.camera.matrix() @ frames.make_transform(frames.LINK_FROM_OPTICAL_R)
    T = map_from_optical @ frames.invert(base_from_optical)
    return float(T[0, 3]), float(T[1, 3]), frames.yaw_of(T)


def visible_candidates(tags: dict, map_from_optical: np.ndarray, K: np.ndarray, width: int, height: int,
                       depth: np.ndarray | None = None, occlusion_tol: float = 0.05) -> list[dict]:
    """Tags that a perfect detector would see: centre in front and inside the image, face
    toward the camera, not occluded (rendered depth at the centre within `occlusion_tol`)."""
    opt_from_map = frames.invert(map_from_optical)
    out = []
    for tag in tags.values():
        c_world = tag.world_from_tag[:3, 3]
        c = opt_from_map[:3, :3] @ c_world + opt_from_map[:3, 3]
        if c[2] <= 0.1:
            continue
        u, v = (K @ (c / c[2]))[:2]
        if not (0 <= u < width and 0 <= v < height):
            continue
        normal = opt_from_map[:3, :3] @ tag.world_from_tag[:3, 2]
        to_cam = -c / np.linalg.norm(c)
        angle = float(np.degrees(np.arccos(np.clip(normal @ to_cam, -1, 1))))
        if angle >= 90:
            continue
        if depth is not None:
            d = depth[int(v), int(u)]
            if not np.isfinite(d) or abs(d - c[2]) > occlusion_tol:
                continue
        out.append({"id": tag.id, "distance": float(np.linalg.norm(c)), "angle_deg": angle})
    return out


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def evaluate(frames_iter, tags: dict, robot) -> dict:
    """frames_iter yields (t, (x, y, yaw) ground truth, CameraFrame). Returns per-frame
    and per-candidate records plus summary numbers."""
    detector = make_detector()
    per_frame, per_candidate = [], []
    for t, gt, frame in frames_iter:
        K = frame.model.matrix
        dets = detect_tags(frame.rgb, K, tags, detector)
        seen = {d.tag_id for d in dets}
        candidates = visible_candidates(tags, frame.map_from_optical, K, frame.model.width, frame.model.height,
                                        frame.depth)
        for c in candidates:
            per_candidate.append({**c, "t": t, "detected": c["id"] in seen})
        rec = {"t": t, "gt": [float(v) for v in gt], "detected": sorted(seen), "estimate": None,
               "position_error": None, "yaw_error_deg": None}
        T = camera_pose(dets, tags, K, robot)
        if T is not None:
            x, y, yaw = robot_pose(T, robot)
            rec["estimate"] = [x, y, yaw]
            rec["position_error"] = float(np.hypot(x - gt[0], y - gt[1]))
            rec["yaw_error_deg"] = float(np.degrees(abs(wrap(yaw - gt[2]))))
        per_frame.append(rec)
    return {"frames": per_frame, "candidates": per_candidate, "summary": summarize(per_frame, per_candidate)}


def frames_along(surfels, robot, traj, camera, renderer, rate: float, max_frames: int | None = None,
                 progress: bool = True):
    """What `evaluate` reads: (t, (x, y, yaw) ground truth, CameraFrame) for the robot camera
    (`camera`, a sim.camera_sensor.CameraModel) rendered `rate` times per simulated second along
    `traj`, at most `max_frames` frames."""
    from tqdm.auto import tqdm

    from ghsplat_jax.sim import simulate

    cfg = simulate.SimConfig(camera_rate=rate, lidar_rate=0.0, max_events=max_frames)
    for ev in tqdm(simulate.schedule(traj, cfg), desc="localize", unit="frame", dynamic_ncols=True,
                   disable=not progress):
        x, y, yaw = ev.pose
        yield ev.t, (x, y, yaw), renderer.render(surfels, camera, robot.map_from_optical(x, y, yaw), ev.t)


def _rate_table(cands: list[dict], key: str, edges) -> list[dict]:
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = [c for c in cands if lo <= c[key] < hi]
        if sel:
            rows.append({"lo": float(lo), "hi": float(hi), "candidates": len(sel),
                         "detection_rate": float(np.mean([c["detected"] for c in sel]))})
    return rows


def summarize(per_frame: list[dict], cands: list[dict]) -> dict:
    errs = np.array([f["position_error"] for f in per_frame if f["position_error"] is not None])
    yaws = np.array([f["yaw_error_deg"] for f in per_frame if f["yaw_error_deg"] is not None])
    stat = lambda a, fn: float(fn(a)) if len(a) else None
    by_tags = {}
    for label, sel in (("1", lambda k: k == 1), ("2+", lambda k: k >= 2)):
        fs = [f for f in per_frame if f["position_error"] is not None and sel(len(f["detected"]))]
        by_tags[label] = {"frames": len(fs),
                          "position_error_m_median": stat(np.array([f["position_error"] for f in fs]), np.median),
                          "yaw_error_deg_median": stat(np.array([f["yaw_error_deg"] for f in fs]), np.median)}
    return {
        "by_tags_seen": by_tags,
        "frames": len(per_frame),
        "availability": float(np.mean([bool(f["detected"]) for f in per_frame])) if per_frame else 0.0,
        "candidates": len(cands),
        "detection_rate": float(np.mean([c["detected"] for c in cands])) if cands else None,
        "position_error_m": {"median": stat(errs, np.median), "p90": stat(errs, lambda a: np.percentile(a, 90)),
                             "max": stat(errs, np.max)},
        "yaw_error_deg": {"median": stat(yaws, np.median), "p90": stat(yaws, lambda a: np.percentile(a, 90)),
                          "max": stat(yaws, np.max)},
        "rate_vs_distance": _rate_table(cands, "distance", np.arange(0, 21, 1.0)),
        "rate_vs_angle": _rate_table(cands, "angle_deg", np.arange(0, 91, 10.0)),
    }
