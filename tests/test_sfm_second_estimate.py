"""The global mapper's second estimate held against a model: exact synthetic models and their
database (pycolmap's synthesize_dataset), a model bent along its views, and the verdict shown."""

from __future__ import annotations

import numpy as np
import pytest
from sfm_models import move_view, synthetic_model

from ghsplat_jax.sfm import second_estimate
from ghsplat_jax.sfm.report import EXIT_INCONSISTENT, verdict

pycolmap = pytest.importorskip("pycolmap")


def _with_database(tmp_path, frames: int = 12):
    db = pycolmap.Database.open(str(tmp_path / "database.db"))
    try:
        model = synthetic_model(frames, db)
    finally:
        db.close()
    return model, tmp_path / "database.db"


def _bend(model, degrees: float) -> list[str]:
    """Turn the views progressively about one world axis, 0 to `degrees` along their order (their
    centres stay): a bend, not a rigid turn. Returns the names in that order."""
    ids = sorted(model.reg_image_ids())
    return [move_view(model, i, turn_deg=degrees * k / (len(ids) - 1), about_world=True) for k, i in enumerate(ids)]


def test_mean_rotation_is_the_rotation_the_set_scatters_round():
    from scipy.spatial.transform import Rotation

    centre = Rotation.from_rotvec([0.3, -0.2, 0.5])
    scatter = Rotation.from_rotvec(np.random.default_rng(0).normal(0, 0.02, (200, 3)))
    mean = second_estimate.mean_rotation((scatter * centre).as_matrix())
    assert np.degrees((Rotation.from_matrix(mean) * centre.inv()).magnitude()) < 0.2


def test_a_similar_copy_agrees_and_a_bent_one_disagrees_at_its_ends():
    model = synthetic_model()
    poses = second_estimate.model_w2c(model)
    # another frame, scale and origin: no deviation
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = {}
    for name, w2c in poses.items():
        centre = -w2c[:3, :3].T @ w2c[:3, 3]
        new = np.eye(4)
        new[:3, :3] = w2c[:3, :3] @ turn.T
        new[:3, 3] = -new[:3, :3] @ (3.0 * turn @ centre + [1.0, 2.0, 3.0])
        moved[name] = new
    deviations = second_estimate.view_deviations(poses, moved, scale=1.0)
    assert max(c for c, _ in deviations.values()) < 1e-9 and max(r for _, r in deviations.values()) < 1e-5

    names = _bend(model, 3.0)
    bent = second_estimate.view_deviations(second_estimate.model_w2c(model), poses, scale=1.0)
    # the mean offset is the middle view's turn: the ends deviate by about half the bend
    assert 1.35 < bent[names[0]][1] < 1.65 and 1.35 < bent[names[-1]][1] < 1.65
    assert min(r for _, r in bent.values()) < 0.15


def test_the_global_estimate_confirms_an_exact_model_and_catches_a_bend(tmp_path):
    model, database = _with_database(tmp_path)
    report = second_estimate.check(database, tmp_path, model, tmp_path / "second")
    assert report["verdict"] == "agree" and report["num_common"] == 12 and report["unconfirmed"] == []
    assert report["pairs_kept"] == 66 and report["pairs_removed"] == 0  # every pair shares points here
    assert report["largest_centre_rel"] < 1e-4 and report["largest_rotation_deg"] < 0.01
    assert not (tmp_path / "second").exists()  # nothing kept when the two agree
    assert "agrees on 12 views" in second_estimate.summary(report)
    assert "left out of it" not in second_estimate.summary(report)
    report["estimated_again_without"] = ["a.png", "b.png"]
    assert "2 views it misplaced at first were left out of it (a.png, b.png)" in second_estimate.summary(report)

    names = _bend(model, 4.0)
    report = second_estimate.check(database, tmp_path, model, tmp_path / "second")
    assert report["verdict"] == "disagree"
    flagged = [v["name"] for v in report["disagree"]]
    assert {names[0], names[-1]} <= set(flagged) and names[len(names) // 2] not in flagged
    assert (tmp_path / "second" / "models" / "0").is_dir()  # kept for inspection
    text = second_estimate.summary(report)
    assert names[0] in text and "of 12 views lie elsewhere" in text

    code, message = verdict("inconsistent", [], 12, 12, 0.9, "OUT", second=report)
    assert code == EXIT_INCONSISTENT and names[0] in message and "--no-second-estimate" in message


def test_a_view_the_estimate_misplaces_grossly_is_its_failure_not_a_bend():
    model, estimate = synthetic_model(), synthetic_model()
    ids = sorted(estimate.reg_image_ids())
    wrong = move_view(estimate, ids[3], shift=(0.5, 0.0, 0.0), turn_deg=30.0)
    options = second_estimate.SecondEstimateOptions()
    report = second_estimate.compare(model, estimate, options)
    assert report["verdict"] == "agree" and report["misplaced_by_estimate"] == [wrong]
    assert report["largest_rotation_deg"] < 1e-4  # the rest, fitted without it, agree exactly
    assert wrong in second_estimate.summary(report)
    for i in ids[4:6]:
        move_view(estimate, i, turn_deg=30.0)
    report = second_estimate.compare(model, estimate, options)  # 3 of 12 misplaced: over 10%
    assert report["verdict"] == "none" and len(report["misplaced_by_estimate"]) >= 2  # it stops past 10%
    assert "of 12 views: no verdict" in second_estimate.summary(report)


def test_a_lone_view_beyond_the_bounds_is_not_a_bend():
    model, estimate = synthetic_model(), synthetic_model()
    lone = move_view(estimate, sorted(estimate.reg_image_ids())[5], turn_deg=2.0)
    report = second_estimate.compare(model, estimate, second_estimate.SecondEstimateOptions())
    assert report["verdict"] == "agree" and [v["name"] for v in report["disagree"]] == [lone]
    assert f"one view alone lies beyond the bounds, {lone}" in second_estimate.summary(report)


def test_pairs_the_model_does_not_share_points_across_are_left_out(tmp_path):
    model, database = _with_database(tmp_path)
    ids = sorted(model.reg_image_ids())
    shared = second_estimate.shared_point_counts(model)
    assert shared[(ids[0], ids[1])] > 15
    kept, removed = second_estimate.confirmed_pairs_database(database, tmp_path / "kept.db", model,
                                                             min_shared_points=10**6)
    assert (kept, removed) == (0, 66)
    db = pycolmap.Database.open(str(tmp_path / "kept.db"))
    try:
        assert len(db.read_two_view_geometries()[0]) == 0
    finally:
        db.close()
    left_out = model.images[ids[0]].name
    kept, removed = second_estimate.confirmed_pairs_database(database, tmp_path / "kept.db", model, 1,
                                                             frozenset({left_out}))
    assert (kept, removed) == (55, 11)  # the 11 pairs of the view left out


def test_no_verdict_without_a_second_estimate():
    report = second_estimate.compare(synthetic_model(6), None, second_estimate.SecondEstimateOptions())
    assert report["verdict"] == "none" and report["num_common"] == 0 and len(report["unconfirmed"]) == 6
    assert "no verdict" in second_estimate.summary(report)
