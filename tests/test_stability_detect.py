"""The stability study's detection mapping (what flagged a training row) and its aggregation
over seeds: pure functions on fake metrics dicts."""

import math

import pytest

from ghsplat_jax.eval.evaluate import diagnose
from ghsplat_jax.experiments import stability


def _rows(split, psnrs, structure=None):
    return [{"split": split, "name": f"{split}{i:02d}.png", "psnr": p,
             **({} if structure is None else {"structure_psnr": structure})} for i, p in enumerate(psnrs)]


def _metrics(train, test, rows):
    """metrics.json as evaluate writes it: split summaries plus diagnose()'s entries."""
    m = {"train": train, "test": test}
    return m | diagnose(m, rows)


def test_a_clean_run_flags_nothing():
    rows = _rows("train", [20.0, 20.5, 19.8]) + _rows("test", [19.0, 19.4, 19.2])
    m = _metrics({"psnr": 20.1}, {"psnr": 19.2}, rows)
    assert stability.detect(m, []) == []
    assert stability.describe_detection(True, [[]], [0]) == ("none needed", None)
    det, msg = stability.describe_detection(False, [[]], [0])
    assert det == "NOT DETECTED: training ends normally" and msg is None


def test_outlier_views_are_named_with_the_exact_warning():
    rows = _rows("train", [20.0] * 5) + _rows("test", [19.0, 19.2, 19.1, 11.0])
    m = _metrics({"psnr": 20.0}, {"psnr": 17.0}, rows)
    found = stability.detect(m, [])
    assert [f["kind"] for f in found] == ["outlier views"]
    assert found[0]["detail"] == "test: test03.png"
    text = next(w for w in m["warnings"] if w.startswith("1 test view(s)"))
    assert found[0]["message"] == f"WARNING ghsplat.eval: OUT: {text}"
    det, msg = stability.describe_detection(False, [found, []], [0, 1])
    assert det == "outlier views (test: test03.png; 1 of 2 seed(s))" and msg == found[0]["message"]


def test_train_test_gap_and_missing_structure_each_name_their_warning():
    rows = _rows("train", [30.0] * 3, structure=15.0) + _rows("test", [21.0] * 3, structure=15.0)
    m = _metrics({"psnr": 30.0, "structure_psnr": 15.0, "structure_gain_db": 0.4},
                 {"psnr": 21.0, "structure_psnr": 15.0, "structure_gain_db": 2.0}, rows)
    found = stability.detect(m, [])
    assert [f["kind"] for f in found] == ["train-test gap", "missing structure"]
    assert found[0]["detail"] == "9.0 dB" and "over-fits" in found[0]["message"]
    assert found[1]["detail"] == "train gain 0.4 dB"  # the test split gains 2 dB: over the 1 dB line
    assert found[1]["message"].startswith("WARNING ghsplat.eval: OUT: train views: where the photos show structure")


def test_input_check_and_nan_guard_come_from_the_logged_lines():
    lines = ["WARNING ghsplat.train: only 5 training views", "WARNING ghsplat.train: step 3: rolled back (NaN)",
             "WARNING ghsplat.train: step 9: rolled back (NaN)"]
    found = stability.detect(None, lines)
    assert [f["kind"] for f in found] == ["input check", "NaN guard"]
    assert found[0]["message"] == lines[0]
    assert found[1]["detail"] == "2 step(s) rolled back"
    assert found[1]["message"] == lines[1] + " (and 1 more)"
    det, msg = stability.describe_detection(False, [found], [0])
    assert det.startswith("input check (warned when training starts; 1 of 1 seed(s)); NaN guard (2 step(s)")
    assert msg.split("\n") == [lines[0], lines[1] + " (and 1 more)"]


def test_a_warning_the_baseline_also_raises_does_not_detect_a_failure():
    found = [{"kind": "missing structure", "detail": "test 12.0 dB", "message": "m"}]
    det, _ = stability.describe_detection(False, [found], [0], baseline_kinds={"missing structure"})
    assert det.startswith("NOT DETECTED") and "missing structure" in det
    det, _ = stability.describe_detection(False, [found], [0], baseline_kinds=set())
    assert det.startswith("missing structure")
    det, _ = stability.describe_detection(True, [found], [0])
    assert det.startswith("passes; warned: missing structure")


def test_seed_stats_and_verdict_spread():
    st = stability.seed_stats([15.0, 16.0, 17.0])
    assert (st["mean"], st["sd"], st["min"], st["max"], st["n"]) == (16.0, 1.0, 15.0, 17.0, 3)
    assert stability.seed_stats([3.0])["sd"] == 0.0
    # paired with the baseline: per-seed differences -2, -2.1, -1.9 against the -1 dB line
    v = stability.verdict_spread([15.0, 15.9, 17.1], -1.0, paired_with=[17.0, 18.0, 19.0])
    assert v["margin_db"] == pytest.approx(-1.0) and v["spread_db"] == pytest.approx(0.1)
    assert v["outside"] is True
    # a noisy case near the line: the verdict is within the spread
    v = stability.verdict_spread([16.0, 18.5, 17.0], -1.0, paired_with=[17.0, 18.0, 19.0])
    assert v["margin_db"] == pytest.approx(1 / 6) and v["outside"] is False
    # absolute criterion (the thin-plant goal)
    v = stability.verdict_spread([19.0, 19.5, 20.0], 18.0)
    assert v["margin_db"] == pytest.approx(1.5) and v["spread_db"] == pytest.approx(0.5) and v["outside"]
    assert stability.verdict_spread([19.0], 18.0)["outside"] is None


def test_study_file_runs_every_training_case_with_three_seeds():
    from pathlib import Path

    from ghsplat_jax.experiments.runner import load_experiment

    root = Path(__file__).resolve().parent.parent
    for preset in ("full", "quick"):
        exp = load_experiment(root / "experiments" / "stability.toml", preset=preset)
        ctx = stability.Context(Path("."), Path("."), None, seeds=exp.spec.get("seeds"))
        cases = stability.check_cases(exp.spec["cases"])
        train = [c for c in cases if c["family"] == "train"]
        assert all(stability.case_seeds(c, ctx) == [0, 1, 2] for c in train)
        thin = {c["name"]: c for c in train if c.get("dataset")}
        auto = {"thin-plant-auto"} if preset == "full" else set()
        assert set(thin) == {"thin-plant", "thin-plant-no-triangulate"} | auto
        assert thin["thin-plant-no-triangulate"]["triangulate"] is False
        assert all(math.isclose(c["goal_plant_psnr"], 18.0) for c in thin.values())
