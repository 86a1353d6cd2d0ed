"""Reports and charts from metrics.json files (no rendering), and the experiment file parser."""

from __future__ import annotations

import csv
import json

import pytest

from ghsplat_jax.eval.metrics import image_metrics, summarize
from ghsplat_jax.experiments.charts import (
    pareto_figure,
    pareto_front,
    scatter_figure,
    scatter_series,
    split_label,
    write_charts,
    write_pareto_charts,
)
from ghsplat_jax.experiments.labels import label_box, overlap, place_labels
from ghsplat_jax.experiments.report import collect_runs, table1_markdown, write_results, write_table1
from ghsplat_jax.experiments.runner import load_experiment
from ghsplat_jax.train.config import ConfigError

TWO_SCENES = '''[[scenes]]
name = "a"
data = "da"
[[scenes]]
name = "b"
data = "db"
'''


def _fake_run(folder, psnr, l1, n, test=True):
    folder.mkdir(parents=True)
    split = {"psnr": psnr, "l1": l1, "ssim": 0.9, "num_views": 3}
    (folder / "metrics.json").write_text(json.dumps({
        "train": split, "test": split if test else {"psnr": None, "l1": None, "ssim": None, "num_views": 0},
        "num_gaussians": n, "train_seconds": 100.0 * n / 1000, "steps": 300}))
    return folder


def test_table1_and_results_tables(tmp_path):
    runs = [_fake_run(tmp_path / "seg_a", 30.5, 0.015, 300_000), _fake_run(tmp_path / "seg_b", 28.25, 0.021, 410_000),
            _fake_run(tmp_path / "seg_c", 25.0, 0.03, 1000, test=False), tmp_path / "unfinished"]
    rows = collect_runs(runs)
    assert [r["scene"] for r in rows] == ["seg_a", "seg_b", "seg_c"]
    assert rows[2]["split"] == "train"
    md, csv_path = write_table1(rows, tmp_path / "report")
    text = md.read_text()
    assert "| seg_a | 0.0150 | 30.50 | 300,000 |" in text
    assert "L1 0.0150-0.0300, PSNR 25.00-30.50 dB" in text and "27.9-32.1" in text
    table = list(csv.DictReader(csv_path.open()))
    assert table[1]["segment"] == "seg_b" and float(table[1]["psnr"]) == 28.25 and table[1]["num_gaussians"] == "410000"
    paths = write_results(rows, tmp_path / "report")
    assert all(p.is_file() for p in paths)
    assert "colour-corrected" not in paths[0].read_text()  # no run has the metric: no empty column
    write_results([dict(rows[0], psnr_cc=31.25)] + rows[1:], tmp_path / "report_cc")
    assert "| seg_a |  | test | 30.50 | 31.25 |" in (tmp_path / "report_cc" / "results.md").read_text()
    charts = write_charts(rows, tmp_path / "report", "t")
    assert {p.name for p in charts} == {"psnr_vs_time.png", "psnr_vs_count.png"}
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in charts)
    # the data behind the charts: every run with both values, at its metrics.json values
    data = json.loads((tmp_path / "report" / "psnr_vs_count.json").read_text())
    assert (data["x"], data["y"]) == ("num_gaussians", "psnr")
    assert data["series"] == {"": [{"scene": "seg_a", "x": 300_000, "y": 30.5}, {"scene": "seg_b", "x": 410_000,
                                                                                    "y": 28.25},
                                   {"scene": "seg_c", "x": 1000, "y": 25.0}]}
    time_data = json.loads((tmp_path / "report" / "psnr_vs_time.json").read_text())["series"][""]
    assert [p["x"] for p in time_data] == [r["train_seconds"] for r in rows] == [30000.0, 41000.0, 100.0]
    assert "Gaussians" in table1_markdown(rows)
    # a table of only non-default runs names their variant (it is not the protocol's row)
    assert "| seg_a (compact) | 0.0150 |" in table1_markdown([dict(rows[0], variant="compact")])


def test_chart_series_split_by_variant_and_drawn_as_given():
    rows = [{"scene": "a", "variant": "budget", "psnr": 30.0, "num_gaussians": 10},
            {"scene": "a", "variant": "default", "psnr": 31.0, "num_gaussians": 40},
            {"scene": "b", "variant": "default", "psnr": None, "num_gaussians": 50},  # not evaluated: left out
            {"scene": "b", "variant": "budget", "psnr": 27.0, "num_gaussians": 12}]
    series = scatter_series(rows, "num_gaussians", "psnr")
    assert list(series) == ["budget", "default"]
    assert [(p["scene"], p["x"], p["y"]) for p in series["budget"]] == [("a", 10, 30.0), ("b", 12, 27.0)]
    assert [p["scene"] for p in series["default"]] == ["a"]
    fig = scatter_figure(series, "surfels", "PSNR (dB)")
    ax = fig.axes[0]
    drawn = [c.get_offsets().tolist() for c in ax.collections]
    assert drawn == [[[10, 30.0], [12, 27.0]], [[40, 31.0]]]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["budget", "default"]
    assert scatter_series(rows, "train_seconds", "psnr") == {}



def test_a_chart_tells_every_variant_apart_and_names_its_views(tmp_path):
    """An ablation's 13 variants on one scene: 13 different (colour, marker) pairs, 13 different
    colours, each point labelled by its variant (not the one scene), and the split on the y axis."""
    variants = [f"v{i:02d}" for i in range(13)]
    rows = [{"scene": "row1_x1", "variant": v, "split": "test", "psnr": 27.0 + i / 10, "num_gaussians": 1000 + i,
             "train_seconds": 600.0 + i} for i, v in enumerate(variants)]
    ax = scatter_figure(scatter_series(rows, "num_gaussians", "psnr"), "surfels", "PSNR (dB)").axes[0]
    colours = [tuple(c.get_facecolor()[0]) for c in ax.collections]
    markers = [c.get_paths()[0].vertices.tobytes() for c in ax.collections]
    assert len(set(colours)) == 13 and len(set(zip(colours, markers))) == 13
    assert [t.get_text() for t in ax.texts] == variants
    write_charts(rows, tmp_path, "ablation")
    assert json.loads((tmp_path / "psnr_vs_time.json").read_text())["series"].keys() == set(variants)
    unnamed = {"": scatter_series(rows[:1], "num_gaussians", "psnr")["v00"]}
    assert [t.get_text() for t in scatter_figure(unnamed, "s", "dB").axes[0].texts] == ["row1_x1"]
    assert split_label("PSNR (dB)", rows) == "PSNR (dB), test views"
    assert split_label("PSNR (dB)", [{}]) == "PSNR (dB)"

def test_metrics_and_summary():
    import numpy as np

    a = np.full((24, 32, 3), 0.5, np.float32)
    m = image_metrics(a + 0.1, a)
    assert m["psnr"] == pytest.approx(20.0, abs=1e-3) and m["l1"] == pytest.approx(0.1, abs=1e-6)
    assert image_metrics(a, a)["ssim"] == pytest.approx(1.0, abs=1e-5)
    assert image_metrics(a + 2.0, a)["l1"] == pytest.approx(0.5, abs=1e-6)  # renders are clipped to [0, 1]
    s = summarize([{"psnr": 20, "l1": 0.1, "ssim": 0.5}, {"psnr": 30, "l1": 0.3, "ssim": 0.7}])
    assert s == {"psnr": 25.0, "l1": pytest.approx(0.2), "ssim": pytest.approx(0.6), "num_views": 2}
    assert summarize([])["num_views"] == 0


def test_background_cover_counts_only_the_pixels_the_image_leaves_empty():
    import numpy as np

    from ghsplat_jax.eval.metrics import background_cover

    image_alpha = np.zeros((4, 8), np.float32)
    image_alpha[:, :4] = 1.0  # the object fills the left half
    rendered = np.zeros((4, 8), np.float32)
    rendered[:, :4] = 1.0
    rendered[0, 4:] = 0.5  # one background row half covered
    rendered[1, 4:] = 0.02  # one below the visible threshold
    cover = background_cover(rendered, image_alpha)
    assert cover == {"background_alpha": pytest.approx((0.5 * 4 + 0.02 * 4) / 16), "background_covered": 0.25}
    assert background_cover(rendered, None) == {} and background_cover(rendered, np.ones((4, 8))) == {}
    rows = [{"psnr": 20, "l1": 0.1, "ssim": 0.5, **cover}, {"psnr": 30, "l1": 0.3, "ssim": 0.7, **cover}]
    assert summarize(rows)["background_covered"] == 0.25
    assert "background_alpha" not in summarize(rows[:1] + [{"psnr": 30, "l1": 0.3, "ssim": 0.7}])


def test_experiment_files_parse(tmp_path):
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent / "experiments"
    for path in sorted(root.glob("*.toml")):  # every preset of every file parses
        import tomllib

        for preset in ["full", *tomllib.loads(path.read_text()).get("presets", {})]:
            exp = load_experiment(path, output=tmp_path / path.stem, preset=preset)
            if exp.kind == "train":  # studies (kind stability) list cases, not runs
                assert exp.runs and all(r.config.data for r in exp.runs), (path, preset)
    quick = load_experiment(root / "quick_cpu.toml", output=tmp_path)
    budget = [r for r in quick.runs if r.variant == "budget"]
    assert budget and all(r.config.strategy.name == "budget" and r.config.steps == 300 for r in budget)
    assert {r.config.data for r in load_experiment(root / "table1.toml").runs} == {
        "llff_fern", "nerf_synthetic_lego", "ngp_fox", "lund_door"}
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[[scenes]]\nname = "a"\ndata = "d"\ntrain = { stepz = 3 }\n')
    with pytest.raises(ConfigError, match="bad.toml.*stepz"):
        load_experiment(bad)
    bad.write_text('name = "x"\n')
    with pytest.raises(ConfigError, match="scenes"):
        load_experiment(bad)


def test_presets_lay_over_the_file_and_keep_their_own_folders(tmp_path):
    exp_file = tmp_path / "e.toml"
    exp_file.write_text('''name = "e"
output = "runs/e"
results = "res/e"
[train]
steps = 1000
lr_opacity = 0.04
''' + TWO_SCENES + '''[presets.quick]
train = { steps = 20 }
[[presets.quick.scenes]]
name = "a"
data = "tiny"
''')
    full = load_experiment(exp_file)
    assert [r.config.steps for r in full.runs] == [1000, 1000] and full.preset == "full"
    assert full.output.as_posix() == "runs/e" and full.results.as_posix() == "res/e"
    quick = load_experiment(exp_file, preset="quick")
    assert [(r.scene, r.config.data, r.config.steps) for r in quick.runs] == [("a", "tiny", 20)]
    assert quick.runs[0].config.lr_opacity == 0.04  # [train] keys the preset does not name stay
    assert quick.output.as_posix() == "runs/e_quick" and quick.results.as_posix() == "res/e/quick"
    moved = load_experiment(exp_file, output=tmp_path / "o", preset="quick")
    assert moved.output == moved.results == tmp_path / "o"  # --output keeps tests out of the repo
    with pytest.raises(ConfigError, match="e.toml.*no preset 'slow'.*full, quick"):
        load_experiment(exp_file, preset="slow")
    text = exp_file.read_text()
    exp_file.write_text(text.replace("[presets.quick]\n", "[presets.quick]\nstepz = 3\n"))
    with pytest.raises(ConfigError, match=r"unknown keys \['stepz'\] in \[presets.quick\]"):
        load_experiment(exp_file, preset="quick")
    exp_file.write_text(text + "stepz = 3\n")  # lands in the preset's scene table
    with pytest.raises(ConfigError, match=r"e.toml: unknown keys \['stepz'\] in scene 'a'"):
        load_experiment(exp_file, preset="quick")


def test_pareto_front_and_its_chart(tmp_path):
    # (cost, quality): b is beaten by a (cheaper and better); c ties a's quality at a higher cost
    assert pareto_front([(1.0, 30.0), (2.0, 29.0), (3.0, 30.0), (4.0, 31.0), (0.5, 20.0)]) == [
        True, False, False, True, True]
    rows = [{"scene": "s", "variant": v, "step_seconds": c, "psnr": q}
            for v, c, q in (("default", 1.0, 30.0), ("tile16", 2.0, 29.0), ("box3", 4.0, 31.0))]
    rows.append({"scene": "alone", "variant": "default", "step_seconds": 1.0, "psnr": 20.0})  # one variant: no chart
    made = write_pareto_charts(rows, tmp_path, "t")
    assert [p.name for p in made] == ["pareto_s.png", "pareto.json"]
    front = json.loads(made[1].read_text())["scenes"]["s"]
    assert {v: f["on_front"] for v, f in front.items()} == {"default": True, "tile16": False, "box3": True}
    # a GPU's step time beside a CPU's draws no front: the scene is left out, says why, and the
    # chart an earlier report drew for it goes, so the folder shows no front the JSON disowns
    mixed = [dict(rows[0], device="NVIDIA H200"), dict(rows[1], device="cpu")]
    made = write_pareto_charts(mixed, tmp_path, "t")
    assert [p.name for p in made] == ["pareto.json"]
    assert "different devices (NVIDIA H200, cpu)" in json.loads(made[0].read_text())["scenes"]["s"]["left_out"]
    assert not (tmp_path / "pareto_s.png").exists()


def test_labels_of_coinciding_points_do_not_overlap():
    """Three points on one pixel and one beside them: each label gets its own box, clear of the
    others and of every marker, and inside the axes."""
    anchors = [(100.0, 100.0)] * 3 + [(108.0, 102.0)]
    sizes = [(50.0, 12.0)] * 4
    bounds = (0.0, 0.0, 400.0, 300.0)
    boxes = [label_box(a, s, p) for a, s, p in zip(anchors, sizes, place_labels(anchors, sizes, bounds, marker=5.0))]
    assert all(overlap(a, b) == 0.0 for i, a in enumerate(boxes) for b in boxes[i + 1:])
    assert all(overlap(box, (x - 5, y - 5, x + 5, y + 5)) == 0.0 for box in boxes for x, y in anchors)
    assert all(overlap(box, bounds) == 50.0 * 12.0 for box in boxes)
    # against the axes' edge a label turns inward
    corner, size = (398.0, 298.0), (50.0, 12.0)
    box = label_box(corner, size, place_labels([corner], [size], bounds)[0])
    assert box[2] <= 400.0 and box[3] <= 300.0


def test_an_ablations_near_variants_get_readable_labels():
    """The ablation's variants a few ms and 0.05 dB apart (default, no_lowpass, skip_chunks; box3
    and median_depth): as drawn, no two variant labels overlap."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    points = {"default": (0.075, 27.72), "skip_chunks": (0.072, 27.66), "skip_none": (0.084, 27.77),
              "tile16": (0.093, 28.10), "tile32": (0.209, 27.84), "chunk32": (0.097, 27.83),
              "box3": (0.079, 27.94), "no_lowpass": (0.072, 27.71), "median_depth": (0.077, 27.95),
              "distortion": (0.054, 26.48)}
    fig = pareto_figure(list(points.values()), list(points), pareto_front(list(points.values())), "s", "dB", "t")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()  # places the annotations
    renderer = canvas.get_renderer()
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.texts] == list(points)
    boxes = [Text.get_window_extent(t, renderer) for t in ax.texts]  # the words, not the leader line
    assert not [(ax.texts[i].get_text(), ax.texts[j].get_text()) for i in range(len(boxes))
                for j in range(i + 1, len(boxes)) if boxes[i].overlaps(boxes[j])]


def test_rows_and_charts_name_an_accelerator(tmp_path):
    from ghsplat_jax.experiments.report import run_row
    from ghsplat_jax.train.run_dir import write_metrics

    write_metrics(tmp_path, {"test": {"psnr": 29.4, "l1": 0.02, "ssim": 0.9, "num_views": 8}, "num_gaussians": 5,
                             "train_seconds": 515.0, "device": "NVIDIA H200"}, [])
    row = dict(run_row(tmp_path, "row3_x1", "default"))
    assert row["device"] == "NVIDIA H200"
    cpu = dict(row, scene="row1_x1", device="cpu")
    series = scatter_series([row, cpu], "train_seconds", "psnr")["default"]
    assert series[0]["device"] == "NVIDIA H200" and "device" not in series[1]
    labels = [t.get_text() for t in scatter_figure({"": series}, "s", "dB").axes[0].texts]
    assert labels == ["row3_x1 (NVIDIA H200)", "row1_x1"]


def test_each_row_names_the_machine_and_code_it_trained_with(tmp_path):
    from ghsplat_jax.experiments.report import run_row, write_results
    from ghsplat_jax.train.run_dir import write_metrics

    gpu = {"processor": "x86_64", "cpu_count": 16, "device": "NVIDIA H200"}
    write_metrics(tmp_path / "a", {"test": {"psnr": 29.4, "num_views": 8}, "num_gaussians": 5, "machine": gpu,
                                   "code_revision": "0123456789" * 4}, [])
    write_metrics(tmp_path / "b", {"test": {"psnr": 28.1, "num_views": 8}, "num_gaussians": 5}, [])  # recorded none
    rows = [run_row(tmp_path / s, s, "default") for s in "ab"]
    assert rows[0]["host"] == "x86_64 x16, NVIDIA H200" and rows[1]["host"] is None
    write_results(rows, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "results.json").read_text())
    assert [r["code_revision"] for r in report["rows"]] == ["0123456789" * 4, None]
    assert report["rows"][0]["machine"] == gpu and "machine" in report["report"]  # the row's, and the writer's
    md = (tmp_path / "out" / "results.md").read_text()
    assert "| x86_64 x16, NVIDIA H200 | 0123456 | finished |" in md and "| - | - | finished |" in md
    assert "'-' where a run trained before runs recorded them" in md


def test_a_row_says_how_long_its_kept_model_trained_under_the_normal_prior(tmp_path):
    """A self-stopped run keeps its best check: its geometry is that of the kept step, under the
    normal loss only from normal_from on (none before it, none with the loss off)."""
    from ghsplat_jax.experiments.report import run_row
    from ghsplat_jax.train.run_dir import CONFIG_NAME, write_metrics

    def run(name, config, **metrics):
        write_metrics(tmp_path / name, {"test": {"psnr": 28.0, "num_views": 8}, "num_gaussians": 5, **metrics}, [])
        if config is not None:
            (tmp_path / name / CONFIG_NAME).write_text(config)
        return run_row(tmp_path / name, name, "auto")

    prior = "lambda_normal = 0.05\nnormal_from = 7000\n"
    stopped = {"steps": 8000, "stop": {"stopped_at": 8000, "best_step": 7250}}
    assert (lambda r: (r["kept_step"], r["normal_loss_steps"]))(run("a", prior, **stopped)) == (7250, 250)
    assert run("b", prior, steps=8000, stop={"best_step": 6750})["normal_loss_steps"] == 0
    assert run("c", prior, steps=30000)["normal_loss_steps"] == 23000  # no stop record: the last step is kept
    assert run("d", "lambda_normal = 0.0\nnormal_from = 7000\n", **stopped)["normal_loss_steps"] == 0
    assert run("e", None, **stopped)["normal_loss_steps"] is None  # no config: not known


def test_a_time_axis_draws_one_kind_of_machine(tmp_path):
    rows = [{"scene": "a", "variant": "default", "train_seconds": 515.0, "psnr": 29.4, "num_gaussians": 9,
             "device": "NVIDIA H200"},
            {"scene": "b", "variant": "default", "train_seconds": 7005.0, "psnr": 28.6, "num_gaussians": 9},
            {"scene": "c", "variant": "auto", "train_seconds": 610.0, "psnr": 28.7, "num_gaussians": 5,
             "device": "cpu"}]
    made = {p.name for p in write_charts(rows, tmp_path, "t")}
    assert made == {"psnr_vs_time.png", "psnr_vs_time_nvidia_h200.png", "psnr_vs_count.png"}
    cpu = json.loads((tmp_path / "psnr_vs_time.json").read_text())["series"]
    assert sorted(p["scene"] for points in cpu.values() for p in points) == ["b", "c"]
    gpu = json.loads((tmp_path / "psnr_vs_time_nvidia_h200.json").read_text())
    assert gpu["title"] == "t: runs on NVIDIA H200" and [p["scene"] for p in gpu["series"]["default"]] == ["a"]
    assert gpu["device"] == "NVIDIA H200"
    assert json.loads((tmp_path / "psnr_vs_time.json").read_text())["device"] == "cpu"
    counts = json.loads((tmp_path / "psnr_vs_count.json").read_text())["series"]  # no time: every run
    assert sum(len(points) for points in counts.values()) == 3


def test_a_time_axis_draws_one_kind_of_cpu(tmp_path):
    """Two CPUs are two kinds of machine: the one with most runs (with the runs that recorded no
    machine) in psnr_vs_time.png, the other beside it; a Pareto chart of one scene's runs on both
    is left out."""
    amd, intel = "AMD EPYC x2, cpu", "Intel Xeon x2, cpu"
    row = {"variant": "auto", "psnr": 28.0, "num_gaussians": 9, "device": "cpu", "step_seconds": 0.1}
    rows = [dict(row, scene="a", train_seconds=600.0, host=amd), dict(row, scene="b", train_seconds=500.0, host=amd),
            dict(row, scene="c", train_seconds=700.0),  # no machine recorded
            dict(row, scene="a", variant="auto_seed1", train_seconds=1300.0, host=intel)]
    made = {p.name for p in write_charts(rows, tmp_path, "t")}
    assert made == {"psnr_vs_time.png", "psnr_vs_time_intel_xeon_x2_cpu.png", "psnr_vs_count.png"}
    main = json.loads((tmp_path / "psnr_vs_time.json").read_text())
    assert main["machine"] == amd and sorted(p["scene"] for p in main["series"]["auto"]) == ["a", "b", "c"]
    other = json.loads((tmp_path / "psnr_vs_time_intel_xeon_x2_cpu.json").read_text())
    assert other["title"] == f"t: runs on {intel}" and list(other["series"]) == ["auto_seed1"]
    pareto = json.loads(write_pareto_charts(rows, tmp_path, "t", reference="auto")[-1].read_text())
    assert pareto["scenes"]["a"]["left_out"] == f"its runs ran on different machines ({amd}; {intel})"


def test_median_step_seconds_skips_the_clock_restart_of_a_resume(tmp_path):
    from ghsplat_jax.train.run_dir import STATS_NAME, median_step_seconds

    assert median_step_seconds(tmp_path) is None
    elapsed = [30.0, 30.5, 31.0, 31.7, 12.0, 12.5]  # compile-heavy first step; resumed from an older checkpoint
    (tmp_path / STATS_NAME).write_text("".join(json.dumps({"step": i, "elapsed_s": e}) + "\n"
                                               for i, e in enumerate(elapsed)))
    assert median_step_seconds(tmp_path) == pytest.approx(0.5)


def test_collect_keeps_a_lost_runs_row_from_the_last_report(tmp_path, caplog):
    """A long experiment's runs folder can be lost between sessions while its report survives in
    the repository: collecting again keeps such a run's row from results.json (with a warning),
    takes every run that has its metrics.json from the run, and drops rows of unplanned runs."""
    from ghsplat_jax.experiments.runner import collect

    exp_file = tmp_path / "e.toml"
    exp_file.write_text(f'''name = "e"
output = "{(tmp_path / 'runs').as_posix()}"
results = "{(tmp_path / 'res').as_posix()}"
''' + TWO_SCENES)
    exp = load_experiment(exp_file)
    for r, psnr in zip(exp.runs, (30.0, 27.0)):
        _fake_run(r.out_dir, psnr, 0.02, 1000)
    assert [row["psnr"] for row in collect(exp)[0]] == [30.0, 27.0]
    report = json.loads((exp.results / "results.json").read_text())
    report["rows"].append(dict(report["rows"][0], scene="gone"))  # a scene the file no longer plans
    (exp.results / "results.json").write_text(json.dumps(report))
    (exp.runs[0].out_dir / "metrics.json").unlink()                # run a lost, its report row kept
    (exp.runs[1].out_dir / "metrics.json").write_text((exp.runs[1].out_dir / "metrics.json").read_text()
                                                      .replace("27.0", "27.5"))  # run b re-evaluated
    with caplog.at_level("WARNING", logger="ghsplat.run"):
        rows = collect(exp)[0]
    assert [(row["scene"], row["psnr"]) for row in rows] == [("a", 30.0), ("b", 27.5)]
    assert "a/default: no metrics.json" in caplog.text and "results.json" in caplog.text
    (exp.results / "results.json").write_text("not json")
    with caplog.at_level("WARNING", logger="ghsplat.run"):
        assert [row["scene"] for row in collect(exp)[0]] == ["b"]
    assert "not a results report" in caplog.text
