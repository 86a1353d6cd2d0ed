"""`make test`: the suite as one pytest process per test file, then one summary.

Why not one process: jaxlib 0.10's CPU JIT can leave unwind tables of freed executables
registered with libgcc (Debian 12's libgcc 12 walks every registered table), and a C++
exception thrown later in the same process, which JAX throws for any error raised while
tracing, then segfaults in `_Unwind_Find_FDE`. The one-process suite died that way at its
381st test, in CI and in a fresh clone alike (core dump: libjax_common `__cxa_throw` ->
`_Unwind_RaiseException` -> `_Unwind_Find_FDE`), while each file passes on its own. Short
processes keep stale tables from piling up; the persistent compilation cache keeps the
compiles a file repeats cheap.

Two suites: `--fast` (`make test`) deselects tests marked `slow` (`-m "not slow"`) and does not
start the files whose every test is slow (a module-level `pytestmark = pytest.mark.slow`);
without it (`make test-all`) every test runs. The fast suite also sets GHSPLAT_SUITE=fast for
the files that scale a search down there (the reader fuzzing: fewer examples). `--list` prints
what would run without running it (add `--collect-only -q` instead to see each file's tests).

    python tests/run_suite.py [--fast] [--list] [pytest args...]   # other args go to every file's pytest
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parent
NO_TESTS = 5  # pytest's exit code when a file's tests are all deselected
FAST = ["-m", "not slow"]
# A module-level mark on its own line: every test in the file is slow.
ALL_SLOW = re.compile(r"^pytestmark\s*=\s*(pytest\.mark\.slow|\[\s*pytest\.mark\.slow\s*\])\s*(#.*)?$", re.MULTILINE)


def outcome(code: int) -> str:
    if code < 0:
        return f"killed by {signal.Signals(-code).name}"
    return "passed" if code in (0, NO_TESTS) else f"failed (pytest exit {code})"


def all_slow(path: Path) -> bool:
    """Whether the file marks every test slow (read as text: no import, no JAX)."""
    return bool(ALL_SLOW.search(path.read_text(encoding="utf-8")))


def select(files: list[Path], fast: bool) -> list[Path]:
    """The files a suite starts: all of them, or for the fast suite those with a test that is not slow."""
    return [path for path in files if not (fast and all_slow(path))]


def run(files: list[Path], args: list[str], root: Path, env: dict[str, str] | None = None) -> int:
    """Each file's tests in their own pytest process run in `root` (with `env` added to the
    environment); 0 when every file passed."""
    results, seconds, start = {}, {}, time.monotonic()
    environ = {**os.environ, **(env or {})}
    for path in files:
        name = path.relative_to(root)
        print(f"== {name}", flush=True)
        began = time.monotonic()
        results[name] = subprocess.call([sys.executable, "-m", "pytest", str(name), *args], cwd=root, env=environ)
        seconds[name] = time.monotonic() - began
    bad = {name: outcome(code) for name, code in results.items() if outcome(code) != "passed"}
    print(f"\n== {len(files) - len(bad)} of {len(files)} test files passed in {time.monotonic() - start:.0f} s")
    slowest = sorted(seconds, key=seconds.get, reverse=True)[:5]
    if len(files) > 1:
        print("   slowest: " + ", ".join(f"{name.name} {seconds[name]:.0f} s" for name in slowest))
    for name, what in bad.items():
        print(f"   {name}: {what}")
    return 1 if bad else 0


def main(argv: list[str]) -> int:
    fast, listing = "--fast" in argv, "--list" in argv
    args = [a for a in argv if a not in ("--fast", "--list")]
    everything = sorted(TESTS.glob("test_*.py"))
    files = select(everything, fast)
    args = (FAST if fast else []) + args
    if listing:
        print(f"{'fast' if fast else 'full'} suite: {len(files)} of {len(everything)} test files, "
              f"each as: python -m pytest FILE {' '.join(repr(a) if ' ' in a else a for a in args)}")
        for path in everything:
            print(f"   {path.relative_to(TESTS.parent)}{'' if path in files else '   (all slow: not run)'}")
        return 0
    return run(files, args, TESTS.parent, {"GHSPLAT_SUITE": "fast"} if fast else None)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
