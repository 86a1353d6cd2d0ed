"""The `ghsplat` commands without a test file of their own, run for real on tiny inputs, their
outputs checked by value: render, export, bench and the quick demo (`ghsplat synth` is in
test_synth_dataset.py, train / eval / run in test_train_cli.py, compose in
test_scene_compose.py, simulate in test_sim_command.py, localize in test_sim_localize.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import ghsplat_jax as gs
from ghsplat_jax import cli
from ghsplat_jax.core.quaternions import from_euler_xyz
from ghsplat_jax.data.images import read_image, read_pixels
from ghsplat_jax.train.config import TrainConfig, save_config
from ghsplat_jax.train.synthetic import cached_synthetic_dataset, random_scene, write_transforms

W, H = 32, 24
DATA = dict(num_views=6, width=W, height=H, num_surfels=40, test_every=3, num_points=200)


def ghsplat(*argv) -> subprocess.CompletedProcess:
    """The command in its own process, as a user runs it (the worktree's package: PYTHONPATH is kept)."""
    return subprocess.run([sys.executable, "-m", "ghsplat_jax.cli", *map(str, argv)], capture_output=True, text=True)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A transforms.json folder rendered from random surfels, and those surfels as a PLY."""
    root = tmp_path_factory.mktemp("scene")
    data = write_transforms(cached_synthetic_dataset(**DATA), root / "data")
    ply = gs.save_ply(random_scene(DATA["num_surfels"], seed=0), root / "scene.ply")
    return data, ply


def test_render_reproduces_a_datasets_views(scene, tmp_path):
    data, ply = scene
    assert cli.main(["render", str(ply), "--data", str(data), "--split", "test", "--out", str(tmp_path)]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(f"view_{i:03d}_{k}" for i in (0, 3) for k in
                           ("rgb.png", "alpha.png", "depth.exr", "depth.png", "normal.png"))
    for i in (0, 3):  # the PLY holds the surfels the dataset was rendered from
        rgb, _ = read_image(tmp_path / f"view_{i:03d}_rgb.png")
        truth, _ = read_image(data / "test" / f"view_{i:03d}.png")
        assert rgb.shape == (H, W, 3) and np.abs(rgb - truth).max() <= 1.5 / 255
        depth = read_pixels(tmp_path / f"view_{i:03d}_depth.exr")
        alpha = read_image(tmp_path / f"view_{i:03d}_alpha.png")[0]
        assert depth.shape == (H, W) and depth.dtype == np.float32
        covered = alpha[..., 0] > 0.5
        assert covered.any() and np.all((depth[covered] > 2.0) & (depth[covered] < 5.0))  # cameras at 3.5 m


def test_render_from_a_look_at_camera_measures_depth_and_colour(tmp_path):
    """One large surfel facing the camera 3 m away: centre depth 3, its colour, opaque."""
    quat = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0]  # normal +z turned to -y, toward the camera
    colour = (np.array([0.8, 0.3, 0.1]) - 0.5) / 0.28209479
    s = gs.make_surfels([[0.0, 0.0, 0.0]], [quat], [[0.0, 0.0]], [8.0], [colour])
    ply = gs.save_ply(s, tmp_path / "one.ply")
    out = tmp_path / "out"
    assert cli.main(["render", str(ply), "--out", str(out), "--eye", "0", "-3", "0", "--size", "32x24",
                     "--background", "0", "0", "1"]) == 0
    rgb, _ = read_image(out / "view_rgb.png")
    depth = read_pixels(out / "view_depth.exr")
    alpha, _ = read_image(out / "view_alpha.png")
    normal, _ = read_image(out / "view_normal.png")
    c = (H // 2, W // 2)
    assert depth[c] == pytest.approx(3.0, abs=1e-3) and alpha[c][0] == pytest.approx(0.99, abs=2 / 255)
    np.testing.assert_allclose(rgb[c], 0.99 * np.array([0.8, 0.3, 0.1]) + 0.01 * np.array([0, 0, 1]), atol=2 / 255)
    np.testing.assert_allclose(normal[c], (0.99 * np.array([0, -1, 0]) + 0.99) / 2, atol=2 / 255)  # facing -y


def test_export_rotates_positions_frames_and_colours_together(tmp_path):
    """`ghsplat export --rotate --translate`: the moved scene seen from the moved camera renders
    the same image (view-dependent colour included: the SH bands are rotated too)."""
    rng = np.random.default_rng(5)
    n = 60
    s = gs.make_surfels(rng.uniform(-0.6, 0.6, (n, 3)), rng.normal(size=(n, 4)), np.log(rng.uniform(0.05, 0.2, (n, 2))),
                        np.full(n, 3.0), rng.normal(0, 0.5, (n, 3)), rng.normal(0, 0.4, (n, 3, 3)), sh_degree=1)
    gs.save_ply(s, tmp_path / "in.ply")
    assert cli.main(["export", str(tmp_path / "in.ply"), "--out", str(tmp_path / "out.ply"), "--rotate", "0", "0",
                     "90", "--translate", "1", "2", "0.5", "--stats-out", str(tmp_path / "stats.json")]) == 0
    moved = gs.load_ply(tmp_path / "out.ply")
    R, t = from_euler_xyz([0, 0, 90], degrees=True), np.array([1.0, 2.0, 0.5])
    np.testing.assert_allclose(moved.means, np.asarray(s.means) @ R.T + t, atol=1e-5)
    assert json.loads((tmp_path / "stats.json").read_text())["count"] == n
    eye, target = np.array([0.5, -3.0, 1.0]), np.zeros(3)
    cfg = gs.RasterConfig(background=(0.0, 0.0, 0.0))
    before = gs.render(s, gs.Camera(gs.intrinsics(W, H, 60), gs.look_at(eye, target), W, H), cfg)
    after = gs.render(moved, gs.Camera(gs.intrinsics(W, H, 60), gs.look_at(R @ eye + t, R @ target + t), W, H), cfg)
    assert float(np.max(before.alpha)) > 0.9
    np.testing.assert_allclose(np.asarray(after.rgb), np.asarray(before.rgb), atol=2e-3)


@pytest.fixture(scope="module")
def finished_run(scene, tmp_path_factory):
    """A finished run folder as the trainer leaves it: config.toml and point_cloud.ply."""
    data, ply = scene
    run = tmp_path_factory.mktemp("run")
    save_config(TrainConfig(data=str(data), test_every=3), run / "config.toml")
    (run / "point_cloud.ply").write_bytes(ply.read_bytes())
    return run


@pytest.mark.slow  # a subprocess compiling three raster variants: the file's longest test after the demo
def test_bench_runs_the_raster_ablation_from_the_checkout(finished_run, tmp_path):
    """raster_ablation imports speed/raster_speed and record.py: `ghsplat bench` must put benchmarks/ on the path."""
    proc = ghsplat("bench", "raster_ablation", "--run", finished_run, "--views", "1", "--repeats", "1",
                   "--tiles", "8", "--chunks", "16", "--variants", "box3,logspace-autodiff", "--results", tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads((tmp_path / "raster_ablation.json").read_text())
    assert result["num_surfels"] == DATA["num_surfels"] and result["image_size"] == [W, H]
    assert result["views"] == ["test/view_000.png"] and result["run"] == str(finished_run)
    rows = result["rows"]
    assert [(r["compositor"], r["bounds"], r["backward"]) for r in rows] == [
        ("carried", "tight", "custom_vjp"), ("carried", "box3", "custom_vjp"), ("logspace", "box3", "autodiff")]
    assert rows[0]["max_abs_diff_vs_default"] == 0.0
    assert rows[1]["max_abs_diff_vs_default"] < 1e-5 and rows[2]["max_abs_diff_vs_default"] < 2e-3  # same image
    assert 0 < rows[0]["kept_pairs"] <= rows[1]["kept_pairs"] == rows[2]["kept_pairs"]  # tight bounds keep fewer
    assert all(r["pixel_evals"] == r["kept_pairs"] * 64 for r in rows)
    assert all(r["forward_s"] > 0 and r["forward_backward_s"] > 0 for r in rows)
    assert read_pixels(tmp_path / "raster_ablation.png").ndim == 3


def test_bench_outside_a_checkout_says_so(monkeypatch, tmp_path, capsys):
    from ghsplat_jax.commands import bench

    monkeypatch.setattr(bench, "BENCHMARKS", tmp_path / "site-packages" / "benchmarks")
    assert cli.main(["bench", "raster_speed"]) == 2
    assert "scripts of the source checkout" in capsys.readouterr().err
    monkeypatch.undo()  # the checkout's benchmarks/ again
    assert cli.main(["bench", "no_such_benchmark"]) == 2
    err = capsys.readouterr().err
    assert "no benchmark" in err and "raster_ablation" in err and "raster_speed" in err


# `ghsplat demo --quick` takes about 150 s on 2 CPU cores: the suite's slowest test, and the only
# one that runs every stage of the pipeline end to end, so `make test-all` (CI) runs it.
@pytest.mark.slow
def test_quick_demo_writes_every_stage(tmp_path):
    from ghsplat_jax.scene.tags import load_tags
    from ghsplat_jax.train import run_dir
    from ghsplat_jax.transport.recorder import read_bag

    out = tmp_path / "demo"
    proc = ghsplat("demo", "--quick", "--out", out)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    metrics = run_dir.read_metrics(out / "run")
    from ghsplat_jax.commands.demo import SETTINGS

    quick = SETTINGS["quick"]  # the auto recipe with a step ceiling: it stops there or before, by its rule
    assert metrics["recipe"] == quick["recipe"] and 0 < metrics["steps"] <= quick["steps"] and "stop" in metrics
    assert metrics["test"]["num_views"] > 0 and metrics["test"]["psnr"] > 10
    assert gs.load_ply(out / "run" / run_dir.PLY_NAME).num == metrics["num_gaussians"]
    assert len(read_pixels(out / "row" / "images" / "00000.png")) == 96  # 128x96 photos
    tags = load_tags(out / "greenhouse.tags.json")[1]
    assert sorted(t.id for t in tags) == [0, 1, 2, 3]
    np.testing.assert_allclose([t.world_from_tag[2, 3] for t in tags], 0.45)  # the layout's marker height
    bag = read_bag(out / "sim.mcap")
    renders = [m for _, m in bag["/render"]]
    assert 0 < len(renders) <= 4 and {(m.width, m.height) for m in renders} == {(128, 96)}
    loc = json.loads((out / "localize" / "localization.json").read_text())
    assert loc["summary"]["frames"] == 6
    assert read_pixels(out / "views" / "greenhouse_rgb.png").shape == (320, 480, 3)
    report = (out / "report.md").read_text()
    assert f"| surfels | {metrics['num_gaussians']} |" in report
    assert f"| training steps | {metrics['steps']}, the auto recipe: " in report and "recipe: None" not in report


def test_make_test_runs_each_file_alone_and_names_a_crashed_one(tmp_path, capsys):
    """`make test`'s runner (tests/run_suite.py): every file runs, a failure or a crash fails the
    suite, and the summary names each bad file with what happened to it."""
    from run_suite import run

    (tmp_path / "test_ok.py").write_text("def test_ok():\n    pass\n")
    (tmp_path / "test_bad.py").write_text("def test_bad():\n    assert False\n")
    (tmp_path / "test_crash.py").write_text(
        "import os, signal\n\ndef test_crash():\n    os.kill(os.getpid(), signal.SIGSEGV)\n")
    files = sorted(tmp_path.glob("test_*.py"))
    assert run(files, ["-q", "-p", "no:faulthandler"], tmp_path) == 1
    out = capsys.readouterr().out
    assert "1 of 3 test files passed" in out
    assert "test_crash.py: killed by SIGSEGV" in out and "test_bad.py: failed (pytest exit 1)" in out
    assert run(files[-1:], ["-q"], tmp_path) == 0  # test_ok.py alone


def test_fast_suite_skips_files_that_are_slow_throughout(tmp_path, capsys):
    """`make test` (run_suite.py --fast) starts only files with a test that is not marked slow."""
    from run_suite import all_slow, select

    (tmp_path / "test_some.py").write_text("import pytest\n\n@pytest.mark.slow\ndef test_a():\n    pass\n")
    (tmp_path / "test_all.py").write_text("import pytest\n\npytestmark = pytest.mark.slow  # long\n")
    (tmp_path / "test_list.py").write_text("import pytest\n\npytestmark = [pytest.mark.slow]\n")
    files = sorted(tmp_path.glob("test_*.py"))
    assert [all_slow(f) for f in files] == [True, True, False]
    assert select(files, fast=True) == [tmp_path / "test_some.py"] and select(files, fast=False) == files


# Each of two tests marks that it started, then waits for the other: both pass only when they run at once.
MEET = """import time
from pathlib import Path

def test_meet():
    here = Path(__file__)
    here.with_suffix(".started").touch()
    other = here.with_name("test_{other}.started")
    deadline = time.monotonic() + 20
    while not other.exists():
        assert time.monotonic() < deadline, "the other file never ran beside this one"
        time.sleep(0.05)
"""


def test_make_test_runs_files_side_by_side_and_keeps_each_output_whole(tmp_path, capsys):
    """`--jobs 2`: two files run at once (each waits for the other), each file's output is printed in one
    piece under its own header, and a file whose tests are all deselected (pytest exit 5) counts as passed."""
    from run_suite import run

    (tmp_path / "test_a.py").write_text(MEET.format(other="b"))
    (tmp_path / "test_b.py").write_text(MEET.format(other="a"))
    (tmp_path / "test_none.py").write_text("import pytest\n\n@pytest.mark.slow\ndef test_x():\n    pass\n")
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    slow: long\n")
    files = sorted(tmp_path.glob("test_*.py"))
    assert run(files, ["-v", "-p", "no:cacheprovider", "-m", "not slow"], tmp_path, jobs=2) == 0
    out = capsys.readouterr().out
    assert "3 of 3 test files passed" in out and "(2 at a time)" in out
    blocks = {b.split(":", 1)[0]: b for b in ("\n" + out).split("\n== ")[1:]}
    assert blocks.keys() >= {"test_a.py", "test_b.py", "test_none.py"}
    for name in ("test_a", "test_b"):  # a file's block holds its own results and none of the other's
        assert f"{name}.py::test_meet PASSED" in blocks[f"{name}.py"]
        assert "::test_meet" not in blocks[f"{name}.py"].replace(f"{name}.py::test_meet", "")
    assert "1 deselected" in blocks["test_none.py"] and blocks["test_none.py"].startswith("test_none.py: passed")


def test_make_test_fails_when_any_file_fails_however_many_run_at_once(tmp_path, capsys):
    from run_suite import run

    for i in range(2):
        (tmp_path / f"test_ok{i}.py").write_text("def test_ok():\n    pass\n")
    (tmp_path / "test_bad.py").write_text("def test_bad():\n    assert False\n")
    files = sorted(tmp_path.glob("test_*.py"))
    for jobs in (2, 5):  # fewer and more workers than files
        assert run(files, ["-q", "-p", "no:cacheprovider"], tmp_path, jobs=jobs) == 1
        out = capsys.readouterr().out
        assert "2 of 3 test files passed" in out and "test_bad.py: failed (pytest exit 1)" in out


def test_make_test_starts_the_longest_files_first_and_records_their_times(tmp_path, capsys):
    """Files start longest first by the recorded seconds, unknown ones before all; a run then records
    each passed file's time (atomically, only changes past jitter, dropping files that are gone)."""
    from run_suite import order, read_times, run, write_times

    files = [tmp_path / f"test_{n}.py" for n in ("short", "long", "new", "mid")]
    recorded = {"test_short.py": 1.0, "test_long.py": 90.0, "test_mid.py": 30.0, "test_gone.py": 5.0}
    assert [p.name for p in order(files, recorded)] == ["test_new.py", "test_long.py", "test_mid.py", "test_short.py"]
    assert order(files, {}) == files

    table = tmp_path / "times.json"
    assert read_times(table, "fast") == {}
    table.write_text(json.dumps({"fast": recorded, "all": {"test_x.py": 7}}))
    write_times(table, "fast", {"test_short.py": 2.5, "test_long.py": 80.0, "test_mid.py": 50.0, "test_new.py": 3.0},
                keep={p.name for p in files})
    # short: +1.5 s (jitter, kept); long: -10 s of 90 (jitter, kept); mid: +20 s (recorded); gone: dropped
    assert read_times(table, "fast") == {"test_short.py": 1.0, "test_long.py": 90.0, "test_mid.py": 50.0,
                                         "test_new.py": 3.0}
    assert read_times(table, "all") == {"test_x.py": 7.0}  # the other suite's record is left alone
    assert sorted(p.name for p in tmp_path.iterdir()) == ["times.json"]  # no temporary file left behind

    # A run starts files in that order, one at a time here: each file appends its name to a log.
    for p in files:
        p.write_text(f"def test_it():\n    with open('started.log', 'a') as f:\n        f.write('{p.name}\\n')\n")
    table.write_text(json.dumps({"fast": {"test_short.py": 1.0, "test_long.py": 90.0, "test_mid.py": 30.0}}))
    assert run(files, ["-q", "-p", "no:cacheprovider"], tmp_path, jobs=1, times=table, suite="fast") == 0
    started = (tmp_path / "started.log").read_text().split()
    assert started == ["test_new.py", "test_long.py", "test_mid.py", "test_short.py"]
    after = read_times(table, "fast")
    assert after.keys() == {p.name for p in files} and after["test_long.py"] < 30  # measured now: far below 90 s
    capsys.readouterr()
    before = table.read_text()
    assert run(files[:1], ["-q", "-p", "no:cacheprovider"], tmp_path, times=table, suite="fast", record=False) == 0
    assert table.read_text() == before


def test_make_test_jobs_option():
    from run_suite import JOBS, jobs_option

    assert JOBS == 2 and jobs_option(["-x"]) == (2, ["-x"])
    assert jobs_option(["--jobs", "3", "-k", "a"]) == (3, ["-k", "a"])
    assert jobs_option(["--jobs=1"]) == (1, []) and jobs_option(["-j", "4", "-q"]) == (4, ["-q"])
    with pytest.raises(SystemExit):
        jobs_option(["--jobs", "0"])


def test_make_test_loads_hypothesis_only_where_a_file_uses_it(tmp_path):
    from run_suite import plugins

    (tmp_path / "test_plain.py").write_text("def test_a():\n    pass\n")
    (tmp_path / "test_fuzz.py").write_text("from hypothesis import given\n")
    assert plugins(tmp_path / "test_plain.py", ["-q"]) == ["-p", "no:hypothesispytest"]
    assert plugins(tmp_path / "test_fuzz.py", ["-q"]) == []
    assert plugins(tmp_path / "test_plain.py", ["--hypothesis-seed=1"]) == []


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_make_test_interrupted_stops_every_test_process(tmp_path, signum):
    """Ctrl-C (SIGINT, to the runner alone here) or SIGTERM on the runner ends the test processes it started."""
    (tmp_path / "test_wait.py").write_text(
        "import os, time\n\ndef test_wait():\n"
        "    open(f'pid{os.getpid()}', 'w').close()\n    time.sleep(120)\n")
    (tmp_path / "test_wait2.py").write_text((tmp_path / "test_wait.py").read_text())
    # main() installs the SIGTERM handler and turns the KeyboardInterrupt into exit 130; run() lets it through
    # after stopping its children. SIGINT gets Python's own handler back: a shell starts background jobs (this
    # suite too, at times) with SIGINT ignored, which a terminal's Ctrl-C never meets.
    script = (f"import signal, sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import run_suite, pathlib; "
              "signal.signal(signal.SIGINT, signal.default_int_handler); "
              "signal.signal(signal.SIGTERM, run_suite.interrupt); "
              f"root = pathlib.Path({str(tmp_path)!r}); "
              "sys.exit(run_suite.run(sorted(root.glob('test_*.py')), ['-q', '-p', 'no:cacheprovider'], root, jobs=2))")
    runner = subprocess.Popen([sys.executable, "-c", script], cwd=tmp_path, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while len(list(tmp_path.glob("pid*"))) < 2:
        assert time.monotonic() < deadline and runner.poll() is None, runner.stdout.read() if runner.stdout else ""
        time.sleep(0.05)
    pids = [int(p.name[3:]) for p in tmp_path.glob("pid*")]
    runner.send_signal(signum)
    out, _ = runner.communicate(timeout=30)
    assert runner.returncode != 0 and b"KeyboardInterrupt" in out
    for pid in pids:  # killed and reaped by the runner: the pid no longer exists
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
