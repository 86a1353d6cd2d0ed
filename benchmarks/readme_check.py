"""`--check` for the scripts that generate a results README: compare the committed text with the
generated one (standard library only, so a check imports neither JAX nor the package)."""

from __future__ import annotations

import difflib
import sys
from pathlib import Path


def text_diff(path: Path, want: str) -> str:
    """'' when `path` holds `want`, else a unified diff (committed -> generated)."""
    have = path.read_text() if path.is_file() else ""
    if want == have:
        return ""
    return "".join(difflib.unified_diff(have.splitlines(True), want.splitlines(True),
                                        f"{path} (committed)", f"{path} (generated)"))


def report(path: Path, diff: str, hint: str) -> int:
    """Print the check's outcome; the exit code (1 when the README differs)."""
    if diff:
        sys.stdout.write(diff)
        print(f"\n{path} differs from {hint}", file=sys.stderr)
        return 1
    print(f"{path}: up to date")
    return 0


def write_or_check(readme: Path, text: str, check: bool, script: str) -> int:
    """A README script's last step: with `check`, compare (exit code 1 on a difference); else
    write `text` atomically (the package's writer, imported only here)."""
    if check:
        return report(readme, text_diff(readme, text), f"what {script} generates; run it without --check")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: ghsplat_jax
    from ghsplat_jax.io_utils import atomic_write

    with atomic_write(readme, "w") as fh:
        fh.write(text)
    print(f"wrote {readme}")
    return 0
