"""The examples in the documentation run. Every ```python block of README.md and docs/*.md
whose first line is `# doctest: run` is executed, in a fresh namespace and a temporary working
directory (an example may write files). Mark an example that way only once it runs against the
current code, on small shapes: each should take seconds on a CPU, compiles included."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MARK = "# doctest: run"
FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL)


def documents() -> list[Path]:
    return [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))


def runnable_blocks() -> list[tuple[str, str]]:
    """(id, code) for every marked block: id is FILE:LINE of the block's fence."""
    blocks = []
    for doc in documents():
        text = doc.read_text(encoding="utf-8")
        for match in FENCE.finditer(text):
            code = match.group(1)
            if code.lstrip().startswith(MARK):
                line = text.count("\n", 0, match.start()) + 1
                blocks.append((f"{doc.relative_to(ROOT)}:{line}", code))
    return blocks


BLOCKS = runnable_blocks()


def test_there_are_runnable_examples():
    assert any(name.startswith("README.md") for name, _ in BLOCKS), "README.md's Python example is not marked"


# Each example compiles its own renders: minutes in all, so `make test-all` runs them.
@pytest.mark.slow
@pytest.mark.parametrize("code", [code for _, code in BLOCKS], ids=[name for name, _ in BLOCKS])
def test_example_runs(code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "<doc example>", "exec"), {"__name__": "__doc_example__"})
