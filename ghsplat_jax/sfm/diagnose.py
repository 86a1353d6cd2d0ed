"""Why SfM registered too few images: low texture, too few matches, separate groups, a short baseline.

A refusal that only counts registered images leaves a new user guessing. These checks read
what extraction, matching and mapping left behind (features per image, the verified pairs
and their two-view geometry, the model's points) and name the cause, the images concerned
and what to do. Each check is independent and cheap; `diagnose` is pure (tests feed it
made-up statistics), `read_evidence` is the only part that touches pycolmap.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

# ---------------------------------------------------------------------------- thresholds
# Tied to what COLMAP's incremental mapper needs (pycolmap defaults; tests/test_sfm_diagnose.py
# checks they still hold). The mapper halves START_INLIERS and START_ANGLE_DEG twice before
# giving up, so 25 matches and 4 degrees are the least any start pair gets away with.
MATCH_INLIERS = 15        # TwoViewGeometryOptions.min_num_inliers: a pair with fewer is no match
PLACE_INLIERS = 30        # mapper.abs_pose_min_num_inliers: matches a photo needs to be added to a model
START_INLIERS = 100       # mapper.init_min_num_inliers: matches of the pair a model starts from
START_ANGLE_DEG = 16.0    # mapper.init_min_tri_angle: that pair's triangulation angle
RELAXED = 4               # two halvings: START_INLIERS / 4 and START_ANGLE_DEG / 4 at the most relaxed
# A photo under 300 features rarely yields the START_INLIERS verified matches (a third of its
# features, and only the overlap matches). The stability study's low-texture row (blur 3 px,
# contrast x0.35, 480x360) gave a median of 90 features per photo against 800 unblurred.
MIN_FEATURES = 300
FEATURES_FAR_BELOW = 0.25  # a photo under a quarter of the median lacks what its neighbours have
# COLMAP drops points triangulated under 1.5 degrees; a model whose median point is under 2
# has depth barely constrained (the photos are nearly one viewpoint).
MODEL_MIN_ANGLE_DEG = 2.0
PANORAMIC_SHARE = 0.5     # most matched pairs fit a pure rotation (or one plane): rotating in place
SHOWN = 5                 # image names listed per cause
MAX_POSED_PAIRS = 500     # strongest pairs whose relative pose (triangulation angle) is estimated
ROTATION_CONFIGS = ("PANORAMIC", "PLANAR_OR_PANORAMIC")


@dataclasses.dataclass
class Evidence:
    """What a run left behind, by image name (pairs as (a, b) in capture order)."""
    names: list[str]                                   # capture order
    keypoints: dict[str, int]                          # SIFT features per image
    inliers: dict[tuple[str, str], int]                # verified inlier matches per matched pair
    configs: dict[tuple[str, str], str] = dataclasses.field(default_factory=dict)  # two-view config name
    angles_deg: dict[tuple[str, str], float] = dataclasses.field(default_factory=dict)  # strong pairs
    registered: set[str] = dataclasses.field(default_factory=set)
    model_angle_deg: float | None = None               # median triangulation angle of the model's points
    dropped: dict[str, str] = dataclasses.field(default_factory=dict)  # registered, then left out: why
    unreadable: list[str] = dataclasses.field(default_factory=list)  # images the database lacks


def _names(names: list[str]) -> str:
    return ", ".join(names[:SHOWN]) + (f" and {len(names) - SHOWN} more" if len(names) > SHOWN else "")


def _cause(cause: str, detail: str, images: list[str], advice: str) -> dict:
    return {"cause": cause, "detail": detail, "images": images[:SHOWN], "num_images": len(images),
            "advice": advice}


def best_partner(ev: Evidence) -> dict[str, int]:
    """Each image's most inlier matches with any other image (0: none)."""
    best = dict.fromkeys(ev.names, 0)
    for (a, b), n in ev.inliers.items():
        for x in (a, b):
            if x in best:
                best[x] = max(best[x], n)
    return best


def groups(ev: Evidence) -> list[list[str]]:
    """Connected parts of the match graph (pairs of at least MATCH_INLIERS), largest first, each
    in capture order (scipy's components, as folds.graph_components counts them)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    index = {n: k for k, n in enumerate(ev.names)}
    edges = [(index[a], index[b]) for (a, b), n in ev.inliers.items()
             if n >= MATCH_INLIERS and a in index and b in index]
    r, c = np.array(edges, dtype=int).reshape(-1, 2).T
    _, labels = connected_components(coo_matrix((np.ones(len(r)), (r, c)), shape=(len(index),) * 2), directed=False)
    parts: dict[int, list[str]] = {}
    for n, label in zip(ev.names, labels):
        parts.setdefault(int(label), []).append(n)
    return sorted(parts.values(), key=lambda g: (-len(g), index[g[0]]))


# ---------------------------------------------------------------------------- checks


def low_texture(ev: Evidence, concern: list[str], refused: bool) -> dict | None:
    """Few SIFT features: all photos (a refusal with a median under MIN_FEATURES), or the missing
    ones under MIN_FEATURES or FEATURES_FAR_BELOW of the median (blank, blurred or dark)."""
    median = float(np.median([ev.keypoints.get(n, 0) for n in ev.names])) if ev.names else 0.0
    weak = [n for n in concern if ev.keypoints.get(n, 0) < max(MIN_FEATURES, FEATURES_FAR_BELOW * median)]
    if refused and median < MIN_FEATURES:
        images = sorted(ev.names, key=lambda n: ev.keypoints.get(n, 0))
        detail = (f"the photos gave a median of {median:g} SIFT features each (under {MIN_FEATURES}, too few to "
                  f"match {START_INLIERS} between two photos)")
    elif weak:
        images = weak
        counts = _names([f"{n} ({ev.keypoints.get(n, 0)})" for n in weak])
        detail = (f"{len(weak)} photos gave few SIFT features ({counts}; median {median:g}, under {MIN_FEATURES} "
                  "or a quarter of the median is too few)")
    else:
        return None
    return _cause("low texture", detail, images,
                  "photograph sharp (no motion blur, in focus) with textured surfaces filling the view; "
                  "a lower --sift-peak-threshold finds more features in low-contrast photos")


def too_few_matches(ev: Evidence, concern: list[str], refused: bool) -> list[dict]:
    """No pair strong enough to start a model (a refusal); missing photos matched by none, or by
    fewer than PLACE_INLIERS matches. One entry at most."""
    best = best_partner(ev)
    out = []
    overlap = "more overlap: take photos 20-30% of the view apart, each overlapping the next by 70-80%"
    if refused and ev.inliers:
        (a, b), n = max(ev.inliers.items(), key=lambda kv: kv[1])
        if n < START_INLIERS:
            out.append(_cause(
                "too few matches",
                f"the best-matched pair of photos ({a}, {b}) shares only {n} verified matches; a model starts "
                f"from a pair with {START_INLIERS} ({START_INLIERS // RELAXED} at the most relaxed)",
                [a, b], overlap))
    elif refused:
        out.append(_cause("too few matches", "no two photos share a verified match", list(ev.names), overlap))
    alone = [n for n in concern if best.get(n, 0) < MATCH_INLIERS]
    weak = [n for n in concern if MATCH_INLIERS <= best.get(n, 0) < PLACE_INLIERS]
    if alone and len(alone) < len(ev.names):
        out.append(_cause("too few matches", f"{len(alone)} photos matched no other photo ({_names(alone)})",
                          alone, overlap))
    if weak:
        shown = [f"{n} ({best[n]})" for n in weak]
        out.append(_cause("too few matches",
                          f"{len(weak)} photos share fewer than {PLACE_INLIERS} verified matches with any other "
                          f"photo, the least a photo needs to be placed ({_names(shown)})", weak, overlap))
    if len(out) < 2:
        return out
    # one entry: its findings in turn, the photos of each
    images = list(dict.fromkeys(n for f in out for n in f["images"]))
    merged = _cause("too few matches", "; ".join(f["detail"] for f in out), images, overlap)
    merged["num_images"] = len(set(alone) | set(weak) | set(images))
    return [merged]


def separate_groups(ev: Evidence, concern: list[str], ordered: bool) -> dict | None:
    """The match graph splits (groups of two or more) and a missing photo lies outside the group
    the model grew from: only photos bridging the groups can join them."""
    parts = [g for g in groups(ev) if len(g) >= 2]
    if len(parts) < 2:
        return None
    main = max(parts, key=lambda g: (len(ev.registered.intersection(g)), len(g)))
    outside = [n for g in parts if g is not main for n in g]
    if not set(outside) & set(concern):
        return None
    sizes = sorted((len(g) for g in parts), reverse=True)
    detail = (f"the photos fall into {len(parts)} groups with no verified match between them "
              f"(sizes {', '.join(map(str, sizes))}); only one group can become the model")
    group_of = {n: k for k, g in enumerate(groups(ev)) for n in g}
    gaps = [(a, b) for a, b in zip(ev.names, ev.names[1:]) if group_of[a] != group_of[b]]
    if ordered and gaps:
        advice = "add photos between " + "; ".join(f"{a} and {b}" for a, b in gaps[:SHOWN])
    else:
        advice = "add photos that overlap both groups"
    return _cause("separate groups", detail, outside, advice)


def short_baseline(ev: Evidence, refused: bool) -> dict | None:
    """Photos nearly one viewpoint: the model's points under MODEL_MIN_ANGLE_DEG, or (refused) the
    strong pairs' widest angle under the most relaxed start angle, or most pairs a pure rotation."""
    parts = []
    images: list[str] = []
    if ev.model_angle_deg is not None and ev.model_angle_deg < MODEL_MIN_ANGLE_DEG:
        parts.append(f"the model's points are seen under a median angle of {ev.model_angle_deg:.1f} degrees "
                     f"between photos (under {MODEL_MIN_ANGLE_DEG:g}: depth is barely constrained)")
        images = sorted(ev.registered, key=ev.names.index)
    if refused and ev.angles_deg:
        widest: dict[str, float] = {}
        for (a, b), angle in ev.angles_deg.items():
            for x in (a, b):
                widest[x] = max(widest.get(x, 0.0), angle)
        floor = START_ANGLE_DEG / RELAXED
        if np.median(list(widest.values())) < floor:
            narrow = [n for n in ev.names if n in widest and widest[n] < floor]
            parts.append(f"{len(narrow)} of {len(widest)} well-matched photos see no other photo from more than "
                         f"{floor:g} degrees apart (a model starts from {START_ANGLE_DEG:g}, {floor:g} at the most "
                         "relaxed)")
            images = images or narrow
    verified = [c for p, c in ev.configs.items() if ev.inliers.get(p, 0) >= MATCH_INLIERS]
    rotation = sum(c in ROTATION_CONFIGS for c in verified)
    if refused and verified and rotation >= PANORAMIC_SHARE * len(verified):
        parts.append(f"{rotation} of {len(verified)} matched pairs fit a pure rotation (or one flat plane)")
    if not parts:
        return None
    return _cause("short baseline", "; ".join(parts), images,
                  "move the camera between photos (a step sideways, or along the row) instead of rotating "
                  "in place; photos taken from one spot cannot be triangulated")


def left_out(ev: Evidence, concern: list[str]) -> dict | None:
    """Photos the mapper placed and a later check (spikes, cross-check) took out again."""
    dropped = [n for n in concern if n in ev.dropped]
    if not dropped:
        return None
    why = sorted({ev.dropped[n] for n in dropped})
    return _cause("left out by a check", f"{len(dropped)} photos were placed, then left out: {'; '.join(why)}",
                  dropped, "see the advice below on the check that left them out")


def unreadable(ev: Evidence) -> dict | None:
    if not ev.unreadable:
        return None
    return _cause("unreadable", f"pycolmap could not read {len(ev.unreadable)} photos ({_names(ev.unreadable)})",
                  list(ev.unreadable), "check that they open in an image viewer; save them again as JPEG or PNG")


def diagnose(ev: Evidence, refused: bool, ordered: bool = True) -> list[dict]:
    """Likely causes, most basic first: [{cause, detail, images (a few names), num_images, advice}].
    `refused`: the run registered too few images (global causes are looked for too); otherwise
    only the unregistered images are explained. `ordered`: names are the capture order."""
    concern = [n for n in ev.names if n not in ev.registered]
    found = [unreadable(ev), left_out(ev, concern), low_texture(ev, concern, refused),
             *too_few_matches(ev, concern, refused),
             separate_groups(ev, concern, ordered), short_baseline(ev, refused)]
    return [f for f in found if f is not None]


def lines(diagnosis: list[dict]) -> list[str]:
    """One line per cause: what, why, and what to do."""
    return [f"{d['cause']}: {d['detail']}. What to do: {d['advice']}." for d in diagnosis]


# ---------------------------------------------------------------------------- reading a run


def median_triangulation_angle(reconstruction, max_points: int = 2000) -> float | None:
    """Median over the model's points (an even sample of at most `max_points`) of the widest
    angle between the rays of two photos that see the point, in degrees (None: no points)."""
    centres = {i: np.asarray(reconstruction.images[i].projection_center(), float)
               for i in reconstruction.reg_image_ids()}
    points = list(reconstruction.points3D.values())
    if not points:
        return None
    step = max(1, len(points) // max_points)
    angles = []
    for p in points[::step]:
        ids = [e.image_id for e in p.track.elements if e.image_id in centres]
        if len(ids) < 2:
            continue
        rays = np.stack([centres[i] for i in ids]) - np.asarray(p.xyz, float)
        rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
        cos = np.clip(rays @ rays.T, -1.0, 1.0)
        angles.append(np.degrees(np.arccos(cos.min())))
    return float(np.median(angles)) if angles else None


def verified_pair_count(db) -> int:
    """Pairs of an open database that verified as a match: at least MATCH_INLIERS inlier matches
    and a defined geometry (COLMAP keeps a two-view entry, with 0 inliers, for every pair tried)."""
    import pycolmap

    _, geometries = db.read_two_view_geometries()
    return sum(1 for g in geometries if len(np.asarray(g.inlier_matches).reshape(-1, 2)) >= MATCH_INLIERS
               and pycolmap.TwoViewGeometryConfiguration(int(g.config)).name not in ("UNDEFINED", "DEGENERATE"))


def read_evidence(database: Path, names: list[str], reconstruction=None,
                  dropped: dict[str, str] | None = None) -> Evidence:
    """Evidence from a run's database (all verified pairs) and its model (None: no model)."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        images = {im.image_id: im for im in db.read_all_images() if im.name in set(names)}
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        keypoints = {im.name: int(db.num_keypoints_for_image(i)) for i, im in images.items()}
        order = {n: k for k, n in enumerate(names)}
        inliers, configs, strong = {}, {}, []
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries):
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            if id1 not in images or id2 not in images:
                continue
            a, b = images[id1].name, images[id2].name
            pair = (a, b) if order[a] < order[b] else (b, a)
            matches = np.asarray(geometry.inlier_matches).reshape(-1, 2)
            config = pycolmap.TwoViewGeometryConfiguration(int(geometry.config)).name
            inliers[pair], configs[pair] = len(matches), config
            if len(matches) >= START_INLIERS // RELAXED and config not in ("UNDEFINED", "DEGENERATE"):
                strong.append((len(matches), id1, id2, pair, geometry, matches))
        strong = sorted(strong, key=lambda s: -s[0])[:MAX_POSED_PAIRS]
        points = {}
        angles = {}
        for _, id1, id2, pair, geometry, matches in strong:
            for i in (id1, id2):
                if i not in points:
                    points[i] = np.asarray(db.read_keypoints(i))[:, :2].astype(float)
            if pycolmap.estimate_two_view_geometry_pose(
                    cameras[images[id1].camera_id], points[id1][matches[:, 0]],
                    cameras[images[id2].camera_id], points[id2][matches[:, 1]], geometry) \
                    and geometry.tri_angle >= 0:
                angles[pair] = float(np.degrees(geometry.tri_angle))
    finally:
        db.close()
    registered = set() if reconstruction is None else {
        reconstruction.images[i].name for i in reconstruction.reg_image_ids()}
    angle = None if reconstruction is None else median_triangulation_angle(reconstruction)
    return Evidence([n for n in names if n in keypoints], keypoints, inliers, configs, angles, registered, angle,
                    dict(dropped or {}), [n for n in names if n not in keypoints])


def diagnose_run(database: Path, names: list[str], reconstruction, refused: bool, ordered: bool = True,
                 dropped: dict[str, str] | None = None) -> list[dict]:
    """`diagnose` on what a run left behind. Evidence that cannot be read gives one "diagnosis
    unavailable" entry naming the error, rather than failing a run that has its model."""
    try:
        ev = read_evidence(database, names, reconstruction, dropped)
    except Exception as exc:  # noqa: BLE001  (a diagnosis must never break the run it explains)
        return [_cause("diagnosis unavailable", f"{type(exc).__name__}: {exc}", [], "see the counts above")]
    return diagnose(ev, refused, ordered)
