"""Row segments for `ghsplat run` ([prepare]): settings checked with errors naming the file, and a
segment whose SfM is not "ok" is reported and never trained."""

import json

import pytest

from ghsplat_jax.cli import main as ghsplat
from ghsplat_jax.experiments.runner import load_experiment
from ghsplat_jax.experiments.segments import prepare_segments
from ghsplat_jax.train.config import ConfigError

EXPERIMENT = """name = "seg"
output = "{out}/runs"
[prepare]
views = 12
{extra}
[train]
steps = 3
[[scenes]]
name = "row0_x0"
data = "{out}/gh/row0_x0/sfm"
segment = {{ row = 0, end = "{end}" }}
"""


def _write(tmp_path, extra="", end="x0"):
    path = tmp_path / "seg.toml"
    path.write_text(EXPERIMENT.format(out=tmp_path, extra=extra, end=end))
    return path


@pytest.mark.parametrize("extra, end, message", [
    ("viewz = 3", "x0", r"seg.toml: unknown keys \['viewz'\] in \[prepare\]"),
    ("width = 'wide'", "x0", r"seg.toml \[prepare\] width must be an integer"),
    ("sfm = { mapper = 'magic' }", "x0", r"seg.toml \[prepare\] sfm: mapper must be one of"),
    ("sfm = { max_size = 10 }", "x0", r"unknown keys \['max_size'\] in \[prepare\] sfm"),
    ("greenhouse = { layout = { rowz = 2 } }", "x0", r"seg.toml \[prepare\] greenhouse.*layout.rowz"),
    ("", "middle", r"segment must be \{ row = N, end"),
])
def test_prepare_settings_are_checked(tmp_path, extra, end, message):
    with pytest.raises(ConfigError, match=message):
        prepare_segments(load_experiment(_write(tmp_path, extra, end)))


def _made_segment(tmp_path, status):
    sfm = tmp_path / "gh" / "row0_x0" / "sfm"
    (sfm / "sparse" / "0").mkdir(parents=True)
    report = {"status": status, "num_images": 12, "num_registered": 12, "versions": {"pycolmap": "4.2.1"}}
    (sfm / "sfm_report.json").write_text(json.dumps(report))
    return sfm


@pytest.mark.parametrize("status, code", [("ok", 0), ("folded", 1)])
def test_prepare_only_makes_data_and_trains_nothing(tmp_path, capsys, status, code):
    """`--prepare-only` (data made here, trained elsewhere) reports the segments, says which are
    unfit, and never starts a run."""
    _made_segment(tmp_path, status)
    assert ghsplat(["run", str(_write(tmp_path)), "--prepare-only"]) == code
    out, err = capsys.readouterr()
    assert f"| row0_x0 | {status} | 12 | 12 |" in (tmp_path / "runs" / "segments.md").read_text()
    assert "data made; report: " in out
    [row] = json.loads((tmp_path / "runs" / "segments.json").read_text())["segments"]
    assert row["pycolmap"] == "4.2.1"  # which install made the SfM
    assert ("row0_x0: SfM status 'folded'" in err) == (status == "folded")
    assert not (tmp_path / "runs" / "row0_x0").exists()
    assert ghsplat(["run", str(_write(tmp_path)), "--prepare-only", "--report-only"]) == 2


def test_a_folded_segment_is_reported_and_not_trained(tmp_path, capsys):
    sfm = _made_segment(tmp_path, "folded")
    path = _write(tmp_path)
    unusable = prepare_segments(load_experiment(path))
    assert list(unusable) == ["row0_x0"] and "folded" in unusable["row0_x0"]
    assert "| row0_x0 | folded | 12 | 12 |" in (tmp_path / "runs" / "segments.md").read_text()
    assert ghsplat(["run", str(path)]) == 1
    err = capsys.readouterr().err
    assert "row0_x0 failed: SfM status 'folded'" in err and str(sfm / "sfm_report.json") in err
    assert not (tmp_path / "runs" / "row0_x0").exists()  # nothing was trained on it


def test_prepare_only_without_prepare_makes_nothing(tmp_path, capsys):
    path = tmp_path / "plain.toml"
    path.write_text(f'name = "plain"\noutput = "{tmp_path}/runs"\n[[scenes]]\nname = "a"\ndata = "{tmp_path}/a"\n')
    assert ghsplat(["run", str(path), "--prepare-only"]) == 0
    assert "no [prepare] table, so no data to make" in capsys.readouterr().out
    assert not (tmp_path / "runs").exists()


def test_prepare_only_refuses_a_stability_study(capsys):
    assert ghsplat(["run", "experiments/stability.toml", "--prepare-only"]) == 2
    assert "not a stability study" in capsys.readouterr().err


def test_only_prepares_just_the_segments_it_names(tmp_path):
    """`ghsplat run --only row0_x0` makes no other segment's photos or SfM (each costs minutes)."""
    _made_segment(tmp_path, "ok")
    path = _write(tmp_path)
    path.write_text(path.read_text() + '[[scenes]]\nname = "row0_x1"\ndata = "{0}/gh/row0_x1/sfm"\n'
                    'segment = {{ row = 0, end = "x1" }}\n'.format(tmp_path))
    assert prepare_segments(load_experiment(path), {"row0_x0"}) == {}
    assert not (tmp_path / "gh" / "row0_x1").exists()


def test_report_only_writes_a_missing_segments_report_and_makes_nothing(tmp_path):
    """A preset trained one segment at a time (`--only`) never wrote segments.md; `--report-only`
    writes it once every segment exists, and makes no segment that is missing."""
    sfm = _made_segment(tmp_path, "ok")
    report = json.loads((sfm / "sfm_report.json").read_text())
    (sfm / "sfm_report.json").write_text(json.dumps(report | {"machine": {"processor": "AMD EPYC", "cpu_count": 2}}))
    path = _write(tmp_path)
    exp = load_experiment(path)
    assert prepare_segments(exp, make=False) == {}
    assert "| row0_x0 | ok | 12 | 12 |" in (tmp_path / "runs" / "segments.md").read_text()
    [row] = json.loads((tmp_path / "runs" / "segments.json").read_text())["segments"]
    assert row["host"] == "AMD EPYC x2, cpu"  # the machine the SfM ran on, from its own report
    path.write_text(path.read_text() + '[[scenes]]\nname = "row0_x1"\ndata = "{0}/gh/row0_x1/sfm"\n'
                    'segment = {{ row = 0, end = "x1" }}\n'.format(tmp_path))
    (tmp_path / "runs" / "segments.md").unlink()
    prepare_segments(load_experiment(path), make=False)
    assert not (tmp_path / "gh" / "row0_x1").exists()  # nothing made
    assert not (tmp_path / "runs" / "segments.md").exists()  # and no report that leaves a segment out


def _write_model(folder, w2cs):
    """A COLMAP text model of cameras with these world_to_cam poses (no points)."""
    from scipy.spatial.transform import Rotation

    folder.mkdir(parents=True)
    (folder / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n")
    lines = []
    for i, w2c in enumerate(w2cs, start=1):
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        lines += [f"{i} {w} {x} {y} {z} {w2c[0, 3]} {w2c[1, 3]} {w2c[2, 3]} 1 {i:05d}.png", ""]
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text("")


def test_an_older_report_gets_the_similarity_onto_the_exact_cameras(tmp_path):
    """A segment's sfm_report.json from before the accuracy recorded its similarity gets it (and
    the reference folder) when the experiment next reads it: what depth and normal errors need."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from ghsplat_jax.experiments.segments import Segment, _is_done
    from ghsplat_jax.scene.transform import transform_camera

    rng = np.random.default_rng(0)
    truth = []
    for _ in range(6):
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
        truth.append(w2c)
    rot = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    # The model's frame: x_model = R^T (x_true - t) / 3, so x_true = 3 R x_model + t.
    model = [transform_camera(w, 1 / 3, rot.T, -rot.T @ np.array([1.0, 2.0, 0.5]) / 3) for w in truth]
    sfm = tmp_path / "gh" / "row0_x0" / "sfm"
    _write_model(sfm / "sparse" / "0", model)
    _write_model(sfm.parent / "photos" / "sparse" / "0", truth)
    (sfm / "sfm_report.json").write_text(json.dumps({"status": "ok", "accuracy": {"scale": 3.0}}))
    report = _is_done(Segment("row0_x0", 0, "x0", sfm))
    frame = report["accuracy"]["to_reference"]
    assert frame["scale"] == pytest.approx(3.0) and np.allclose(frame["rotation"], rot, atol=1e-6)
    assert np.allclose(frame["translation"], [1.0, 2.0, 0.5], atol=1e-6)
    assert report["accuracy"]["reference"] == "../../../photos/sparse/0"  # from sfm/sparse/0: the tree can move
    assert json.loads((sfm / "sfm_report.json").read_text()) == report  # written back
