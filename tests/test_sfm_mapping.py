"""Which mapping the order filter keeps: registering from fewer inliers first, COLMAP's
thresholds when that model is flagged (the mapper and the fold check are stand-ins)."""

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
