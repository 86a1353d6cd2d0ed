"""Which mapping the order filter keeps: registering from fewer inliers first, COLMAP's
thresholds when that model is flagged (the mapper and the fold check are stand-ins); and a
flagged model trimmed at its seams."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ghsplat_jax.sfm import pipeline
from ghsplat_jax.sfm.matchgraph import MatchGraph


class _Model:
    def __init__(self, views: int, relaxed: bool):
        self.views, self.relaxed = views, relaxed

    def num_reg_images(self):
        return self.views


def _run(monkeypatch, flag_relaxed: bool, method: str = "order", relaxed_views: int = 30):
    graph = MatchGraph([f"{k}.png" for k in range(4)], [1, 2, 3, 4], [1] * 4, [np.zeros((0, 2))] * 4, {})
    calls, filters = [], []

    def map_images(database, root, models_dir, options, filtered=False):
        calls.append(filtered)
        return {0: _Model(relaxed_views if filtered else 20, filtered)}

    def diagnose(graph, mapped_graph, poses, best, options, **kwargs):
        flagged = best.relaxed and flag_relaxed
        return {"fold_suspected": flagged, "reasons": ["bent"] if flagged else []}

    monkeypatch.setattr(pipeline, "map_images", map_images)
    monkeypatch.setattr(pipeline, "filter_pairs",
                        lambda *a: (filters.append(a[5]), (Path("f.db"), {"method": method}, {}, set()))[1])
    monkeypatch.setattr(pipeline.folds, "diagnose", diagnose)
    monkeypatch.setattr(pipeline, "model_poses", lambda best, graph: None)
    monkeypatch.setattr(pipeline, "trim_at_seams", lambda *a: None)  # no seam to cut at here
    mapped = pipeline.map_and_check(Path("d.db"), Path("."), graph, method, pipeline.SfmOptions(), Path("m"), None)
    if method != "none":
        assert filters == calls  # the filter's chain and the map are relaxed together
    return mapped, calls


def test_the_order_filter_keeps_its_relaxed_map_when_the_fold_check_passes(monkeypatch):
    mapped, calls = _run(monkeypatch, flag_relaxed=False)
    assert calls == [True] and mapped.best.views == 30 and "first_mapping" not in mapped.disambiguation


def test_a_flagged_relaxed_map_is_mapped_again_at_colmaps_thresholds(monkeypatch):
    mapped, calls = _run(monkeypatch, flag_relaxed=True)
    assert calls == [True, False] and mapped.best.views == 20 and not mapped.diagnostics["fold_suspected"]
    assert mapped.disambiguation["first_mapping"] == {"min_pose_inliers": 15, "num_registered": 30,
                                                      "reasons": ["bent"]}


def test_a_relaxed_map_of_two_views_is_mapped_again(monkeypatch):
    mapped, calls = _run(monkeypatch, flag_relaxed=False, relaxed_views=2)
    assert calls == [True, False] and mapped.best.views == 20


def test_other_filters_map_at_colmaps_thresholds(monkeypatch):
    _, calls = _run(monkeypatch, flag_relaxed=True, method="tracks")
    assert calls == [False]


def _synthetic_model(views: int = 8):
    import pycolmap

    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_frames_per_rig, options.num_points3D = 1, views, 50
    model = pycolmap.synthesize_dataset(options)
    names = sorted(image.name for image in model.images.values())
    graph = MatchGraph(names, list(range(1, views + 1)), [1] * views, [np.zeros((0, 2))] * views, {})
    return model, graph


def _trim(monkeypatch, pieces, flag_trimmed=False, chain_views=5):
    model, graph = _synthetic_model()
    monkeypatch.setattr(pipeline.folds, "seam_pieces", lambda graph, poses, options: pieces)
    seen = []

    def diagnose(m):
        seen.append(m.num_reg_images())
        return {"fold_suspected": flag_trimmed, "reasons": ["bent"] if flag_trimmed else [],
                "chain_consistency": {"segments": [{"num_images": chain_views}, {"num_images": 2}]}}

    flagged = {"fold_suspected": True, "reasons": ["1 of 7 neighbour pairs contradict"]}
    return model, graph, pipeline.trim_at_seams(model, graph, flagged, pipeline.SfmOptions(), diagnose), seen


def test_a_flagged_model_is_trimmed_to_its_largest_piece_when_that_passes(monkeypatch):
    model, graph, trimmed, seen = _trim(monkeypatch, [[3, 4, 5, 6, 7], [0, 1, 2]])
    copy, diagnostics = trimmed
    assert seen == [5] and copy.num_reg_images() == 5 and model.num_reg_images() == 8  # a copy is trimmed
    assert sorted(copy.images[i].name for i in copy.reg_image_ids()) == graph.names[3:]
    assert diagnostics["trimmed_at_seams"] == {"dropped": graph.names[:3],
                                               "reasons_before": ["1 of 7 neighbour pairs contradict"]}


def test_no_trim_when_the_piece_still_fails_or_no_piece_stands_out(monkeypatch):
    assert _trim(monkeypatch, [[3, 4, 5, 6, 7], [0, 1, 2]], flag_trimmed=True)[2] is None
    assert _trim(monkeypatch, [[4, 5, 6, 7], [0, 1, 2, 3]])[2] is None      # a tie: which side is right?
    assert _trim(monkeypatch, [[0, 1], [2], [3], [4], [5], [6], [7]])[2] is None  # under MIN_MODEL_VIEWS
    assert _trim(monkeypatch, [list(range(8))])[2] is None                  # no seam
    # most of the piece must lie in one chain segment: 3 of 5 is too few, 4 of 5 will do
    assert _trim(monkeypatch, [[3, 4, 5, 6, 7], [0, 1, 2]], chain_views=3)[2] is None
    assert _trim(monkeypatch, [[3, 4, 5, 6, 7], [0, 1, 2]], chain_views=4)[2] is not None
