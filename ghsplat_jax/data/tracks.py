"""Whether a dataset's cameras agree with its SfM points: the reprojection error of the points
each training view observed (its COLMAP track entries), as an angle.

Bundle adjustment leaves every registered view agreeing with the points it observed to within
its residual, the points' stored ERROR: 0.06-0.07 degrees on the Table 1 segments (0.37 px at
384x288), 0.03 on lund_door. Poses changed after the SfM (edited, converted, taken from another
source, or perturbed as the stability study does) no longer agree: moving every camera of the
study's 96x72 row by 0.5%, 1% and 2% of the scene's extent gave median errors of 0.17, 0.34 and
0.67 degrees, and training on such poses cost up to 1.1 dB of test PSNR. A warning fires above
both POSE_DISAGREEMENT_DEG and STORED_FACTOR x the SfM's own residual, so a model whose SfM
residual is large anyway (low-resolution or blurred photos) is not flagged for it.

The check cannot see what the SfM itself got wrong while staying self-consistent (a folded or
drifting model): `ghsplat sfm`'s fold and cross checks are for that.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ghsplat_jax.core.camera import project_points
from ghsplat_jax.data.splits import subsample

log = logging.getLogger("ghsplat.data")

POSE_DISAGREEMENT_DEG = 0.12  # warn above this median reprojection angle (and STORED_FACTOR x the SfM's)
STORED_FACTOR = 3.0
MAX_VIEWS = 100               # views checked (evenly spaced), points per view: a cost bound on big models
MAX_POINTS = 500
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")  # tracks of distorted models are in distorted pixels


@dataclasses.dataclass(frozen=True)
class TrackAgreement:
    """Reprojection of the SfM points into the training views (medians over views of each
    view's median over its points). `worst`: the views of largest angle, largest first."""

    views: int
    median_deg: float
    median_px: float       # at the loaded resolution
    stored_deg: float      # the SfM's own residual (points3D ERROR), the same way
    worst: tuple[tuple[str, float], ...]

    @property
    def disagrees(self) -> bool:
        return self.median_deg > max(POSE_DISAGREEMENT_DEG, STORED_FACTOR * self.stored_deg)


def read_model(dataset):
    """The pycolmap Reconstruction a COLMAP dataset was read from, or None where there is none
    (another format, pycolmap missing, a model it cannot read): the checks on it are optional."""
    source = getattr(dataset, "source", None)
    if getattr(dataset, "format", None) != "colmap" or source is None:
        return None
    try:
        import pycolmap

        return pycolmap.Reconstruction(str(source.parent))
    except Exception as exc:  # noqa: BLE001 (an optional check: no pycolmap, or a model it cannot read)
        log.debug("%s: no track check (%s)", source.parent, exc)
        return None


@dataclasses.dataclass(frozen=True)
class ViewTrack:
    """What one view observed in the SfM model: at most MAX_POINTS of its track entries."""

    index: int              # the view's place in the list given to view_tracks
    view: object            # the data.dataset.View
    xy: np.ndarray          # (N,2) keypoints in the view's loaded pixels
    point_ids: np.ndarray   # (N,) the points3D they observe
    scale: float            # loaded pixels per model pixel


def view_tracks(recon, views) -> list[ViewTrack] | None:
    """The track entries of each of `views` the model holds (views it lacks, or with none, left
    out); None where a camera is distorted (its tracks are in distorted pixels, the views not)."""
    by_name = {im.name: im for im in recon.images.values()}
    out = []
    for i, view in enumerate(views):
        image = by_name.get(view.name)
        if image is None:
            continue
        camera = recon.cameras[image.camera_id]
        if camera.model.name not in PINHOLE_MODELS:
            return None
        observed = subsample([p for p in image.points2D if p.has_point3D()], MAX_POINTS)
        if observed:
            scale = view.camera.width / camera.width
            out.append(ViewTrack(i, view, np.array([p.xy for p in observed]) * scale,
                                 np.array([p.point3D_id for p in observed]), scale))
    return out


def track_agreement(dataset) -> TrackAgreement | None:
    """The training views' agreement with the dataset's SfM points; None where it cannot be
    told (not a COLMAP dataset, pycolmap missing, a distorted camera model, no tracks)."""
    recon = read_model(dataset)
    tracks = None if recon is None else view_tracks(recon, subsample(list(dataset.train), MAX_VIEWS))
    if tracks is None:
        return None
    rows = []
    for t in tracks:
        view = t.view
        points = [recon.points3D[int(i)] for i in t.point_ids]
        proj, z = project_points(np.array([p.xyz for p in points]), view.camera.K, view.camera.world_to_cam)
        focal = float(np.asarray(view.camera.K)[0, 0])
        px = np.where(z > 0, np.linalg.norm(proj - t.xy, axis=1), np.inf)
        stored = np.array([p.error for p in points]) * t.scale
        rows.append((view.name, float(np.median(px)), float(np.median(stored)), focal))
    if not rows:
        return None
    deg = np.degrees(np.arctan(np.array([r[1] for r in rows]) / np.array([r[3] for r in rows])))
    stored = np.degrees(np.arctan(np.array([r[2] for r in rows]) / np.array([r[3] for r in rows])))
    order = np.argsort(-deg)[:3]
    return TrackAgreement(len(rows), float(np.median(deg)), float(np.median([r[1] for r in rows])),
                          float(np.median(stored)), tuple((rows[i][0], float(deg[i])) for i in order))


def pose_disagreement(dataset, where: str) -> str | None:
    """The warning for cameras that disagree with their SfM points (see the module docstring), or None."""
    a = track_agreement(dataset)
    if a is None or not a.disagrees:
        return None
    worst = ", ".join(f"{name} ({deg:.2f})" for name, deg in a.worst)
    return (f"{where}: the cameras disagree with the dataset's SfM points: the points each training view observed "
            f"reproject {a.median_deg:.2f} degrees ({a.median_px:.2f} px) from where the photos show them (median "
            f"over {a.views} views; worst {worst}), against {a.stored_deg:.2f} degrees when the SfM left them. The "
            "poses were changed after the SfM, or the points come from another model; training on them blurs the "
            "model (in the stability study, cameras moved by 2% of the scene's extent cost 1.1 dB of test PSNR). "
            "Re-run `ghsplat sfm`, or train with --pose-refine")
