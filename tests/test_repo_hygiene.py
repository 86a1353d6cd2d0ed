"""Repository hygiene, without importing JAX: the README stays a short user's guide, the licence
the package declares ships with it, and no development-log labels (a numbered work-period
marker such as "stop" followed by a number) creep into tracked text files; results and comments
say what happened, with a date or a commit where it matters."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README_MAX_LINES = 150

# The word, singular or plural, then a number (after a space, hyphen or underscore, or none),
# and the phrase "at" + the word. The examples below spell the word as WORD so that this file
# does not trip its own check.
WORD = "st" + "op"
HISTORY_LABEL = re.compile(r"(?<![a-z])stops?[ _-]?\d+|\bat stop\b", re.IGNORECASE)
SKIP_DIRS = {".git", ".venv", "node_modules", "__pycache__", ".pytest_cache", ".mypy_cache",
             ".ipynb_checkpoints", "build", "dist", "runs", "demo_out"}


def tracked_files() -> list[Path]:
    """`git ls-files` when this is a git checkout, else every file under the root."""
    if shutil.which("git") and (ROOT / ".git").exists():
        result = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=False)
        if result.returncode == 0:
            return [ROOT / name for name in result.stdout.decode().split("\0") if name]
    files = []
    for folder, dirs, names in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info")]
        files += [Path(folder) / n for n in names]
    return files


def text_of(path: Path) -> str | None:
    """The file's text, or None for a binary (a NUL byte, or not UTF-8) or missing file."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def test_no_history_labels_in_tracked_text_files():
    hits = []
    for path in tracked_files():
        text = text_of(path)
        if text is None:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            match = HISTORY_LABEL.search(line)
            if match:
                start = max(0, match.start() - 40)
                hits.append(f"{path.relative_to(ROOT)}:{number}: ...{line[start:match.end() + 40]}...")
    assert not hits, ("development-log labels in tracked files; say what happened instead "
                      "(a date, a commit, 'on an earlier host'):\n" + "\n".join(hits[:50]))


def test_the_pattern_catches_the_labels_it_is_meant_for():
    for bad in ("at WORD 46", "WORDs 42-45", "WORD-46", "WORD 34's code", "WORD 35 tried".capitalize(),
                "window_WORD40", "measured at WORD."):
        bad = bad.replace("WORD", WORD).replace("Word", WORD.capitalize())
        assert HISTORY_LABEL.search(bad), bad
    for fine in ("stopped at step 21,438", "non-stop", "the stop rule", "stop_gradient(x)", "stops early",
                 "a bus stop", "stopping at 30,000 steps"):
        assert not HISTORY_LABEL.search(fine), fine


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): move details to docs/")


def test_license_exists():
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "Apache License" in text and "Version 2.0" in text


def test_make_test_is_the_fast_suite_and_ci_runs_everything():
    """`make test` runs ruff, mypy and the tests not marked slow; `make test-all` (CI) every test."""
    make = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert re.search(r"^lint: .*\n\t\$\(BIN\)/ruff check \.\n\t\$\(BIN\)/mypy$", make, re.MULTILINE)
    assert re.search(r"^test: lint\n\t\$\(BIN\)/python tests/run_suite.py --fast$", make, re.MULTILINE)
    assert re.search(r"^test-all: lint\n\t\$\(BIN\)/python tests/run_suite.py$", make, re.MULTILINE)
    assert re.search(r"^make test-all$", (ROOT / ".ci" / "run").read_text(encoding="utf-8"), re.MULTILINE)
