"""Pair filters and fold diagnostics on synthetic match graphs (pure NumPy, no pycolmap).

A camera walks along a row of points; matches are exact projections. A model with the
true poses explains every neighbour pair; a folded one (the second half of the walk
mapped back onto the first, as a row of identical plants invites) does not.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ghsplat_jax.sfm import disambiguate as dis
from ghsplat_jax.sfm import folds
from ghsplat_jax.sfm.matchgraph import (
    MatchGraph,
    ModelPoses,
    pair_agreement,
    ray_agreement,
)

F, CX, CY = 300.0, 160.0, 120.0


def _look_y(x: float) -> np.ndarray:
    """world_to_cam (3,4) of a camera at (x, -2, 1) looking along +y (OpenCV axes)."""
    r = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # rows: cam x = world x, cam y = -z, cam z = y
    return np.column_stack([r, -r @ np.array([x, -2.0, 1.0])])


def _project(w2c, points):
    cam = points @ w2c[:, :3].T + w2c[:, 3]
    xy = cam[:, :2] / cam[:, 2:3] * F + [CX, CY]
    inside = (cam[:, 2] > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < 320) & (xy[:, 1] >= 0) & (xy[:, 1] < 240)
    return xy, inside


def _walk(n=12, step=0.4, seed=0):
    """(graph, true poses): n cameras along x, points on a wall at y = 0."""
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(-2, n * step + 2, 3000), rng.uniform(-0.2, 0.2, 3000),
                              rng.uniform(0, 2, 3000)])
    poses = [_look_y(k * step) for k in range(n)]
    projections = [_project(p, points) for p in poses]
    keypoints, index = [], []
    for xy, inside in projections:
        ids = np.flatnonzero(inside)
        keypoints.append(xy[ids])
        index.append({p: k for k, p in enumerate(ids)})
    pairs = {}
    for i in range(n):
        for j in range(i + 1, n):
            common = sorted(set(index[i]) & set(index[j]))
            if len(common) >= 15:
                pairs[(i, j)] = np.array([[index[i][p], index[j][p]] for p in common])
    graph = MatchGraph([f"{k:03d}.png" for k in range(n)], list(range(1, n + 1)), [1] * n, keypoints, pairs)
    return graph, poses


def _model(poses) -> ModelPoses:
    normalise = lambda xy: (np.asarray(xy) - [CX, CY]) / F  # noqa: E731
    return ModelPoses({k: p for k, p in enumerate(poses)}, {k: normalise for k in range(len(poses))},
                      {k: F for k in range(len(poses))})


def test_ray_agreement_needs_points_in_front():
    w2c_a, w2c_b = _look_y(0.0), _look_y(0.5)
    points = np.array([[0.2, 0.0, 1.0], [0.3, 0.5, 1.5]])
    xa = (points @ w2c_a[:, :3].T + w2c_a[:, 3])
    xb = (points @ w2c_b[:, :3].T + w2c_b[:, 3])
    xa, xb = xa[:, :2] / xa[:, 2:], xb[:, :2] / xb[:, 2:]
    assert ray_agreement(xa, xb, w2c_a, w2c_b, np.radians(0.5)).all()
    # the same matches with the second camera placed behind-to-front (baseline reversed) do not
    assert not ray_agreement(xa, xb, w2c_a, _look_y(-0.5), np.radians(0.5)).any()


def test_clean_walk_is_not_flagged_and_a_folded_one_is():
    graph, poses = _walk()
    options = folds.FoldOptions(window=2)
    clean = folds.neighbour_contradictions(graph, _model(poses), options)
    assert clean["num_checked"] > 10 and clean["num_contradicted"] == 0
    # fold: cameras 6.. placed back over the first half (positions mirrored about x = 2.2)
    folded = [p if k < 6 else _look_y(2 * 2.2 - k * 0.4) for k, p in enumerate(poses)]
    bad = folds.neighbour_contradictions(graph, _model(folded), options)
    assert bad["num_contradicted"] >= 1 and bad["num_contradicted"] > options.max_contradicted
    assert ["005.png", "006.png"] == bad["contradicted"][0][:2]


def test_chain_segments_must_agree_with_the_model_and_reach_its_views():
    graph, poses = _walk(n=12)
    options = folds.FoldOptions(min_segment=4)
    segment = _model(poses[:8])  # the chain reached the first 8 views
    clean = folds.chain_consistency(_model(poses[:8]), [segment], graph, options)
    assert clean["num_segments"] == 1 and clean["num_inconsistent"] == 0 and clean["num_unverified"] == 0
    folded = [p if k < 4 else _look_y(2 * 1.4 - k * 0.4) for k, p in enumerate(poses)]
    bad = folds.chain_consistency(_model(folded), [segment], graph, options)
    assert bad["num_inconsistent"] == 1 and bad["segments"][0]["centre_rmse_rel"] > options.max_chain_deviation
    assert bad["num_unverified"] == 4 and bad["unverified"] == ["008.png", "009.png", "010.png", "011.png"]
    report = folds.diagnose(graph, graph, _model(folded), _Reconstruction(), options, capture_order=True,
                            num_models=1, chain=[segment])
    assert report["fold_suspected"] and len(report["reasons"]) >= 2


class _Reconstruction:
    """Just enough of a pycolmap model for opposite_tracks: no points."""
    points3D: dict = {}

    def reg_image_ids(self):
        return []


def test_order_jumps_and_components():
    graph, poses = _walk(n=8)
    jumped = [p if k < 4 else _look_y(k * 0.4 + 5.0) for k, p in enumerate(poses)]
    report = folds.order_jumps(graph, _model(jumped), folds.FoldOptions(jump_factor=6.0))
    assert report["num_jumps"] == 1 and report["jumps"][0][:2] == ["003.png", "004.png"]
    assert folds.graph_components(graph) == [8]
    split = MatchGraph(graph.names, graph.image_ids, graph.camera_ids, graph.keypoints,
                       {p: m for p, m in graph.pairs.items() if (p[0] < 4) == (p[1] < 4)})
    assert folds.graph_components(split) == [4, 4]


def test_rotation_chain_of_a_clean_walk_has_no_drift():
    pytest.importorskip("cv2")
    graph, poses = _walk(n=6)
    chain = folds.rotation_chain(graph, _model(poses), folds.FoldOptions())
    assert chain["num_links"] == 5 and chain["max_drift_deg"] < 0.5


def test_a_model_whose_rotations_drift_from_the_chained_ones_is_flagged():
    pytest.importorskip("cv2")
    graph, poses = _walk(n=6)
    options = folds.FoldOptions()
    clean = folds.diagnose(graph, graph, _model(poses), _Reconstruction(), options, capture_order=True,
                           num_models=1)
    assert not clean["fold_suspected"]

    def turned(w2c, deg):  # the camera yawed about its own y axis, centre kept
        a = np.radians(deg)
        r = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) @ w2c[:, :3]
        centre = -w2c[:, :3].T @ w2c[:, 3]
        return np.column_stack([r, -r @ centre])

    # the last frames placed turned by more than the bound: the chain of measured relative
    # rotations (straight ahead) cannot reach them
    bent = [p if k < 4 else turned(p, 40.0) for k, p in enumerate(poses)]
    report = folds.diagnose(graph, graph, _model(bent), _Reconstruction(), options, capture_order=True,
                            num_models=1)
    assert report["rotation_chain"]["max_drift_deg"] == pytest.approx(40.0, abs=0.5)
    assert report["fold_suspected"] and any("drift 40 degrees" in r for r in report["reasons"])


def test_order_filter_keeps_verified_long_pairs_and_drops_aliased_ones():
    graph, poses = _walk()
    options = dis.DisambiguateOptions(window=1)
    # alias: pair (0, 5) matched to the wrong keypoints of image 5 (a look-alike elsewhere)
    rng = np.random.default_rng(1)
    aliased = dict(graph.pairs)
    aliased[(0, 5)] = np.column_stack([np.arange(40), rng.permutation(len(graph.keypoints[5]))[:40]])
    graph = MatchGraph(graph.names, graph.image_ids, graph.camera_ids, graph.keypoints, aliased)
    keep, info, narrowed = dis.order_filter(graph, [_model(poses)], options)
    assert dis.sequential_pairs(graph, options) <= keep
    assert (0, 2) in keep and (0, 5) not in keep
    assert info["num_long_range_kept"] == info["num_long_range_pairs"] - 1
    assert pair_agreement(graph, _model(poses), (0, 5), 1.0) < 0.5
    assert set(narrowed) == keep - dis.sequential_pairs(graph, options)  # trusted pairs stay whole
    assert info["num_matches_dropped_from_kept"] == 0


def test_order_filter_keeps_only_the_agreeing_matches_of_a_kept_pair():
    graph, poses = _walk()
    # pair (0, 3): its true matches plus a few aliased ones (look-alike keypoints of image 3)
    true = graph.pairs[(0, 3)]
    rng = np.random.default_rng(2)
    bad = np.column_stack([rng.choice(len(graph.keypoints[0]), 8), rng.choice(len(graph.keypoints[3]), 8)])
    bad = bad[~(bad[:, None] == true[None]).all(-1).any(1)]
    graph = dataclasses.replace(graph, pairs={**graph.pairs, (0, 3): np.concatenate([true, bad])})
    keep, info, narrowed = dis.order_filter(graph, [_model(poses)], dis.DisambiguateOptions(window=1))
    assert (0, 3) in keep
    np.testing.assert_array_equal(narrowed[(0, 3)], true)
    assert info["num_matches_dropped_from_kept"] == len(bad)


def test_track_filter_drops_pairs_made_of_confusing_tracks():
    graph, _ = _walk(n=14, step=0.5)
    # images 0 and 13 are far apart; give them matches that merge tracks across the walk
    far = {**graph.pairs, (0, 13): np.column_stack([np.arange(40), np.arange(40)])}
    graph = MatchGraph(graph.names, graph.image_ids, graph.camera_ids, graph.keypoints, far)
    keep, info = dis.track_filter(graph, dis.DisambiguateOptions(path_neighbours=2, max_track_span=3))
    assert (0, 13) not in keep
    assert (0, 1) in keep and (5, 6) in keep
    assert info["num_kept"] >= 0.7 * len(graph.pairs)  # confusion spills onto a few neighbours


def test_options_are_checked():
    with pytest.raises(ValueError, match="window"):
        dis.DisambiguateOptions(window=0).validate()
    with pytest.raises(ValueError, match="min_agreement"):
        dis.DisambiguateOptions(min_agreement=2.0).validate()


def _posed_at(centres: dict[int, np.ndarray]) -> ModelPoses:
    w2c = {k: np.hstack([np.eye(3), -np.asarray(c, float)[:, None]]) for k, c in centres.items()}
    return ModelPoses(w2c, {k: None for k in centres}, {k: 500.0 for k in centres})


def test_a_frame_that_leaves_and_comes_back_is_a_spike_but_a_single_jump_is_not():
    line = {k: np.array([0.3 * k, 0.0, 1.2]) for k in range(20)}
    spiked = dict(line)
    spiked[9] = np.array([-4.0, 3.0, 1.2])  # one look-alike plant matched: placed across the row
    del spiked[10], spiked[11]  # unregistered frames widen the gap after it
    assert folds.spikes(_posed_at(spiked), folds.FoldOptions()) == [9]
    assert folds.spikes(_posed_at(line), folds.FoldOptions()) == []
    # a robot crossing to the other aisle jumps once and stays: not a mis-registration
    turned = {k: c + (np.array([0.0, 5.0, 0.0]) if k >= 10 else 0) for k, c in line.items()}
    assert folds.spikes(_posed_at(turned), folds.FoldOptions()) == []


def test_a_chain_of_photos_is_diagnosed_in_the_failure_advice():
    """Photos that each overlap only their neighbours give two-view tracks, which incremental
    mapping cannot grow (the robot aisle drives of the SfM benchmark): the advice says so first;
    a dense walk does not get that tip, and photos with no match are named."""
    from ghsplat_jax.sfm.pipeline import SfmOptions
    from ghsplat_jax.sfm.report import failure_advice, match_graph_stats

    chain, _ = _walk(step=1.3)
    stats = match_graph_stats(chain)
    assert stats["partners_median"] == 2 and stats["num_pairs"] == len(chain.pairs)
    assert "matched only 2 others" in failure_advice(SfmOptions(), 12, 0, stats)[0]
    dense, _ = _walk(step=0.4)
    assert match_graph_stats(dense)["partners_median"] > 2
    assert not any("matched only" in tip for tip in failure_advice(SfmOptions(), 12, 0, match_graph_stats(dense)))
    lonely = dataclasses.replace(dense, pairs={p: m for p, m in dense.pairs.items() if 11 not in p})
    stats = match_graph_stats(lonely)
    assert stats["unmatched_images"] == ["011.png"]
    assert any("011.png" in tip for tip in failure_advice(SfmOptions(), 12, 11, stats))
    # few features for the cap (small or low-contrast photos): the peak threshold is the knob
    assert stats["keypoints_median"] == np.median([len(k) for k in lonely.keypoints]) < 4096
    assert any("--sift-peak-threshold (now 0.00667" in tip for tip in failure_advice(SfmOptions(), 12, 11, stats))
    capped = dict(stats, keypoints_median=8000.0)
    assert not any("--sift-peak-threshold" in tip for tip in failure_advice(SfmOptions(), 12, 11, capped))


def test_keep_pairs_writes_the_narrowed_matches_in_capture_order(tmp_path):
    """A real database whose image ids run against the capture order: keep_pairs drops the
    pairs outside `keep` and stores a narrowed pair's matches the right way round."""
    pycolmap = pytest.importorskip("pycolmap")
    from ghsplat_jax.sfm.matchgraph import keep_pairs, read_match_graph

    source = tmp_path / "database.db"
    db = pycolmap.Database.open(str(source))
    camera_id = db.write_camera(pycolmap.Camera(model="SIMPLE_PINHOLE", width=320, height=240, params=[F, CX, CY]))
    rng = np.random.default_rng(0)
    names = ["a.png", "b.png", "c.png"]
    ids = {name: db.write_image(pycolmap.Image(name=name, camera_id=camera_id)) for name in reversed(names)}
    for name in names:
        db.write_keypoints(ids[name], rng.uniform(0, 200, (50, 2)).astype(np.float32))
    for a, b in (("a.png", "b.png"), ("a.png", "c.png"), ("b.png", "c.png")):
        geometry = pycolmap.TwoViewGeometry()
        geometry.config = 2  # calibrated
        geometry.inlier_matches = np.column_stack([np.arange(20), np.arange(20)[::-1] + 5]).astype(np.uint32)
        db.write_two_view_geometry(ids[a], ids[b], geometry)
    db.close()

    graph = read_match_graph(source, names)
    assert ids["a.png"] > ids["c.png"]  # capture order (0, 2) is stored as (id c, id a)
    narrowed = {(0, 2): graph.pairs[(0, 2)][2:18]}
    target = tmp_path / "filtered.db"
    assert keep_pairs(source, target, graph, {(0, 1), (0, 2)}, narrowed) == 1
    filtered = read_match_graph(target, names)
    assert set(filtered.pairs) == {(0, 1), (0, 2)}
    np.testing.assert_array_equal(filtered.pairs[(0, 2)], graph.pairs[(0, 2)][2:18])
    np.testing.assert_array_equal(filtered.pairs[(0, 1)], graph.pairs[(0, 1)])


def test_chain_segments_inside_larger_ones_are_dropped():
    _, poses = _walk(n=12)
    full = _model(poses)
    views = lambda ks: ModelPoses({k: full.world_to_cam[k] for k in ks}, full.normalise, full.focal)  # noqa: E731
    big, inside, other = views(range(8)), views(range(3, 6)), views(range(6, 11))
    kept = dis.distinct_segments([inside, other, big])
    assert [sorted(s.world_to_cam) for s in kept] == [list(range(8)), [6, 7, 8, 9, 10]]


def _turned(w2c, deg):
    """The camera yawed about its own y axis by `deg`, centre kept."""
    a = np.radians(deg)
    r = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) @ w2c[:, :3]
    centre = -w2c[:, :3].T @ w2c[:, 3]
    return np.column_stack([r, -r @ centre])


def test_the_chain_is_cut_where_a_link_disagrees_with_its_own_matches():
    pytest.importorskip("cv2")
    graph, poses = _walk(n=12)
    opts = dis.DisambiguateOptions(max_link_rotation_deg=3.0)
    # exact poses: no link disagrees, one piece
    assert [sorted(s.world_to_cam) for s in dis.cut_links(graph, [_model(poses)], opts)] == [list(range(12))]
    assert folds.link_rotation_error(graph, _model(poses), (4, 5)) == pytest.approx(0.0, abs=0.1)
    # view 6 placed turned by 5 degrees: both of its links disagree, so it is cut out, and the
    # pieces keep only views that their own matches confirm
    bent = [_turned(p, 5.0) if k == 6 else p for k, p in enumerate(poses)]
    assert folds.link_rotation_error(graph, _model(bent), (5, 6)) == pytest.approx(5.0, abs=0.2)
    pieces = dis.cut_links(graph, [_model(bent)], opts)
    assert [sorted(s.world_to_cam) for s in pieces] == [list(range(6)), list(range(7, 12))]
    # a gap in the capture order (view 2 not registered) also cuts; pieces under 3 views go
    gap = ModelPoses({k: p for k, p in enumerate(poses) if k != 2}, _model(poses).normalise, _model(poses).focal)
    assert [sorted(s.world_to_cam) for s in dis.cut_links(graph, [gap], opts)] == [list(range(3, 12))]


def test_views_the_order_filters_chain_placed_count_as_verified():
    graph, poses = _walk(n=12)
    options = folds.FoldOptions(min_segment=4)
    distant = dataclasses.replace(graph, pairs={p: m for p, m in graph.pairs.items() if p[1] - p[0] > 1 or p[0] < 7})
    # the fold check's chain reached views 0-7 only: views 8-11 were placed through distant pairs
    alone = folds.chain_consistency(_model(poses), [_model(poses[:8])], graph, options, distant)
    assert alone["num_unverified"] == 4
    reached = folds.chain_consistency(_model(poses), [_model(poses[:8])], graph, options, distant,
                                      reached=set(range(6, 12)))
    assert reached["num_unverified"] == 0


def test_a_model_is_split_at_the_seams_its_neighbour_pairs_contradict():
    graph, poses = _walk(n=12)
    options = folds.FoldOptions()
    assert folds.seam_pieces(graph, _model(poses), options) == [list(range(12))]
    # views 0-3 placed 2 m further along the row (a look-alike plant matched): their own pairs
    # still agree, the pair (3, 4) does not, so the model splits there
    shifted = [_look_y(k * 0.4 + 2.0) if k < 4 else p for k, p in enumerate(poses)]
    assert folds.seam_pieces(graph, _model(shifted), options) == [list(range(4, 12)), [0, 1, 2, 3]]
    # in a closed walk the ends are neighbours: with no seam between them it is one piece
    loop = folds.FoldOptions(cyclic=True)
    assert folds.seam_pieces(graph, _model(shifted), loop) == [list(range(4, 12)) + [0, 1, 2, 3]]
