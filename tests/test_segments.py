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
