"""`make test`: the suite as one pytest process per test file, then one summary.

Why not one process: jaxlib 0.10's CPU JIT can leave unwind tables of freed executables
registered with libgcc (Debian 12's libgcc 12 walks every registered table), and a C++
exception thrown later in the same process, which JAX throws for any error raised while
tracing, then segfaults in `_Unwind_Find_FDE`. The one-process suite died that way at its
381st test, in CI and in a fresh clone alike (core dump: libjax_common `__cxa_throw` ->
`_Unwind_RaiseException` -> `_Unwind_Find_FDE`), while each file passes on its own. Short
processes keep stale tables from piling up; the persistent compilation cache keeps the
compiles a file repeats cheap.

    python tests/run_suite.py [pytest args...]   # args go to every file's pytest
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parent
NO_TESTS = 5  # pytest's exit code when a file's tests are all deselected


def outcome(code: int) -> str:
    if code < 0:
        return f"killed by {signal.Signals(-code).name}"
    return "passed" if code in (0, NO_TESTS) else f"failed (pytest exit {code})"


def run(files: list[Path], args: list[str], root: Path) -> int:
    """Each file's tests in their own pytest process run in `root`; 0 when every file passed."""
    results, start = {}, time.monotonic()
    for path in files:
        name = path.relative_to(root)
        print(f"== {name}", flush=True)
        results[name] = subprocess.call([sys.executable, "-m", "pytest", str(name), *args], cwd=root)
    bad = {name: outcome(code) for name, code in results.items() if outcome(code) != "passed"}
    print(f"\n== {len(files) - len(bad)} of {len(files)} test files passed in {time.monotonic() - start:.0f} s")
    for name, what in bad.items():
        print(f"   {name}: {what}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(run(sorted(TESTS.glob("test_*.py")), sys.argv[1:], TESTS.parent))
