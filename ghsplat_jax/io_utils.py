"""Small I/O helpers shared by every writer: atomic writes (files and folders) and JSON.

One rule for every output: write under a temporary name beside the target, then rename,
so a reader (or a crash) sees the old output or the new one, never half of one.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import shutil
import tempfile
from pathlib import Path


def replace_path(new: str | os.PathLike, target: str | os.PathLike) -> None:
    """Move `new` (a file or a folder) to `target`, replacing whatever is there."""
    new, target = Path(new), Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    if not (target.is_dir() and not target.is_symlink()):
        os.replace(new, target)
        return
    # os.replace cannot replace a non-empty folder: move the old one aside first.
    old = target.with_name(f".{target.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    os.replace(target, old)
    os.replace(new, target)
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path with `path`'s name (so writers that pick a format from the
    suffix, or name files after their folder, behave the same) in a private folder beside
    it; on success it replaces `path` (a file or a folder), on an exception it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        tmp = scratch / path.name
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"{path}: the writer produced no output")
        replace_path(tmp, path)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def remove_scratch(folder: str | os.PathLike) -> list[Path]:
    """Remove what writers killed mid-write (SIGKILL, power loss) left in `folder`: the
    scratch folders of `atomic_path` and the `.NAME.old` folders of `replace_path`. Only for a
    folder no other process is writing into (a run being resumed)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stale = [p for p in folder.iterdir() if p.is_dir() and p.name.startswith(".")
             and (p.name.endswith(".tmp") or p.name.endswith(".old"))]
    for p in stale:
        shutil.rmtree(p, ignore_errors=True)
    return stale


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb"):
    """Open a file for writing that appears at `path` complete (flushed and synced) or not at all."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def json_safe(obj):
    """`obj` as JSON can hold it (write_json refuses NaN): NaN and inf to None, numpy scalars to
    Python numbers, tuples to lists, through dicts and lists."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "dtype") and hasattr(obj, "item") and getattr(obj, "ndim", None) == 0:  # numpy scalar
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    return obj


def write_json(path: str | os.PathLike, obj) -> Path:
    with atomic_write(path, "w") as fh:
        json.dump(obj, fh, indent=2, allow_nan=False)
        fh.write("\n")
    return Path(path)


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    """The records of a JSON-lines log (stats.jsonl, test_curve.jsonl); [] when it does not exist.
    A line cut short (a run stopped mid-write) is skipped."""
    path = Path(path)
    records = []
    for line in path.read_text().splitlines() if path.is_file() else []:
        try:
            records.append(json.loads(line))
        except ValueError:
            continue
    return records


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Write a matplotlib Figure as PNG atomically (a `matplotlib.figure.Figure` needs no
    pyplot and no backend switch: it renders with Agg for PNG)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return Path(path)


def device_name() -> str:
    """The device JAX computes on, as results name it: "cpu", or the accelerator's kind (e.g.
    "NVIDIA H200"), so a report can tell a GPU's training time from a CPU's."""
    import jax

    return str(jax.devices()[0].device_kind)


def machine_info(start_backend: bool = True) -> dict:
    """What a result was measured on: recorded beside every benchmark and experiment report.
    start_backend=False leaves JAX's backend unstarted (no jax_backend / device): for a process
    that only starts others, which must not claim the accelerator."""
    import platform

    import jax

    info = {"platform": platform.platform(), "processor": platform.processor() or _cpu_model() or platform.machine(),
            "cpu_simd": _cpu_simd(), "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__}
    if start_backend:
        info.update(jax_backend=jax.default_backend(), device=device_name(),
                    reference_kernel_s=reference_kernel_seconds())
    return dict(info, load_average=list(os.getloadavg()))


def host_label(machine: dict | None) -> str | None:
    """A machine record in a few words (processor, cores, device): one kind of machine, whose
    times a table may set side by side; None for no record."""
    if not machine:
        return None
    return f"{machine.get('processor') or 'unknown CPU'} x{machine.get('cpu_count')}, {machine.get('device') or 'cpu'}"


def machine_kind(row: dict, among: list[dict] = ()) -> str:
    """The kind of machine a row (a run, or its record in a results file) ran on, whose times may
    be set side by side: its `host` (host_label's words). A row that names none ran before rows
    recorded their machine: it takes the host most rows of its device in `among` name (until then
    this project's CPU rows ran on one host), else its device."""
    if row.get("host"):
        return row["host"]
    device = row.get("device") or "cpu"
    hosts = [r["host"] for r in among if r.get("host") and (r.get("device") or "cpu") == device]
    return max(dict.fromkeys(hosts), key=hosts.count) if hosts else device


def one_machine(rows: list[dict], prefer: str | None = None, among: list[dict] | None = None
                ) -> tuple[str, list[dict]]:
    """The rows whose times may be set side by side, and their kind of machine (machine_kind over
    `among`, the whole report, by default `rows`): those of `prefer` where any ran there (a report's
    main kind, so its tables compare too), else those of the kind most rows ran on (a tie: the first
    row's). Times from two kinds of machine differ by the machines' speed, not by what ran (2x
    between two 2-core hosts of this project)."""
    kinds = [machine_kind(r, rows if among is None else among) for r in rows]
    kind = prefer if prefer in kinds else max(dict.fromkeys(kinds), key=kinds.count) if kinds else "cpu"
    return kind, [r for r, k in zip(rows, kinds) if k == kind]


_REFERENCE_SECONDS: list[float] = []


def reference_kernel_seconds(repeats: int = 7) -> float:
    """Median seconds of a fixed jitted kernel on the default device, measured once per process:
    a yardstick recorded beside step times, so times from different hosts (or one host under
    different loads) can be compared as ratios to it. The kernel mixes what a training step does:
    an exponential, a running product along rows (transmittance), a gather and a small matmul."""
    if _REFERENCE_SECONDS:
        return _REFERENCE_SECONDS[0]
    import time

    import jax
    import jax.numpy as jnp

    @jax.jit
    def kernel(x, idx):
        t = jnp.cumprod(1.0 - 0.5 * jnp.exp(-x * x), axis=1)
        return jnp.sum(t[idx] @ x[:256].T)

    x = jax.random.uniform(jax.random.PRNGKey(0), (2048, 512), jnp.float32)
    idx = jax.random.randint(jax.random.PRNGKey(1), (4096,), 0, 2048)
    kernel(x, idx).block_until_ready()  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        kernel(x, idx).block_until_ready()
        times.append(time.perf_counter() - t0)
    _REFERENCE_SECONDS.append(round(sorted(times)[len(times) // 2], 6))
    return _REFERENCE_SECONDS[0]


@functools.cache
def code_revision() -> str:
    """The package's git revision ("<sha>", "<sha>+dirty" with uncommitted changes under it), or
    "unknown" outside a git checkout: recorded beside results so a number names its code. Read
    once per process: the code a process runs is the code it imported, and a checkout moved under
    a long run (its training at one revision, its metrics written at the next) must not rename it."""
    import subprocess

    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", str(here)], cwd=here,
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + ("+dirty" if dirty else "")


def _cpuinfo_field(name: str) -> str:
    """A field of the first CPU in /proc/cpuinfo ("" where there is none, e.g. off Linux)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return ""
    return next((line.split(":", 1)[1].strip() for line in lines if line.split(":", 1)[0].strip() == name), "")


def _cpu_model() -> str:
    return _cpuinfo_field("model name")  # platform.processor() is empty on Linux


def _cpu_simd() -> list[str]:
    """The vector extensions the CPU offers: numerical libraries pick their code paths by them, so
    float results (SIFT, SfM) can differ between machines with the same packages."""
    flags = set((_cpuinfo_field("flags") or _cpuinfo_field("Features")).split())  # x86 names them flags, Arm Features
    return sorted(flags & {"sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512_vnni", "avx512_bf16",
                           "amx_tile", "asimd", "sve", "sve2"})
