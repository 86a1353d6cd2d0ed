"""Fold diagnostics: does a reconstruction contradict the capture order or its own matches?

A folded model (a row of look-alike plants mapped onto itself) registers every view with
a small reprojection error, so those numbers cannot catch it. What it cannot hide:

- neighbour frames (within the trusted window of the capture order) whose verified
  matches no longer triangulate in front of both cameras or reproject within a degree;
- jumps: consecutive frames placed much farther apart than the typical step (reported
  only: a robot turning at a row end or a paused camera jumps too);
- relative rotations chained along the capture sequence that drift away from the model's
  by more than a generous bound, which grows with the chain like a random walk of its links'
  own errors (and, for a closed walk, a loop that does not close);
- tracks observed from opposite sides (rays more than `opposite_deg` apart), which a
  surface point on a plant or the ground cannot be;
- the chain: segments mapped from neighbour pairs alone (no look-alike pair between
  distant frames reaches them, so they cannot fold) must agree with the model up to a
  similarity, and hold (nearly) all of its views: a view the chain never reached was
  placed by distant-frame matches alone, the kind a look-alike plant fakes;
- a split: several models, or a match graph in several pieces.

`diagnose` returns a JSON-ready dict; its "fold_suspected" is what `ghsplat sfm` acts on.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.sfm.matchgraph import MatchGraph, ModelPoses, pair_agreement


@dataclasses.dataclass
class FoldOptions:
    window: int = 1                  # neighbour frames: at most this many apart in capture order
    cyclic: bool = False             # the capture closes a loop
    agree_angle_deg: float = 1.0     # a match agrees when its rays meet within this angle
    # A neighbour pair contradicts the model below this fraction. Low on purpose: when the
    # step between frames nears the plant spacing, most of a true pair's F-inliers can be
    # look-alike matches (sideways motion keeps them on the epipolar lines), while a fold
    # leaves a seam of neighbour pairs that the model explains almost not at all.
    min_agreement: float = 0.1
    max_contradicted: int = 0        # fold when more neighbour pairs than this contradict the model
    jump_factor: float = 6.0         # a step this many times the median step is a jump
    min_segment: int = 5             # chain segments with fewer images in the model are not compared
    max_chain_deviation: float = 0.05  # fold when a segment's centres deviate more (of its extent)
    max_chain_rotation_deg: float = 5.0  # ... or its rotations by more than this
    # Fold when more of the views were placed by distant pairs alone. The weakest rule: a
    # correct varied row had 29% such views (the chain breaks where neighbours overlap
    # little), folded identical rows 44-100%; calibrated on these few cases only.
    max_unverified: float = 0.4
    # Fold when the chained relative rotations of consecutive frames drift farther than this from
    # the model's. Models within 1% of the truth drifted at most 13.7 deg (36 recorded runs, 36-59
    # views), a 60-view greenhouse segment 4.9% off 16.6; silent folds of greenhouse segments that
    # passed every other check drifted 63.8 and 92.8 (sfm_disambiguation/repeatability*.md).
    max_rotation_drift_deg: float = 30.0
    # ... or, for a longer chain, than drift_sigmas times the drift its own links explain: a chain
    # of n links with independent per-link errors of s degrees per axis drifts like s sqrt(n) (a
    # random walk), so a fixed bound refuses long correct captures (a 72-view orbit 0.06% off
    # drifted 32 degrees). s comes from the links themselves, robustly (the median of the links'
    # own rotation errors, which a few seam links of a fold barely move).
    drift_sigmas: float = 5.0
    opposite_deg: float = 150.0      # observing rays farther apart than this: seen from both sides
    max_opposite: float = 0.02       # fold when more of the tracks are seen from both sides


def _angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def _neighbour_agreement(graph: MatchGraph, poses: ModelPoses, options: FoldOptions) -> dict:
    """{neighbour pair: fraction of its matches the model's poses explain}, for the pairs
    within the window that can be measured."""
    scores = {pair: pair_agreement(graph, poses, pair, options.agree_angle_deg) for pair in sorted(graph.pairs)
              if graph.order_distance(*pair, cyclic=options.cyclic) <= options.window}
    return {pair: a for pair, a in scores.items() if a is not None}


def neighbour_contradictions(graph: MatchGraph, poses: ModelPoses, options: FoldOptions) -> dict:
    """Neighbour pairs whose matches the model's poses do not explain."""
    scores = _neighbour_agreement(graph, poses, options)
    checked = len(scores)
    contradicted = [(pair, a) for pair, a in scores.items() if a < options.min_agreement]
    return {
        "num_checked": checked,
        "num_contradicted": len(contradicted),
        "fraction_contradicted": round(len(contradicted) / checked, 4) if checked else 0.0,
        "contradicted": [[graph.names[i], graph.names[j], round(a, 3)] for (i, j), a in contradicted[:20]],
    }


def split_runs(views: list[int], joined) -> list[list[int]]:
    """`views` (sorted) split into runs of consecutive entries a, b for which joined(a, b)."""
    runs = [[views[0]]] if views else []
    for a, b in zip(views, views[1:]):
        if joined(a, b):
            runs[-1].append(b)
        else:
            runs.append([b])
    return runs


def seam_pieces(graph: MatchGraph, poses: ModelPoses, options: FoldOptions) -> list[list[int]]:
    """The registered views in capture order, split at the seams a fold leaves (consecutive
    views whose neighbour pair the model contradicts), largest piece first. Only measured
    contradictions split; in a closed walk the first and last pieces join across the ends
    unless that pair is contradicted too."""
    views = sorted(poses.world_to_cam)
    if not views:
        return []
    seams = {pair for pair, a in _neighbour_agreement(graph, poses, options).items() if a < options.min_agreement}
    pieces = split_runs(views, lambda a, b: (a, b) not in seams)
    ends = (views[0], views[-1])
    if (options.cyclic and len(pieces) > 1 and graph.order_distance(*ends, cyclic=True) <= options.window
            and ends not in seams):
        pieces[0] = pieces.pop() + pieces[0]
    return sorted(pieces, key=len, reverse=True)


def long_range_contradictions(graph: MatchGraph, poses: ModelPoses, options: FoldOptions) -> dict:
    """Verified pairs beyond the window the model does not explain (aliased matches it rejected,
    or, in a folded model, true matches it overruled): informative, not a flag on its own."""
    scores = [pair_agreement(graph, poses, p, options.agree_angle_deg) for p in graph.pairs
              if graph.order_distance(*p, cyclic=options.cyclic) > options.window]
    scores = [s for s in scores if s is not None]
    bad = sum(s < options.min_agreement for s in scores)
    return {"num_checked": len(scores), "num_contradicted": int(bad),
            "fraction_contradicted": round(bad / len(scores), 4) if scores else 0.0}


def _centres(poses: ModelPoses) -> dict[int, np.ndarray]:
    """Camera centre of every registered frame, by capture-order index."""
    return {k: -w2c[:3, :3].T @ w2c[:3, 3] for k, w2c in poses.world_to_cam.items()}


def spikes(poses: ModelPoses, options: FoldOptions) -> list[int]:
    """Registered frames placed far from both registered capture neighbours (more than
    jump_factor median steps per frame of gap) while those neighbours sit within that of each
    other: a walking camera cannot leave and come back, so such a pose is a mis-registration
    (a look-alike plant matched)."""
    posed = sorted(poses.world_to_cam)
    if len(posed) < 4:
        return []
    c = _centres(poses)
    median = float(np.median([np.linalg.norm(c[a] - c[b]) for a, b in zip(posed, posed[1:])]))
    far = lambda a, b: np.linalg.norm(c[a] - c[b]) > options.jump_factor * median * abs(b - a)  # noqa: E731
    return [k for a, k, b in zip(posed, posed[1:], posed[2:]) if median > 0 and far(a, k) and far(k, b)
            and not far(a, b)]


def order_jumps(graph: MatchGraph, poses: ModelPoses, options: FoldOptions) -> dict:
    """Consecutive registered frames placed more than jump_factor median steps apart."""
    posed = sorted(poses.world_to_cam)
    centres = _centres(poses)
    steps = [(a, b, float(np.linalg.norm(centres[a] - centres[b]))) for a, b in zip(posed, posed[1:])]
    if len(steps) < 3:
        return {"median_step": None, "num_jumps": 0, "jumps": []}
    median = float(np.median([s for _, _, s in steps]))
    jumps = [(a, b, s / median) for a, b, s in steps if median > 0 and s > options.jump_factor * median]
    return {"median_step": median, "num_jumps": len(jumps),
            "jumps": [[graph.names[a], graph.names[b], round(r, 2)] for a, b, r in jumps[:20]]}


def relative_rotation(graph: MatchGraph, poses: ModelPoses, pair: tuple[int, int]) -> np.ndarray | None:
    """R_j R_i^T measured from the pair's inlier matches (essential matrix, model intrinsics)."""
    import cv2

    i, j = pair
    m = graph.pairs.get(pair)
    if m is None or len(m) < 8 or i not in poses.normalise or j not in poses.normalise:
        return None
    xa = np.asarray(poses.normalise[i](graph.keypoints[i][m[:, 0]]), np.float64)
    xb = np.asarray(poses.normalise[j](graph.keypoints[j][m[:, 1]]), np.float64)
    threshold = 1.0 / max(poses.focal[i], 1.0)
    e, mask = cv2.findEssentialMat(xa, xb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=threshold)
    if e is None or e.shape != (3, 3):
        return None
    _, r, _, _ = cv2.recoverPose(e, xa, xb, np.eye(3), mask=mask)
    return r


def link_rotation_error(graph: MatchGraph, poses: ModelPoses, pair: tuple[int, int]) -> float | None:
    """Degrees between the pair's relative rotation in the model and the one its own matches
    give (None: the pair cannot be measured, or an image is not registered)."""
    i, j = pair
    if i not in poses.world_to_cam or j not in poses.world_to_cam:
        return None
    measured = relative_rotation(graph, poses, pair)
    if measured is None:
        return None
    model = poses.world_to_cam[j][:3, :3] @ poses.world_to_cam[i][:3, :3].T
    return _angle_deg(measured @ model.T)


MAXWELL_MEDIAN = 1.5382  # median angle of a small rotation with N(0, s^2) per axis, in units of s


def drift_bound(link_errors_deg, options: FoldOptions) -> float:
    """The chained drift allowed to a chain whose links have these rotation errors (degrees):
    max_rotation_drift_deg, or drift_sigmas x s x sqrt(links) for a long chain, s the per-axis
    link noise estimated from the median link error."""
    errors = np.asarray(link_errors_deg, float)
    if len(errors) == 0:
        return options.max_rotation_drift_deg
    sigma = float(np.median(errors)) / MAXWELL_MEDIAN
    return max(options.max_rotation_drift_deg, options.drift_sigmas * sigma * np.sqrt(len(errors)))


def chained_drift(runs) -> tuple[list[float], list[float]]:
    """(drift after each link, each link's own error), degrees, of chains of links given as runs
    of (measured relative rotation, the model's) pairs: the measured rotations chained from the
    start of their run against the model's chained the same way (R_last R_first^T)."""
    drift, errors = [], []
    for run in runs:
        chained, model = np.eye(3), np.eye(3)
        for measured, step in run:
            chained, model = measured @ chained, step @ model
            errors.append(_angle_deg(measured @ step.T))
            drift.append(_angle_deg(chained @ model.T))
    return drift, errors


def rotation_chain(graph: MatchGraph, poses: ModelPoses, options: FoldOptions) -> dict:
    """Relative rotations of consecutive frames, chained along the capture order, against the
    model's; each link's own error; the drift bound those link errors allow (drift_bound); and
    the closing error of the loop when the last frame matches the first."""
    n = len(graph.names)
    runs, start, chained = [], None, np.eye(3)
    for k in range(n - 1):
        r = relative_rotation(graph, poses, (k, k + 1))
        if r is None or k not in poses.world_to_cam or k + 1 not in poses.world_to_cam:
            start = None  # a gap: restart the chain
            continue
        if start is None:
            start, chained = k, np.eye(3)
            runs.append([])
        chained = r @ chained
        runs[-1].append((r, poses.world_to_cam[k + 1][:3, :3] @ poses.world_to_cam[k][:3, :3].T))
    drift, errors = chained_drift(runs)
    closure = None
    if start == 0 and (0, n - 1) in graph.pairs:
        r = relative_rotation(graph, poses, (0, n - 1))  # R_last R_first^T measured directly
        if r is not None:
            closure = _angle_deg(r @ chained.T)
    return {"num_links": len(errors), "max_drift_deg": round(max(drift), 3) if drift else None,
            "link_error_median_deg": round(float(np.median(errors)), 3) if errors else None,
            "link_error_max_deg": round(max(errors), 3) if errors else None,
            "drift_bound_deg": round(drift_bound(errors, options), 3),
            "loop_closure_deg": None if closure is None else round(closure, 3)}


def opposite_tracks(reconstruction, options: FoldOptions) -> dict:
    """Fraction of 3D points with two observing rays more than opposite_deg apart."""
    centres = {i: reconstruction.images[i].projection_center() for i in reconstruction.reg_image_ids()}
    cos_limit = np.cos(np.radians(options.opposite_deg))
    total = opposite = 0
    for point in reconstruction.points3D.values():
        ids = [e.image_id for e in point.track.elements]
        rays = np.array([centres[i] - point.xyz for i in ids if i in centres])
        if len(rays) < 2:
            continue
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        total += 1
        opposite += bool((rays @ rays.T).min() < cos_limit)
    return {"num_points": total, "num_opposite": opposite,
            "fraction_opposite": round(opposite / total, 4) if total else 0.0}


def chain_consistency(poses: ModelPoses, chain: list[ModelPoses], graph: MatchGraph,
                      options: FoldOptions, mapped_graph: MatchGraph | None = None,
                      reached: set[int] = frozenset()) -> dict:
    """Each chain segment (mapped from neighbour pairs only, so it cannot fold) against the
    model: camera-centre RMSE after a similarity alignment, as a fraction of the segment's
    extent in the model, and the largest rotation difference. `reached`: views that neighbour
    links placed besides the chain's (the order filter's own chain)."""
    from ghsplat_jax.sfm.evaluate import compare_poses

    segments = []
    for segment in chain:
        common = sorted(set(segment.world_to_cam) & set(poses.world_to_cam))
        if len(common) < options.min_segment:
            continue
        lift = lambda m: np.vstack([m, [0.0, 0.0, 0.0, 1.0]])  # noqa: E731
        est = np.stack([lift(segment.world_to_cam[k]) for k in common])
        ref = np.stack([lift(poses.world_to_cam[k]) for k in common])
        result = compare_poses(est, ref)
        rmse = result["centre_error_rmse"] / max(result["extent"], 1e-12)
        segments.append({"first": graph.names[common[0]], "last": graph.names[common[-1]],
                         "num_images": len(common), "centre_rmse_rel": round(rmse, 5),
                         "rotation_max_deg": round(result["rotation_error_max_deg"], 3)})
    bad = [s for s in segments if s["centre_rmse_rel"] > options.max_chain_deviation
           or s["rotation_max_deg"] > options.max_chain_rotation_deg]
    # Views the chain never reached were registered through pairs of distant frames only:
    # on a self-similar row exactly the ones a look-alike match can misplace.
    # A view outside the chain whose mapped pairs are all neighbour pairs (the order filter
    # keeps no unverifiable distant pair) was placed by neighbours after all.
    reached = set(reached).union(*(set(s.world_to_cam) for s in chain))
    mapped = (mapped_graph or graph).pairs
    distant = {k for p in mapped if graph.order_distance(*p, cyclic=options.cyclic) > options.window
               and p[0] in poses.world_to_cam and p[1] in poses.world_to_cam for k in p}
    unverified = sorted((set(poses.world_to_cam) - reached) & distant)
    return {"num_segments": len(segments), "num_inconsistent": len(bad), "segments": segments[:20],
            "num_unverified": len(unverified),
            "fraction_unverified": round(len(unverified) / max(len(poses.world_to_cam), 1), 4),
            "unverified": [graph.names[k] for k in unverified[:20]]}


def graph_components(graph: MatchGraph) -> list[int]:
    """Sizes of the connected pieces of the verified match graph, largest first."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(graph.names)
    if not graph.pairs:
        return [1] * n
    r, c = np.array(list(graph.pairs)).T
    _, labels = connected_components(coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n)), directed=False)
    return sorted(np.bincount(labels).tolist(), reverse=True)


def diagnose(graph: MatchGraph, mapped_graph: MatchGraph, poses: ModelPoses, reconstruction,
             options: FoldOptions, capture_order: bool, num_models: int,
             chain: list[ModelPoses] | None = None, reached: set[int] = frozenset()) -> dict:
    """All fold diagnostics. `graph`: every verified pair; `mapped_graph`: the pairs the mapper
    was given (the same unless a filter dropped some); `reached`: as chain_consistency."""
    report = {"capture_order": capture_order, "window": options.window, "cyclic": options.cyclic}
    reasons = []
    if capture_order:
        neighbours = neighbour_contradictions(graph, poses, options)
        jumps = order_jumps(graph, poses, options)
        chained = rotation_chain(graph, poses, options)
        report.update(neighbour_pairs=neighbours, order_jumps=jumps, rotation_chain=chained)
        if neighbours["num_contradicted"] > options.max_contradicted:
            reasons.append(f"{neighbours['num_contradicted']} of {neighbours['num_checked']} neighbour "
                           "pairs in the capture order contradict the final poses")
        if (chained["max_drift_deg"] or 0.0) > chained["drift_bound_deg"]:
            reasons.append(f"the relative rotations of consecutive frames, chained along the capture order, "
                           f"drift {chained['max_drift_deg']:.0f} degrees from the model's (more than "
                           f"{chained['drift_bound_deg']:.0f}, which {chained['num_links']} links of median error "
                           f"{chained['link_error_median_deg']:.2g} degrees allow)")
    if chain is not None:  # an empty chain (nothing mapped from neighbours alone) confirms no view
        consistency = chain_consistency(poses, chain, graph, options, mapped_graph, reached)
        report["chain_consistency"] = consistency
        if consistency["num_inconsistent"]:
            reasons.append(f"{consistency['num_inconsistent']} of {consistency['num_segments']} segments "
                           "mapped from neighbour frames alone disagree with the model")
        if consistency["fraction_unverified"] > options.max_unverified:
            reasons.append(f"{consistency['num_unverified']} of {len(poses.world_to_cam)} views are placed "
                           "only through matches with distant frames, which neighbour frames cannot confirm")
    report["long_range_pairs"] = long_range_contradictions(graph, poses, options)
    opposite = opposite_tracks(reconstruction, options)
    report["opposite_tracks"] = opposite
    if opposite["fraction_opposite"] > options.max_opposite:
        reasons.append(f"{100 * opposite['fraction_opposite']:.1f}% of the 3D points are seen from "
                       "opposite sides")
    report["match_graph_components"] = graph_components(mapped_graph)
    report["num_models"] = num_models
    report["fold_suspected"] = bool(reasons)
    report["reasons"] = reasons
    return report


FOLD_ADVICE = [
    "the views look alike (a row of near-identical plants): the model is probably folded onto "
    "itself; do not train on it",
    "keep the capture order in the file names (frame numbers) with --capture-order name, so "
    "the order filter can run (--disambiguate auto or order)",
    "capture more densely (video, or more photos along the aisles): neighbour frames need "
    "enough overlap that three of them see the same leaves",
    "try --disambiguate tracks or --mapper global",
    "capture with more distinctive content in view (row-end posts, tags, markers along the row)",
]
