"""The rotation-chain bound on synthetic chains (pure NumPy) and the leave-one-out cross-check
on small exact models (pycolmap's synthesize_dataset, no feature extraction or mapping)."""

from __future__ import annotations

import numpy as np
import pytest
from sfm_models import move_view, synthetic_model

from ghsplat_jax.sfm import crosscheck, folds


def _rotations(rng, n: int, sigma_deg: float) -> np.ndarray:
    """n random rotations with N(0, sigma^2) per axis (rotation vectors), as (n,3,3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rng.normal(0.0, np.radians(sigma_deg), (n, 3))).as_matrix()


def _chain(rng, n: int, noise_deg: float, seam: tuple[int, float] | None = None):
    """One run of n links: the model's steps (an orbit-like 5 degrees of turn a frame) and the
    measured ones, off by per-link noise; `seam` (link, degrees): one link measured that far off."""
    turn = np.radians(5.0)
    step = np.array([[np.cos(turn), 0, np.sin(turn)], [0, 1, 0], [-np.sin(turn), 0, np.cos(turn)]])
    model = [step] * n
    measured = list(_rotations(rng, n, noise_deg) @ step)
    if seam is not None:
        k, degrees = seam
        a = np.radians(degrees)
        measured[k] = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]) @ measured[k]
    return [list(zip(measured, model))]


def _flagged(runs, options=folds.FoldOptions()) -> tuple[bool, float, float]:
    drift, errors = folds.chained_drift(runs)
    bound = folds.drift_bound(errors, options)
    return max(drift) > bound, max(drift), bound


def test_the_drift_bound_grows_with_the_chain_and_its_link_noise():
    options = folds.FoldOptions()
    assert folds.drift_bound([], options) == options.max_rotation_drift_deg
    short = folds.drift_bound([0.5] * 20, options)
    assert short == options.max_rotation_drift_deg  # short, quiet chains keep the fixed bound
    long = folds.drift_bound([2.0] * 300, options)
    assert long == pytest.approx(options.drift_sigmas * 2.0 / folds.MAXWELL_MEDIAN * np.sqrt(300))
    # the median: a few wild links (a fold's seam) do not raise the bound
    assert folds.drift_bound([0.5] * 68 + [60.0] * 4, options) == options.max_rotation_drift_deg


def test_long_noisy_chains_pass_and_a_seam_is_flagged():
    rng = np.random.default_rng(0)
    over_fixed = 0
    for _ in range(40):
        flagged, drift, bound = _flagged(_chain(rng, 120, 2.0))
        over_fixed += drift > folds.FoldOptions().max_rotation_drift_deg
        assert not flagged, (drift, bound)
    assert over_fixed >= 10  # the old fixed 30-degree bound refused many of these correct chains
    for _ in range(10):
        flagged, drift, bound = _flagged(_chain(rng, 60, 0.5, seam=(30, 60.0)))
        assert flagged and drift > 50 and bound == folds.FoldOptions().max_rotation_drift_deg


def test_chained_drift_restarts_at_gaps():
    rng = np.random.default_rng(1)
    a, b = _chain(rng, 10, 0.0)[0], _chain(rng, 10, 0.0, seam=(0, 20.0))[0]
    drift, errors = folds.chained_drift([a, b])
    assert len(drift) == len(errors) == 20
    assert max(drift[:10]) < 1e-6 and min(drift[10:]) == pytest.approx(20.0, abs=1e-6)
    assert max(errors) == pytest.approx(20.0, abs=1e-6)


# --- leave-one-out cross-check -------------------------------------------------------------

def test_leave_one_out_triangulation_uses_only_the_other_rays():
    point = np.array([0.3, -0.2, 4.0])
    centres = np.array([[-1.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [5.0, 5.0, 5.0]])
    rays = point - centres
    rays[3] = [0.0, 0.0, 1.0]  # a wrong ray: only its own left-out estimate ignores it
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    xyz, usable = crosscheck.leave_one_out_points(np.zeros(4, int), rays, centres, min_track=2)
    assert usable.all()
    np.testing.assert_allclose(xyz[3], point, atol=1e-9)
    assert np.linalg.norm(xyz[0] - point) > 0.1
    two = crosscheck.leave_one_out_points(np.zeros(2, int), rays[:2], centres[:2], min_track=2)[1]
    assert not two.any()  # one other ray cannot triangulate
    # near-parallel other rays (under min_angle_deg) are not used
    far = np.array([0.0, 0.0, 400.0])
    rays_far = far - centres[:3]
    rays_far /= np.linalg.norm(rays_far, axis=1, keepdims=True)
    assert not crosscheck.leave_one_out_points(np.zeros(3, int), rays_far, centres[:3], 2, 2.0)[1].any()


def test_cross_check_confirms_an_exact_model():
    report = crosscheck.cross_check(synthetic_model())
    assert report["num_views"] == report["num_confirmed"] == 12 and report["flagged"] == []
    assert report["largest_centre_rel"] < 1e-6 and report["largest_rotation_deg"] < 1e-4


@pytest.mark.parametrize("shift, turn", [((0.3, 0.0, 0.0), 0.0), ((0.0, 0.0, 0.0), 3.0)])
def test_cross_check_flags_and_drops_a_moved_view(shift, turn):
    model = synthetic_model()
    ids = sorted(model.reg_image_ids())
    moved = move_view(model, ids[2], shift, turn)
    report = crosscheck.cross_check(model)
    # the moved view lies farthest off; its wrong rays can push a few others' estimates past the
    # thresholds too (every view here sees every point), which check_and_drop's one-at-a-time
    # dropping leaves in the model
    options = crosscheck.CrossCheckOptions()
    worst = max(report["flagged"], key=lambda f: crosscheck._badness(f, options))
    assert worst["name"] == moved
    assert worst["centre_rel"] > 2 * options.max_centre_rel or worst["rotation_deg"] > 2 * options.max_rotation_deg
    dropped = crosscheck.check_and_drop(model)
    assert dropped["dropped"] == [moved] and dropped["flagged"] == [] and model.num_reg_images() == 11
    assert dropped["refined"]  # the rest bundle-adjusted without it
    assert dropped["rounds"][0][0]["name"] == moved
    advice = crosscheck.advice(dropped)
    assert advice and moved in advice[0] and "--no-cross-check" in advice[-1]


def test_views_the_others_cannot_confirm_are_flagged():
    model = synthetic_model(6)
    report = crosscheck.cross_check(model, crosscheck.CrossCheckOptions(min_points=1000))
    assert report["num_confirmed"] == 0 and len(report["flagged"]) == 6
    assert all("cannot be re-localised" in f["reason"] for f in report["flagged"])
    quiet = crosscheck.cross_check(model, crosscheck.CrossCheckOptions(min_points=1000, flag_unconfirmed=False))
    assert quiet["flagged"] == []
