"""The notebooks under notebooks/ run top to bottom on the embedded default in quick mode
(GHSPLAT_QUICK=1, CPU), each within its time limit, and are committed without outputs.

Each notebook runs in a fresh Jupyter kernel (nbclient) of this very interpreter, importing this
checkout's package; its files go to a temporary folder. GHSPLAT_NOTEBOOK_TIMEOUT (seconds, default
900) is the limit per notebook, all cells together: a guard against a hang, not a speed target (those
live in benchmarks/). The suite runs two test files at a time, and this project's 2-core hosts differ
2x in speed: beside another file on the slower one (load average 3.8), 02_experiment_charts went
past 300 s.
"""

from __future__ import annotations

import json
import os
import re
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
LIMIT_S = float(os.environ.get("GHSPLAT_NOTEBOOK_TIMEOUT", "900"))
KERNEL = "ghsplat-test-python"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3, f"expected the three walkthroughs in {ROOT / 'notebooks'}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_committed_clean(path):
    """No outputs or execution counts in the repository (small diffs), and the first code cell
    reads GHSPLAT_QUICK."""
    nb = json.loads(path.read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    dirty = [i for i, c in enumerate(code) if c.get("outputs") or c.get("execution_count") is not None]
    assert not dirty, f"{path.name}: code cells {dirty} carry outputs; clear them before committing"
    assert "GHSPLAT_QUICK" in "".join(code[0]["source"]), f"{path.name}: the first code cell must read GHSPLAT_QUICK"


def _kernel_dir(tmp_path: Path) -> Path:
    """A kernel spec that starts this interpreter (not whichever `python3` kernel Jupyter finds)."""
    spec = tmp_path / "jupyter" / "kernels" / KERNEL
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "ghsplat test kernel", "language": "python"}))
    return tmp_path / "jupyter"


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat", reason="notebook tests need nbformat (pip install -e '.[test]')")
    nbclient = pytest.importorskip("nbclient", reason="notebook tests need nbclient (pip install -e '.[test]')")
    pytest.importorskip("ipykernel",
                        reason="notebook tests need a Jupyter kernel: ipykernel (pip install -e '.[test]')")
    from nbclient.exceptions import CellExecutionError, CellTimeoutError, DeadKernelError

    monkeypatch.setenv("GHSPLAT_QUICK", "1")
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    monkeypatch.setenv("GHSPLAT_NOTEBOOK_OUT", str(tmp_path / "out"))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    monkeypatch.setenv("JUPYTER_PATH", str(_kernel_dir(tmp_path)))

    nb = nbformat.read(path, as_version=4)
    deadline = time.monotonic() + LIMIT_S
    client = nbclient.NotebookClient(
        nb, kernel_name=KERNEL, resources={"metadata": {"path": str(path.parent)}},
        timeout_func=lambda cell: max(1, int(deadline - time.monotonic())), startup_timeout=120)
    start = time.monotonic()
    try:
        client.execute()
    except CellTimeoutError:
        pytest.fail(f"{path.name}: not finished within {LIMIT_S:.0f} s in quick mode "
                    f"(load average {os.getloadavg()[0]:.1f})", pytrace=False)
    except (CellExecutionError, DeadKernelError) as exc:
        pytest.fail(f"{path.name} failed:\n{_ANSI.sub('', str(exc))}", pytrace=False)
    print(f"{path.name}: {time.monotonic() - start:.0f} s (load average {os.getloadavg()[0]:.1f})")
