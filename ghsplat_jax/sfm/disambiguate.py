"""Learning-free pair filters against self-similar rows: which verified pairs the mapper may use.

A row of near-identical plants gives many verified pairs between views of *different*
plants; the mapper then folds the row onto itself. Two filters, chosen by
`--disambiguate`:

- "order" (capture-order prior with loop verification): frames shot while walking are
  neighbours, so pairs within `window` frames of each other are trusted; a first map from
  those pairs alone (the chain) predicts the pose of every other pair, and a long-range
  pair is kept only when most of its matches agree with that prediction, and with those
  matches only. Needs the capture order (file names, sorted). The chain and the final map
  register views from fewer inliers than COLMAP's defaults (their pairs are trusted or
  verified), and the chain is cut wherever a link's rotation in the map disagrees with
  the one the link's own matches give.
- "tracks" (track context on the match graph, after Yan et al., CVPR 2017): a path network
  (maximum spanning tree plus each image's strongest pairs) gives a geodesic distance
  between images; a track whose images lie far apart on it is "confusing" (the same
  plant part seen at several places), and a pair whose matches are mostly confusing is
  dropped. Needs no capture order.

Both return the set of pairs to keep plus a report (the order filter also the agreeing
matches of each long-range pair it keeps); pipeline.py writes a filtered copy of the
database and maps from it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.sfm.folds import link_rotation_error, split_runs
from ghsplat_jax.sfm.matchgraph import MatchGraph, ModelPoses, agreeing_matches

METHODS = ("auto", "order", "tracks", "none")


@dataclasses.dataclass
class DisambiguateOptions:
    window: int = 1                 # order: pairs at most this many frames apart are trusted
    cyclic: bool = False            # order: the capture closes a loop (last frame next to first)
    verify_angle_deg: float = 1.0   # order: a match agrees when its rays meet within this angle
    min_agreement: float = 0.5      # order: keep a long-range pair when this fraction agrees
    path_neighbours: int = 3        # tracks: strongest pairs per image in the path network
    max_track_span: int = 4         # tracks: geodesic hops beyond which a track is confusing
    min_distinct: float = 0.5       # tracks: keep a pair when this fraction of matches is not confusing
    # order: the filter's chain and map register a view from this many absolute-pose inliers
    # and this inlier ratio (COLMAP: 30 and 0.25; pipeline.map_and_check maps again at those
    # when the fold check flags the result). On four hand-held loops of 36-52 views this took
    # the views registered from 15, 10, 15 and 12 to 34, 24, 17 and 14, all within 0.5% RMSE
    # (1% max); the relaxed chain without the link check had drifted to 6.8% on one of them.
    min_pose_inliers: int = 15
    min_pose_inlier_ratio: float = 0.1
    max_link_rotation_deg: float = 3.0  # order: cut the chain at links whose rotation disagrees more

    def validate(self) -> None:
        if self.window < 1:
            raise ValueError(f"disambiguation window must be >= 1 frame, got {self.window}")
        if not 0.0 < self.verify_angle_deg < 30.0:
            raise ValueError(f"verify angle must be in (0, 30) degrees, got {self.verify_angle_deg}")
        for name in ("min_agreement", "min_distinct"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.path_neighbours < 1 or self.max_track_span < 1:
            raise ValueError("path_neighbours and max_track_span must be >= 1")
        if self.min_pose_inliers < 6 or not 0.0 < self.min_pose_inlier_ratio <= 1.0:
            raise ValueError("min_pose_inliers must be >= 6 and min_pose_inlier_ratio in (0, 1]")
        if not self.max_link_rotation_deg > 0.0:
            raise ValueError(f"max_link_rotation_deg must be positive, got {self.max_link_rotation_deg}")


# ---------------------------------------------------------------------------- capture order


def sequential_pairs(graph: MatchGraph, options: DisambiguateOptions) -> set[tuple[int, int]]:
    """Verified pairs within the trusted window of the capture order."""
    return {p for p in graph.pairs if graph.order_distance(*p, cyclic=options.cyclic) <= options.window}


def distinct_segments(segments: list[ModelPoses]) -> list[ModelPoses]:
    """Chain segments, largest first, without those whose images a larger one already holds:
    the mapper may map a few of a segment's images again as a model of their own, and that
    smaller, weaker model adds nothing to check against (a 5-view copy turned one camera by
    10 degrees and flagged a correct model as folded)."""
    kept: list[ModelPoses] = []
    for segment in sorted(segments, key=lambda s: len(s.world_to_cam), reverse=True):
        if not any(set(segment.world_to_cam) <= set(k.world_to_cam) for k in kept):
            kept.append(segment)
    return kept


def cut_links(graph: MatchGraph, segments: list[ModelPoses], options: DisambiguateOptions,
              min_views: int = 3) -> list[ModelPoses]:
    """Chain segments split wherever consecutive views (in capture order) are not a trusted
    pair, or the pair's rotation in the segment is more than `max_link_rotation_deg` from the
    one its own matches give: a view registered from few inliers can sit a few degrees off,
    and every long-range pair verified against it would carry that error. Pieces of fewer
    than `min_views` views are dropped; the result is `distinct_segments`."""
    trusted = sequential_pairs(graph, options)
    pieces = []
    for segment in segments:
        def agrees(a, b, segment=segment):
            error = link_rotation_error(graph, segment, (a, b)) if (a, b) in trusted else None
            return error is not None and error <= options.max_link_rotation_deg

        runs = split_runs(sorted(segment.world_to_cam), agrees)
        pieces += [ModelPoses({k: segment.world_to_cam[k] for k in run}, segment.normalise, segment.focal)
                   for run in runs if len(run) >= min_views]
    return distinct_segments(pieces)


def chain_agreement(graph: MatchGraph, chain: list[ModelPoses], pair: tuple[int, int],
                    angle_deg: float) -> np.ndarray | None:
    """(M,) bool: which of the pair's matches agree with the first chain segment that holds
    both images (None: none does)."""
    for segment in chain:
        ok = agreeing_matches(graph, segment, pair, angle_deg)
        if ok is not None:
            return ok
    return None


def order_filter(graph: MatchGraph, chain: list[ModelPoses], options: DisambiguateOptions):
    """(pairs to keep, report, narrowed) for the capture-order prior, given the chain's segments.
    A long-range pair is kept when most of its matches agree with the chain, and then with
    those matches only (`narrowed`, {pair: (M, 2) matches}): a look-alike plant can add a few
    aliased matches to a pair whose others are right, and a few are enough to bend the map."""
    trusted = sequential_pairs(graph, options)
    agree = {p: chain_agreement(graph, chain, p, options.verify_angle_deg)
             for p in graph.pairs if p not in trusted}
    narrowed = {p: graph.pairs[p][ok] for p, ok in agree.items()
                if ok is not None and len(ok) and ok.mean() >= options.min_agreement}
    return trusted | set(narrowed), {
        "method": "order",
        "num_pairs": len(graph.pairs),
        "num_sequential_pairs": len(trusted),
        "num_long_range_pairs": len(agree),
        "num_long_range_kept": len(narrowed),
        "num_long_range_unverifiable": sum(ok is None for ok in agree.values()),  # no segment holds both
        "num_matches_dropped_from_kept": int(sum(len(graph.pairs[p]) - len(m) for p, m in narrowed.items())),
        "chain_segments": [len(s.world_to_cam) for s in chain],
    }, narrowed


# ---------------------------------------------------------------------------- track context


def tracks_from_pairs(graph: MatchGraph) -> tuple[np.ndarray, np.ndarray]:
    """(track id per keypoint, offsets): union of all inlier matches; keypoint k of image i
    is global node offsets[i] + k."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    offsets = np.concatenate([[0], np.cumsum([len(k) for k in graph.keypoints])])
    rows, cols = [], []
    for (i, j), m in graph.pairs.items():
        rows.append(offsets[i] + m[:, 0])
        cols.append(offsets[j] + m[:, 1])
    n = int(offsets[-1])
    if not rows:
        return np.arange(n), offsets
    r, c = np.concatenate(rows), np.concatenate(cols)
    adjacency = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(n, n))
    _, labels = connected_components(adjacency, directed=False)
    return labels, offsets


def path_network_distances(graph: MatchGraph, neighbours: int) -> np.ndarray:
    """(N, N) hop distances on the maximum spanning tree plus each image's strongest pairs."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree, shortest_path

    n = len(graph.names)
    weight = np.zeros((n, n))
    for (i, j), m in graph.pairs.items():
        weight[i, j] = weight[j, i] = len(m)
    edges = np.zeros((n, n), bool)
    # maximum spanning tree = minimum spanning tree of (max + 1 - weight) on existing edges
    mst = minimum_spanning_tree(np.where(weight > 0, weight.max() + 1 - weight, 0)).toarray() > 0
    edges |= mst | mst.T
    for i in range(n):
        strongest = np.argsort(-weight[i])[:neighbours]
        strongest = strongest[weight[i, strongest] > 0]
        edges[i, strongest] = edges[strongest, i] = True
    r, c = np.nonzero(edges)
    return shortest_path(coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n)), unweighted=True)


def track_filter(graph: MatchGraph, options: DisambiguateOptions):
    """(pairs to keep, report) from the track context of every pair's matches."""
    labels, offsets = tracks_from_pairs(graph)
    dist = path_network_distances(graph, options.path_neighbours)
    image_of = np.repeat(np.arange(len(graph.names)), np.diff(offsets))
    # track span: the largest path-network distance between two images that see it
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.diff(labels[order])) + 1
    span = np.zeros(labels.max() + 1 if len(labels) else 0)
    for group in np.split(order, bounds):
        images = np.unique(image_of[group])
        if len(images) > 1:
            span[labels[group[0]]] = dist[np.ix_(images, images)].max()
    confusing = span > options.max_track_span
    kept, scores = set(), {}
    for (i, j), m in graph.pairs.items():
        distinct = 1.0 - confusing[labels[offsets[i] + m[:, 0]]].mean()
        scores[(i, j)] = distinct
        if distinct >= options.min_distinct:
            kept.add((i, j))
    return kept, {
        "method": "tracks",
        "num_pairs": len(graph.pairs),
        "num_kept": len(kept),
        "num_tracks": int((span > 0).sum()),
        "confusing_track_fraction": float(confusing.sum() / max((span > 0).sum(), 1)),
        "path_network_diameter": float(np.max(dist[np.isfinite(dist)])) if len(dist) else 0.0,
    }
