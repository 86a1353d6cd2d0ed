"""Does XLA:CPU run independent loops side by side? One program, two host devices, two threads.

    python benchmarks/profiling/loop_threads.py [--rows 256] [--iterations 2000] [--repeats 7]

The compositor's loop bodies are mostly single-threaded (fusion_profile.py), so a second core
could only help if two loops ran at once. Times, interleaved and as medians of wall and CPU
seconds: one loop of 2n iterations; two independent loops of n in one program; the same two
loops as a `shard_map` over two host devices (a child process with
--xla_force_host_platform_device_count=2, since the flag must be set before JAX starts); and two
calls of the loop of n, each from its own Python thread (one device).
Writes benchmarks/results/loop_threads.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "--child" in sys.argv:
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402

from ghsplat_jax.io_utils import write_json


def body(i, state):
    x, acc = state
    y = jnp.exp(-0.5 * (x * x + i * 1e-3)) * jnp.sin(x) + jnp.cos(0.3 * x)
    return x + 1e-4 * y, acc + jnp.sum(y, axis=-1)


def loop(x, n: int):
    return jax.lax.fori_loop(0, n, body, (x, jnp.zeros_like(x[:, 0])))[1]


def in_two_threads(fn):
    """fn(x) and fn(1.1 x), each called from its own thread: two programs at once."""
    def both(x):
        results = [None, None]
        def call(k, arg):
            results[k] = fn(arg).block_until_ready()
        threads = [threading.Thread(target=call, args=(k, arg)) for k, arg in enumerate((x, 1.1 * x))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return results[0] + results[1]
    return both


def variants(n: int, devices: int) -> dict:
    half = jax.jit(lambda x: loop(x, n))
    out = {"one loop of 2n": (jax.jit(lambda x: loop(x, 2 * n)), 1),
           "two loops of n, one program": (jax.jit(lambda x: loop(x, n) + loop(1.1 * x, n)), 1),
           "two loops of n, two threads": (in_two_threads(half), 1)}
    if devices >= 2:
        try:
            from jax import shard_map
        except ImportError:  # older jax
            from jax.experimental.shard_map import shard_map
        from jax.sharding import Mesh
        from jax.sharding import PartitionSpec as P
        mesh = Mesh(np.array(jax.devices()[:2]), ("d",))
        both = shard_map(lambda xs: loop(xs[0], n)[None], mesh=mesh, in_specs=P("d"), out_specs=P("d"))
        out["two loops of n, two host devices"] = (jax.jit(lambda x2: both(x2).sum(0)), 2)
    return out


def time_all(rows: int, n: int, repeats: int) -> dict:
    x = jnp.linspace(0.1, 1.0, rows * 64).reshape(rows, 64)
    cases = variants(n, len(jax.devices()))
    args = {name: x if copies == 1 else jnp.stack([x, 1.1 * x]) for name, (_, copies) in cases.items()}
    for name, (fn, _) in cases.items():
        fn(args[name]).block_until_ready()
    samples = {name: [] for name in cases}
    for _ in range(repeats):
        for name, (fn, _) in cases.items():
            t0, c0 = time.perf_counter(), time.process_time()
            fn(args[name]).block_until_ready()
            samples[name].append((time.perf_counter() - t0, time.process_time() - c0))
    return {name: dict(seconds=float(np.median([s[0] for s in v])), cpu_seconds=float(np.median([s[1] for s in v])),
                       samples=v) for name, v in samples.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=256, help="plane rows (x 64 columns)")
    ap.add_argument("--iterations", type=int, default=2000, help="n")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(time_all(args.rows, args.iterations, args.repeats)))
        return 0
    cmd = [sys.executable, __file__, "--child", "--rows", str(args.rows), "--iterations", str(args.iterations),
           "--repeats", str(args.repeats)]
    rows = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])
    base = rows["one loop of 2n"]["seconds"]
    for row in rows.values():
        row["speedup"] = base / row["seconds"]
    result = dict(rows=rows, plane=[args.rows, 64], iterations=args.iterations, machine=machine_record())
    write_json(RESULTS / "loop_threads.json", result)
    print(json.dumps({k: {m: round(v[m], 3) for m in ("seconds", "cpu_seconds", "speedup")} for k, v in rows.items()},
                     indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
