"""The SfM refusal names its cause: low texture, too few matches, separate groups, a short baseline
(ghsplat_jax/sfm/diagnose.py), on made-up statistics; and the thresholds still match pycolmap's."""

from __future__ import annotations

from ghsplat_jax.sfm import diagnose as dg
from ghsplat_jax.sfm.report import EXIT_TOO_FEW_REGISTERED, summary_text, verdict

NAMES = [f"{k:03d}.png" for k in range(10)]


def chain(inliers: int, names=NAMES) -> dict:
    """Each photo matched to the next two, `inliers` verified matches per pair."""
    return {(a, b): inliers for k, a in enumerate(names) for b in names[k + 1:k + 3]}


def evidence(**changes) -> dg.Evidence:
    base = dict(names=NAMES, keypoints=dict.fromkeys(NAMES, 2000), inliers=chain(400),
                configs=dict.fromkeys(chain(400), "UNCALIBRATED"), angles_deg=dict.fromkeys(chain(400), 12.0))
    return dg.Evidence(**{**base, **changes})


def causes(diagnosis: list[dict]) -> list[str]:
    return [d["cause"] for d in diagnosis]


def test_a_healthy_capture_has_no_cause():
    assert dg.diagnose(evidence(), refused=True) == []


def test_low_texture_is_named_from_the_feature_counts():
    ev = evidence(keypoints=dict.fromkeys(NAMES, 90), inliers=chain(40))
    found = dg.diagnose(ev, refused=True)
    assert causes(found)[:2] == ["low texture", "too few matches"]
    assert "median of 90 SIFT features" in found[0]["detail"]
    assert "sharp" in found[0]["advice"]


def test_one_blank_photo_is_named_among_good_ones():
    counts = dict.fromkeys(NAMES, 2000) | {"004.png": 120}
    found = dg.diagnose(evidence(keypoints=counts, registered=set(NAMES) - {"004.png"}), refused=False)
    assert causes(found) == ["low texture"]
    assert found[0]["images"] == ["004.png"] and "004.png (120)" in found[0]["detail"]


def test_too_few_matches_names_the_best_pair_and_the_weak_photos():
    inliers = chain(45) | {("003.png", "004.png"): 20, ("003.png", "005.png"): 18, ("002.png", "003.png"): 17,
                           ("001.png", "003.png"): 16}
    found = dg.diagnose(evidence(inliers=inliers), refused=True)
    assert causes(found) == ["too few matches"]
    detail = found[0]["detail"]
    assert "shares only 45 verified matches" in detail and f"a pair with {dg.START_INLIERS}" in detail
    assert "003.png (20)" in detail
    assert "overlapping the next by 70-80%" in found[0]["advice"]


def test_a_photo_that_matched_nothing_is_named():
    inliers = {p: n for p, n in chain(400).items() if "009.png" not in p}
    found = dg.diagnose(evidence(inliers=inliers, registered=set(NAMES[:9])), refused=False)
    assert causes(found) == ["too few matches"]
    assert "1 photos matched no other photo (009.png)" in found[0]["detail"]


def test_a_split_match_graph_says_where_photos_are_missing():
    inliers = {(a, b): n for (a, b), n in chain(400).items() if (a < "005.png") == (b < "005.png")}
    found = dg.diagnose(evidence(inliers=inliers, registered=set(NAMES[:5])), refused=True)
    split = [d for d in found if d["cause"] == "separate groups"]
    assert split and "2 groups" in split[0]["detail"] and "sizes 5, 5" in split[0]["detail"]
    assert split[0]["advice"] == "add photos between 004.png and 005.png"
    assert split[0]["images"] == NAMES[5:]
    # without a known capture order there is no "between"
    unordered = dg.diagnose(evidence(inliers=inliers, registered=set(NAMES[:5])), refused=True, ordered=False)
    advice = [d["advice"] for d in unordered if d["cause"] == "separate groups"]
    assert advice == ["add photos that overlap both groups"]


def test_rotating_in_place_is_a_short_baseline():
    pairs = chain(400)
    found = dg.diagnose(evidence(angles_deg=dict.fromkeys(pairs, 0.8),
                                 configs=dict.fromkeys(pairs, "PLANAR_OR_PANORAMIC")), refused=True)
    assert causes(found) == ["short baseline"]
    assert "fit a pure rotation" in found[0]["detail"] and "more than 4 degrees" in found[0]["detail"]
    assert "instead of rotating in place" in found[0]["advice"]


def test_a_model_of_flat_angles_is_a_short_baseline():
    found = dg.diagnose(evidence(model_angle_deg=1.2, registered=set(NAMES[:3])), refused=True)
    assert causes(found) == ["short baseline"] and "median angle of 1.2 degrees" in found[0]["detail"]


def test_only_unregistered_photos_are_explained_when_the_model_is_accepted():
    ev = evidence(keypoints=dict.fromkeys(NAMES, 90), registered=set(NAMES[:9]),
                  dropped={"009.png": "landed elsewhere (cross-check)"})
    found = dg.diagnose(ev, refused=False)
    assert causes(found) == ["left out by a check", "low texture"]
    assert found[1]["images"] == ["009.png"]


def test_unreadable_photos_are_named():
    found = dg.diagnose(evidence(unreadable=["bad.png"], registered=set(NAMES)), refused=False)
    assert causes(found) == ["unreadable"] and "bad.png" in found[0]["detail"]


def test_the_refusal_message_and_the_summary_name_the_causes():
    found = dg.diagnose(evidence(keypoints=dict.fromkeys(NAMES, 90), inliers=chain(40)), refused=True)
    code, message = verdict("failed", [], 0, 10, 0.9, "OUT", found)
    assert code == EXIT_TOO_FEW_REGISTERED
    assert message.startswith("ghsplat sfm: only 0 of 10 images registered (below --min-registered-fraction 0.9)")
    assert "Likely causes:" in message and "low texture:" in message and "too few matches:" in message
    assert verdict("failed", [], 0, 10, 0.9, "OUT")[1].count("\n") == 0  # no diagnosis: the old line
    text = summary_text({"num_images": 10, "num_registered": 0, "status": "failed", "diagnosis": found})
    assert "Why so few images registered:" in text and "What to do:" in text


def test_thresholds_are_pycolmaps():
    import pycolmap

    mapper = pycolmap.IncrementalPipelineOptions().mapper
    assert dg.START_INLIERS == mapper.init_min_num_inliers
    assert dg.PLACE_INLIERS == mapper.abs_pose_min_num_inliers
    assert dg.START_ANGLE_DEG == mapper.init_min_tri_angle
    assert dg.MATCH_INLIERS == pycolmap.TwoViewGeometryOptions().min_num_inliers
    assert set(dg.ROTATION_CONFIGS) <= set(pycolmap.TwoViewGeometryConfiguration.__members__)
