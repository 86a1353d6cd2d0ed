"""Photos exposed unlike the rest of their capture (auto exposure, a flash, a passing cloud).

Training does not notice such a photo: the view-dependent colour learns its brightness (on the
fetched aloe, whose first photos are brighter than the rest, the renders matched each photo's
brightness to 1-5%), and the model then shows that exposure to new views from that side, or, for
a test photo, scores the model against a brightness no training view had.

Brightness alone cannot tell: views of one greenhouse row differ by up to 1.6x in mean luminance
because they see different things. So the photos are compared where they see the same thing, at
the SfM points they observed (their COLMAP tracks): each observation's linear luminance is
modelled as the photo's exposure times the point's own brightness, and the exposures are fitted
robustly (alternating means over points and medians over photos, in logs), as panorama gain
compensation does. Datasets without tracks (transforms.json, LLFF) are not checked.

Measured: photos of one exposure fit within 0.98-1.01 of their median (Table 1's row2_x1 segment,
57 photos; the demo row, 32); the aloe's first three photos fit at 3.00, 3.12 and 1.41, its others
at 0.88-1.04. MAX_RATIO = 1.3 leaves a wide margin both ways.
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from ghsplat_jax.data.tracks import read_model, view_tracks

MAX_RATIO = 1.3       # warn about a photo exposed more than this apart from the capture's median
MIN_POINTS = 20       # shared points a photo needs for its exposure to be told
_FOUND: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # dataset -> {max_ratio: outliers}
_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
_DARK, _CLIPPED = 2e-3, 0.98  # observations too dark to scale, or clipped in a channel, are left out


def linear_luminance(rgb: np.ndarray) -> np.ndarray:
    """Linear-light luminance of sRGB values in [0, 1] (..., 3): exposure scales linear light."""
    srgb = np.clip(np.asarray(rgb, np.float32), 0.0, 1.0)
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4) @ _LUMA


def fit_exposures(view_of: np.ndarray, point_of: np.ndarray, log_lum: np.ndarray, num_views: int,
                  iterations: int = 30) -> np.ndarray:
    """Log exposure of each view (median 0) from observations log_lum = e[view] + a[point] + noise:
    a by the mean over a point's observations, e by the median over a view's (robust to the points
    a view sees occluded or specular). NaN for a view with fewer than MIN_POINTS observations."""
    _, point_of = np.unique(point_of, return_inverse=True)
    counts = np.bincount(point_of)
    per_view = np.bincount(view_of, minlength=num_views)
    told = per_view >= MIN_POINTS
    order = np.argsort(view_of, kind="stable")  # each view's observations, one slice each
    ends = np.cumsum(per_view)
    e = np.zeros(num_views)
    for _ in range(iterations):
        a = np.bincount(point_of, log_lum - e[view_of]) / counts
        rest = (log_lum - a[point_of])[order]
        e = np.array([np.median(rest[end - n:end]) if ok else 0.0 for end, n, ok in zip(ends, per_view, told)])
        e -= np.median(e[told]) if told.any() else 0.0
    return np.where(told, e, np.nan)


def observations(dataset, views) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(view index, point id, log linear luminance) of the SfM points the views observed, sampled
    in each photo at the keypoint; only points two or more of the views saw. None without tracks."""
    recon = read_model(dataset)
    tracks = None if recon is None else view_tracks(recon, views)
    if tracks is None:
        return None
    rows = []
    for t in tracks:
        h, w = t.view.image.shape[:2]
        col = np.clip(np.floor(t.xy[:, 0]).astype(int), 0, w - 1)
        row = np.clip(np.floor(t.xy[:, 1]).astype(int), 0, h - 1)
        rgb = t.view.image[row, col, :3]
        lum = linear_luminance(rgb)
        keep = (lum > _DARK) & np.all(rgb < _CLIPPED, axis=1)
        rows.append((np.full(int(keep.sum()), t.index), t.point_ids[keep], np.log(lum[keep])))
    if not rows:
        return None
    view_of, point_of, log_lum = (np.concatenate(c) for c in zip(*rows))
    shared = np.isin(point_of, np.flatnonzero(np.bincount(point_of) >= 2))
    return view_of[shared], point_of[shared], log_lum[shared]


def exposure_outliers(dataset, max_ratio: float = MAX_RATIO) -> list[tuple[str, str, float]] | None:
    """(split, name, exposure ratio to the capture's median) of the photos (training and test,
    every one: a photo left out would pass unseen) exposed more than `max_ratio` apart, the
    largest departure first; None where it cannot be told (no tracks: see the module docstring).
    Found once per dataset object: a training run asks twice (to warn, and whether to compensate)."""
    found = _FOUND.setdefault(dataset, {})
    if max_ratio not in found:
        found[max_ratio] = _find_outliers(dataset, max_ratio)
    return found[max_ratio]


def _find_outliers(dataset, max_ratio: float) -> list[tuple[str, str, float]] | None:
    views = [("train", v) for v in dataset.train] + [("test", v) for v in dataset.test]
    obs = observations(dataset, [v for _, v in views])
    if obs is None:
        return None
    ratios = np.exp(fit_exposures(*obs, num_views=len(views)))
    odd = [(split, v.name, float(r)) for (split, v), r in zip(views, ratios)
           if np.isfinite(r) and abs(math.log(r)) > math.log(max_ratio)]
    return sorted(odd, key=lambda item: -abs(math.log(item[2])))


def exposure_warning(dataset, where: str, compensating: bool = False) -> str | None:
    """The warning for photos exposed unlike the rest (see the module docstring), or None.
    `compensating`: training matches each training photo's exposure (train/exposure.py)."""
    odd = exposure_outliers(dataset)
    if not odd:
        return None
    listed = ", ".join(f"{name} ({split}) {ratio:.2f}x" for split, name, ratio in odd)
    found = (f"{where}: {len(odd)} photo(s) exposed unlike the rest of the capture, where they see the same SfM "
             f"points: {listed} the median photo's brightness. ")
    if compensating:
        return found + ("Exposure compensation is on, so training matches each training photo's exposure and the "
                        "model keeps the median photo's; a test photo exposed unlike it is still scored against "
                        "that (`psnr_cc` in metrics.json takes its exposure out)")
    return found + ("Training learns a training photo's exposure as view-dependent colour and shows it to new views "
                    "from its side; a test photo's is scored against a brightness no training view had. Lock the "
                    "camera's exposure when capturing, leave such photos out (remove them from the images and run "
                    "`ghsplat sfm` again), or match the training photos' exposure while training (`ghsplat train "
                    "--exposure-compensation`)")


def flagged_training_photos(dataset) -> list[str]:
    """The training photos the check finds exposed unlike the rest (none where it cannot tell)."""
    return [name for split, name, _ in exposure_outliers(dataset) or [] if split == "train"]
