"""What every benchmark records, in one place: where its results go (RESULTS, benchmarks/results/)
and what it ran on (machine_record: ghsplat_jax.io_utils.machine_info plus what the benchmark
adds). The scripts live in benchmarks/KIND/ and import this module (and each other, as
`speed.sim_speed`, ...) with benchmarks/ first on sys.path:

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/
    from record import RESULTS, machine_record  # noqa: E402
"""

from __future__ import annotations

import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parent
ROOT = BENCHMARKS.parent        # the source checkout
RESULTS = BENCHMARKS / "results"

if str(ROOT) not in sys.path:  # the checkout's package, also when it is not installed
    sys.path.insert(1, str(ROOT))

from ghsplat_jax.io_utils import machine_info  # noqa: E402


def machine_record(start_backend: bool = True, **extra) -> dict:
    """machine_info() (platform, processor and SIMD, cores, Python, JAX and its device, load
    average) with the benchmark's own facts in `extra` (e.g. the load average when it started).
    start_backend=False: a process that only starts others leaves the accelerator to them."""
    return {**machine_info(start_backend), **extra}
