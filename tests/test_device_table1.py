"""benchmarks/analysis/device_table1.py: which run a GPU session pauses or resumes, its rate windows and
what it packs to bring back."""

import argparse
import json
import tarfile

from benchmark_scripts import load_benchmark

dt = load_benchmark("device_table1")


def run(name, step, rate, sharers=3):
    r = dt.Run(name, "default", None, None, 0.0, last_step=step)
    r.rate, r.sharers = rate, sharers
    return r


def test_pauses_the_run_furthest_from_done_and_never_the_last():
    near, mid, far = run("a", 20000, 40.0), run("b", 10000, 40.0), run("c", 5000, 40.0)
    action, chosen = dt.decide([near, mid, far], [], left=300.0, steps=30000)
    assert action == "pause" and chosen is far
    # alone, `far` would still miss the end, but a lone run is left going
    assert dt.decide([far], [], left=60.0, steps=30000) is None
    # a run without a measured rate yet: no decision on guesses
    assert dt.decide([near, run("d", 100, None)], [], left=1.0, steps=30000) is None


def test_resumes_the_paused_run_nearest_to_done_when_it_fits():
    going, paused = [run("a", 29000, 80.0, sharers=1)], [run("b", 20000, 50.0), run("c", 25000, 50.0)]
    action, chosen = dt.decide(going, paused, left=400.0, steps=30000)
    assert action == "resume" and chosen.segment == "c"
    assert dt.decide(going, paused, left=100.0, steps=30000) is None  # 5,000 steps at two sharing do not fit


def test_sharing_slows_each_run_by_the_measured_exponent():
    alone = run("a", 0, 86.0, sharers=1)
    five = dt.projected_seconds([alone] + [run(str(i), 0, 86.0, sharers=1) for i in range(4)], steps=30000)
    one = dt.projected_seconds([alone], steps=30000)
    assert abs((five - dt.EVAL_MARGIN_S) / (one - dt.EVAL_MARGIN_S) - 5 ** dt.SHARE_EXPONENT) < 1e-9


def test_rate_windows(tmp_path):
    stats = tmp_path / "stats.jsonl"
    stats.write_text("".join(json.dumps(dict(step=s, elapsed_s=30.0 + 0.01 * s, num_surfels=1000)) + "\n"
                             for s in range(1, 9001)))
    windows = dt.rate_windows(stats)
    assert len(windows) == 3 and all(abs(w["steps_per_s"] - 100.0) < 1.0 for w in windows)


def test_pack_leaves_checkpoints_and_plys_behind(tmp_path):
    folder = tmp_path / "runs" / "row0_x0" / "default"
    folder.mkdir(parents=True)
    for name in ("metrics.json", "stats.jsonl", "checkpoint.npz", "point_cloud.ply"):
        (folder / name).write_text("x")
    (tmp_path / "out").mkdir()
    dt.pack(argparse.Namespace(runs=str(tmp_path / "runs"), out=str(tmp_path / "out")))
    with tarfile.open(tmp_path / "out" / "row0_x0.tar.gz") as tar:
        names = set(tar.getnames())
    assert {"row0_x0/default/metrics.json", "row0_x0/default/stats.jsonl"} <= names
    assert not any(n.endswith((".npz", ".ply")) for n in names)
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["row0_x0.tar.gz"]  # no scratch file left
