"""`make test`: the suite as one pytest process per test file, a few at a time, then one summary.

Why not one process: jaxlib 0.10's CPU JIT can leave unwind tables of freed executables
registered with libgcc (Debian 12's libgcc 12 walks every registered table), and a C++
exception thrown later in the same process, which JAX throws for any error raised while
tracing, then segfaults in `_Unwind_Find_FDE`. The one-process suite died that way at its
381st test, in CI and in a fresh clone alike (core dump: libjax_common `__cxa_throw` ->
`_Unwind_RaiseException` -> `_Unwind_Find_FDE`), while each file passes on its own. Short
processes keep stale tables from piling up; the persistent compilation cache keeps the
compiles a file repeats cheap.

Files run `--jobs N` at a time (default 2: most of a file's time is single-threaded XLA
compiles and small shapes, so two processes keep 2 cores busy), longest first by the seconds
each took last time (tests/suite_times.json, rewritten after a complete run; files it does not
know start first). Each file's output is printed in one piece when it ends.

Two suites: `--fast` (`make test`) deselects tests marked `slow` (`-m "not slow"`) and does not
start the files whose every test is slow (a module-level `pytestmark = pytest.mark.slow`);
without it (`make test-all`) every test runs. The fast suite also sets GHSPLAT_SUITE=fast for
the files that scale a search down there (the reader fuzzing: fewer examples). `--list` prints
what would run without running it (add `--collect-only -q` instead to see each file's tests).

    python tests/run_suite.py [--fast] [--list] [--jobs N] [pytest args...]   # other args go to every file's pytest
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO

TESTS = Path(__file__).resolve().parent
TIMES = TESTS / "suite_times.json"
NO_TESTS = 5  # pytest's exit code when a file's tests are all deselected
FAST = ["-m", "not slow"]
JOBS = 2
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


def plugins(path: Path, args: list[str]) -> list[str]:
    """Plugin switches for the file's pytest: Hypothesis's plugin imports all of Hypothesis at start-up (about
    1 s of CPU a process), so only the files that mention it load it (all do when an argument is one of its
    `--hypothesis-...` options)."""
    if "hypothesis" in path.read_text(encoding="utf-8") or any(a.startswith("--hypothesis") for a in args):
        return []
    return ["-p", "no:hypothesispytest"]


def order(files: list[Path], seconds: dict[str, float]) -> list[Path]:
    """Longest first by the recorded seconds (keyed by file name); files without a record first of all,
    since a new file may well be long. Ties keep the given order."""
    return sorted(files, key=lambda path: -seconds.get(path.name, float("inf")))


def read_times(path: Path, suite: str) -> dict[str, float]:
    """The seconds each file took in the last complete run of `suite` ("fast" or "all"); {} when unknown."""
    try:
        table = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    times = table.get(suite, {}) if isinstance(table, dict) else {}
    if not isinstance(times, dict):
        return {}
    return {str(k): float(v) for k, v in times.items() if isinstance(v, (int, float))}


def write_times(path: Path, suite: str, seconds: dict[str, float], keep: set[str]) -> None:
    """Record `seconds` for `suite`, dropping files not in `keep`. A recorded time only changes when the
    new one differs by more than a quarter (and 2 s), so ordinary jitter leaves the file as it is; the
    file is replaced whole (temporary file, then rename) so an interrupted write never leaves half a table."""
    try:
        table = json.loads(path.read_text(encoding="utf-8"))
        table = table if isinstance(table, dict) else {}
    except (OSError, ValueError):
        table = {}
    old = read_times(path, suite)
    new = {name: s for name, s in old.items() if name in keep}
    for name, s in seconds.items():
        if name not in new or abs(s - new[name]) > max(2.0, 0.25 * new[name]):
            new[name] = round(s, 1)
    if new == old:
        return
    table[suite] = dict(sorted(new.items()))
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(table, f, indent=1, sort_keys=True)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def run(files: list[Path], args: list[str], root: Path, env: dict[str, str] | None = None, jobs: int = 1,
        times: Path | None = None, suite: str = "all", record: bool = True) -> int:
    """Each file's tests in their own pytest process run in `root` (with `env` added to the
    environment), `jobs` at a time, longest first by `suite`'s record in `times`, which a run that
    completes then updates when `record`; 0 when every file passed."""
    environ = {**os.environ, **(env or {})}
    queue = order(files, read_times(times, suite)) if times else list(files)
    results: dict[Path, int] = {}
    seconds: dict[Path, float] = {}
    running: dict[Path, tuple[subprocess.Popen[bytes], IO[bytes], float]] = {}
    start = time.monotonic()
    try:
        while queue or running:
            while queue and len(running) < max(1, jobs):
                path = queue.pop(0)
                name = path.relative_to(root)
                log: IO[bytes] = tempfile.TemporaryFile()
                command = [sys.executable, "-m", "pytest", str(name), *plugins(path, args), *args]
                proc = subprocess.Popen(command, cwd=root, env=environ, stdout=log, stderr=subprocess.STDOUT)
                running[name] = (proc, log, time.monotonic())
            for name, (proc, log, began) in list(running.items()):
                code = proc.poll()
                if code is None:
                    continue
                del running[name]
                results[name], seconds[name] = code, time.monotonic() - began
                log.seek(0)
                text = log.read().decode("utf-8", "replace")
                log.close()
                print(f"== {name}: {outcome(code)} in {seconds[name]:.0f} s ({len(results)} of {len(files)})")
                print(text, end="" if text.endswith("\n") or not text else "\n", flush=True)
            if running:
                time.sleep(0.1)
    finally:  # Ctrl-C (or any error here): no test process outlives the runner
        for proc, _, _ in running.values():
            proc.kill()
        for proc, out, _ in running.values():
            proc.wait()
            out.close()
    bad = {name: outcome(code) for name, code in results.items() if outcome(code) != "passed"}
    print(f"\n== {len(files) - len(bad)} of {len(files)} test files passed in {time.monotonic() - start:.0f} s"
          f" ({max(1, jobs)} at a time)")
    slowest = sorted(seconds, key=lambda name: seconds[name], reverse=True)[:5]
    if len(files) > 1:
        print("   slowest: " + ", ".join(f"{name.name} {seconds[name]:.0f} s" for name in slowest))
    for name, what in bad.items():
        print(f"   {name}: {what}")
    if times and record:
        passed = {name.name: s for name, s in seconds.items() if outcome(results[name]) == "passed"}
        write_times(times, suite, passed, {path.name for path in files})
    return 1 if bad else 0


def jobs_option(argv: list[str]) -> tuple[int, list[str]]:
    """`--jobs N` / `--jobs=N` / `-j N` out of argv: (N, the other arguments)."""
    jobs, rest, i = JOBS, [], 0
    while i < len(argv):
        a = argv[i]
        if a in ("--jobs", "-j") and i + 1 < len(argv):
            jobs, i = int(argv[i + 1]), i + 2
            continue
        if a.startswith("--jobs="):
            jobs = int(a.split("=", 1)[1])
        else:
            rest.append(a)
        i += 1
    if jobs < 1:
        raise SystemExit(f"--jobs must be at least 1, not {jobs}")
    return jobs, rest


def interrupt(signum: int, frame: object) -> None:
    """SIGTERM handler: stop as Ctrl-C does, so the finally block in run() ends the test processes too."""
    raise KeyboardInterrupt


def main(argv: list[str]) -> int:
    fast, listing = "--fast" in argv, "--list" in argv
    jobs, args = jobs_option([a for a in argv if a not in ("--fast", "--list")])
    everything = sorted(TESTS.glob("test_*.py"))
    files = select(everything, fast)
    suite = "fast" if fast else "all"
    # Extra pytest arguments (-k, -x, a marker...) change what a file runs: such a run is not recorded.
    record = not args
    args = (FAST if fast else []) + args
    if listing:
        print(f"{'fast' if fast else 'full'} suite: {len(files)} of {len(everything)} test files, {jobs} at a time, "
              f"each as: python -m pytest FILE {' '.join(repr(a) if ' ' in a else a for a in args)}")
        for path in order(files, read_times(TIMES, suite)) + [p for p in everything if p not in files]:
            print(f"   {path.relative_to(TESTS.parent)}{'' if path in files else '   (all slow: not run)'}")
        return 0
    signal.signal(signal.SIGTERM, interrupt)
    try:
        return run(files, args, TESTS.parent, {"GHSPLAT_SUITE": "fast"} if fast else None, jobs=jobs,
                   times=TIMES, suite=suite, record=record)
    except KeyboardInterrupt:
        print("\n== interrupted: every test process stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
