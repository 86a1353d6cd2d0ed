"""Per-op profile of a simulated camera frame, or of a training step, on XLA:CPU: where the thread time goes.

Every compiled op (fusion, dot, sort, scatter) of the camera's program is timed with
jax.profiler over a few frames and mapped to the source lines it came from (the compiled HLO's
stack-frame metadata). Ops inside the compositor's loop run once per batch; the rest once per
frame. The same trace says how many ops ran at once (not how many cores: see `busy_threads`).
This rasterizer's speed depends on XLA:CPU's fusion choices, so a change in a JAX upgrade shows
up here first.

    JAX_PLATFORMS=cpu python benchmarks/profiling/fusion_profile.py --surfels 100000 --frames 3
    JAX_PLATFORMS=cpu python benchmarks/profiling/fusion_profile.py --train-run RUN [--label NAME]

Writes benchmarks/results/fusion_profile.json. CPU only (it reads XLA:CPU's thread names).
With `--train-run` (a run folder with config.toml and checkpoint.npz) it profiles real training
steps from that checkpoint instead and adds a window to fusion_profile_step.json: thread time
in the compositor's forward loop, its backward loop and the rest of the step (by source file),
the loop iterations, the nanoseconds of thread time per evaluated pair-pixel in each pass beside
the machine's fused exp rate measured in the same process, and how long one or more ops ran at
once. Each of its top ops also lists the JAX operations it fuses (`jax_ops`, from the HLO's
op_name metadata): the compositor's custom backward keeps only its call's source line.
`--one-core` pins the process to one core, so two windows say what the other cores buy.
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "--one-core" in sys.argv:  # before JAX starts its thread pools, which inherit the affinity
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402
from speed.sim_speed import greenhouse_surfels  # noqa: E402

from ghsplat_jax.io_utils import write_json

DEFAULT_OUT = str(RESULTS / "fusion_profile.json")
TOP_WRITTEN = 40  # ops written per profile (by time)
# XLA:CPU runs compiled ops on its intra-op pool, and small programs inline on the client's thread.
OP_THREADS = ("tf_XLAEigen", "tf_XLAPjRtCpuClient")


def _is_op(name: str) -> bool:
    """Compiled ops are named by HLO (fusion.3, sort.0); the runtime's own events have C++ names."""
    return "::" not in name and "Thunk" not in name and not name.startswith("end: ")


def op_events(trace_dir: str) -> list[tuple[int, int, str, str]]:
    """(start ns, end ns, thread, op name) of every compiled op in a jax.profiler trace."""
    files = sorted(glob.glob(f"{trace_dir}/**/*.xplane.pb", recursive=True))
    if not files:
        raise FileNotFoundError(f"no profiler trace under {trace_dir}")
    data = jax.profiler.ProfileData.from_file(files[-1])
    return [(e.start_ns, e.start_ns + e.duration_ns, line.name, e.name)
            for plane in data.planes for line in plane.lines if line.name.startswith(OP_THREADS)
            for e in line.events if _is_op(e.name)]


def busy_threads(events) -> dict:
    """Milliseconds of the traced span with no, one and two or more compiled ops running at once.
    A fusion that XLA splits over its thread pool (outer_dimension_partitions) is one event, so
    this counts concurrent ops, not busy cores: an elementwise loop that ran 1.9x faster on two
    cores than on one still shows a single op running. Compare `--one-core` runs for that."""
    edges = sorted([(s, 1) for s, _, _, _ in events] + [(e, -1) for _, e, _, _ in events])
    busy, running, last = [0, 0, 0], 0, edges[0][0] if edges else 0
    for t, step in edges:
        busy[min(running, 2)] += t - last
        running, last = running + step, t
    return dict(idle_ms=busy[0] / 1e6, one_busy_ms=busy[1] / 1e6, two_or_more_busy_ms=busy[2] / 1e6)


def source_of(hlo: str) -> dict[str, list[str]]:
    """{op name: ["file:line function", ...]} from the compiled HLO text's stack-frame tables,
    the lines most of the op's instructions come from first; empty where this JAX writes them
    differently."""
    try:
        between = lambda a, b: hlo.split(a, 1)[1].split(b, 1)[0]
        files = dict(re.findall(r'^(\d+) "(.*)"$', between("FileNames", "FunctionNames"), re.M))
        funcs = dict(re.findall(r'^(\d+) "(.*)"$', between("FunctionNames", "FileLocations"), re.M))
        locs = {m[0]: f"{Path(files[m[1]]).name}:{m[3]} {funcs[m[2]]}" for m in re.findall(
            r"^(\d+) \{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)",
            between("FileLocations", "StackFrames"), re.M)}
        frames = dict(re.findall(r"^(\d+) \{file_location_id=(\d+)", between("StackFrames", "\n\n"), re.M))
    except (IndexError, KeyError):
        return {}
    out = {}
    for name, text in _op_texts(hlo).items():
        ids = re.findall(r"stack_frame_id=(\d+)", text)
        counts = collections.Counter(locs[frames[i]] for i in ids if frames.get(i) in locs)
        out[name] = [loc for loc, _ in counts.most_common()]  # the lines most of the op comes from first
    return out


def _op_texts(hlo: str) -> dict[str, str]:
    """{op name: its instruction's line, or for a fusion the body of the computation it calls}."""
    bodies = dict(re.findall(r"\n%([\w.\-]+) [^\n]*\{\n(.*?)\n\}", hlo, re.S))
    out = {}
    for line in hlo.splitlines():
        m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = ", line)
        if m:
            call = re.search(r"calls=%([\w.\-]+)", line)
            out[m.group(1)] = bodies.get(call.group(1), "") if call else line
    return out


def jax_ops_of(hlo: str) -> dict[str, list[str]]:
    """{op name: [JAX operation, ...]} from the op_name metadata of the instructions an op fuses,
    the most frequent first, each the last two parts of its name path (for example
    "kbp,bcp->kbc/dot_general"). Where a custom VJP's backward keeps only the call's source line,
    these still tell its ops apart."""
    out = {}
    for name, text in _op_texts(hlo).items():
        counts = collections.Counter("/".join(n.split("/")[-2:]) for n in re.findall(r'op_name="([^"]*)"', text))
        out[name] = [op for op, _ in counts.most_common()]
    return out


def profile_camera(surfels: int, width: int, height: int, frames: int) -> dict:
    from ghsplat_jax.sim import frames as frames_mod
    from ghsplat_jax.sim import robot as robot_mod
    from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer

    s = jax.device_put(greenhouse_surfels(surfels))
    r = robot_mod.Robot()
    cam = CameraModel.from_fov(r.optical_frame, width, height, 70.0)
    renderer = CameraRenderer()
    poses = [r.map_from_optical(-1.0 + 0.05 * i, 0.8, 0.0) for i in range(frames + 1)]
    renderer.render(s, cam, poses[0])  # compile
    walls = []
    for pose in poses[1:]:
        t = time.perf_counter()
        renderer.render(s, cam, pose)
        walls.append(time.perf_counter() - t)
    with tempfile.TemporaryDirectory() as trace_dir:
        with jax.profiler.trace(trace_dir):
            for pose in poses[1:]:
                renderer.render(s, cam, pose)
        events = op_events(trace_dir)
    fn = renderer.program(width, height)
    Ks = cam.matrix[None].astype(np.float32)
    w2cs = frames_mod.world_to_cam(poses[0])[None].astype(np.float32)
    sources = source_of(fn.lower(s, Ks, w2cs).compile().as_text())

    ms, calls = collections.Counter(), collections.Counter()
    for start, end, _, name in events:
        ms[name] += (end - start) / 1e6 / frames
        calls[name] += 1 / frames
    ops = [dict(op=name, ms_per_frame=round(ms[name], 3), calls_per_frame=round(calls[name], 1),
                in_loop=calls[name] > 5, source=sources.get(name, [])[:3]) for name, _ in ms.most_common()]
    return dict(surfels=surfels, image=[width, height], frames=frames, frame_wall_s=float(np.median(walls)),
                thread_ms_per_frame=sum(ms.values()),
                loop_thread_ms_per_frame=sum(o["ms_per_frame"] for o in ops if o["in_loop"]),
                busy_per_frame={k: v / frames for k, v in busy_threads(events).items()}, ops=ops)


def _loop_bodies(hlo: str) -> dict[str, str]:
    """{body computation: "forward" or "backward"} of the compositor's while loops in a compiled
    training step (the backward is the one JAX emits under transpose())."""
    out = {}
    for line in hlo.splitlines():
        m = re.search(r"while\(.*body=%([\w.\-]+).*op_name=\"([^\"]*)\"", line)
        if m and m.group(2).endswith("/while"):
            out[m.group(1)] = "backward" if "transpose(" in m.group(2) else "forward"
    return out


def _owners(hlo: str) -> dict[str, str]:
    """{instruction name: the computation it sits in}."""
    owner, current = {}, None
    for line in hlo.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if head and not line.startswith(" "):
            current = head.group(1)
            continue
        m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = ", line)
        if m and current:
            owner[m.group(1)] = current
    return owner


def profile_training_step(run_dir: Path, steps: int) -> dict:
    """Thread time of real training steps from a run's checkpoint, split by compositor loop."""
    import jax.numpy as jnp
    from speed.raster_speed import exp_rate
    from speed.train_speed import compiled_session

    from ghsplat_jax import host_memory
    from ghsplat_jax.train.config import load_config
    from ghsplat_jax.train.run_dir import load_training_data
    from ghsplat_jax.train.trainer import step_raster_config, view_order

    host_memory.reuse_freed_memory()  # as `ghsplat train` runs
    # The step as one program, whose compiled text maps every op to its loop (the parted step's
    # programs would each need their own map).
    config = load_config(run_dir / "config.toml").replace(step_threads=1)
    session = compiled_session(config, load_training_data(config), run_dir / "checkpoint.npz")
    state0, step0 = session.state, int(session.state.step)

    def run(k):
        session.state = state0
        t, c = time.perf_counter(), time.process_time()
        metrics = session.step(step0 + k)
        jax.block_until_ready(session.state.params.means)
        return time.perf_counter() - t, time.process_time() - c, metrics

    for k in range(steps):  # pair capacities settle (a grown buffer recompiles once)
        run(k)
    timed = [run(k) for k in range(steps)]
    with tempfile.TemporaryDirectory() as trace_dir:
        with jax.profiler.trace(trace_dir):
            for k in range(steps):
                run(k)
        events = op_events(trace_dir)
    rcfg = step_raster_config(config, session.pair_capacity, step0)  # the program the traced steps ran
    v = view_order(config.seed, step0, session.images.shape[0])
    hlo = session.step_fn.lower(state0, session.images[v], session.Ks[v], session.w2cs[v], jnp.float32(1e-4), rcfg,
                                session.width, session.height).compile().as_text()
    bodies, owner, sources, jax_ops = _loop_bodies(hlo), _owners(hlo), source_of(hlo), jax_ops_of(hlo)

    op_ms, op_calls, by_file = collections.Counter(), collections.Counter(), collections.Counter()
    for start, end, _, name in events:
        key = (bodies.get(owner.get(name), "rest of the step" if name in owner else "unmatched"), name)
        op_ms[key] += (end - start) / 1e6 / steps
        op_calls[key] += 1 / steps
        if key[0] == "rest of the step":
            by_file[(sources.get(name) or ["(no source)"])[0].split(":")[0]] += (end - start) / 1e6 / steps
    region_ms = collections.Counter()
    for (region, _), t in op_ms.items():
        region_ms[region] += t
    # Every op of a loop body runs once per iteration: the most frequent one counts them.
    iterations = {r: max((c for (region, _), c in op_calls.items() if region == r), default=0.0)
                  for r in ("forward", "backward")}
    per_iteration = rcfg.batch_chunks * rcfg.chunk_size * rcfg.tile_size ** 2  # pair-pixels evaluated
    wall, cpu, metrics = zip(*timed)
    rate = exp_rate()
    return dict(run=str(run_dir), step=step0, surfels=int(jnp.sum(state0.active)), pool=state0.capacity,
                image=[session.width, session.height], steps=steps,
                step_wall_s=float(np.median(wall)), step_cpu_s=float(np.median(cpu)),
                candidate_pairs=float(np.median([m["num_pairs"] for m in metrics])),
                thread_ms_per_step={k: round(v, 2) for k, v in region_ms.most_common()},
                loop_iterations_per_step=iterations, pair_pixels_per_iteration=per_iteration,
                thread_ns_per_pair_pixel={r: region_ms[r] * 1e6 / max(n * per_iteration, 1)
                                          for r, n in iterations.items()},
                exp_rate_per_s=rate, exp_ns_per_evaluation=1e9 / rate,
                rest_of_step_ms_by_file={k: round(v, 2) for k, v in by_file.most_common()},
                ops_at_once_per_step={k: v / steps for k, v in busy_threads(events).items()},
                top_ops=[dict(region=region, op=name, ms_per_step=round(t, 3),
                              calls_per_step=round(op_calls[region, name], 1), source=sources.get(name, [])[:3],
                              jax_ops=jax_ops.get(name, [])[:3])
                         for (region, name), t in op_ms.most_common(TOP_WRITTEN)])


def main_step(args) -> int:
    result = profile_training_step(Path(args.train_run), args.steps)
    result.update(machine=machine_record(), cores_used=len(os.sched_getaffinity(0)))
    out = Path(args.out).with_name("fusion_profile_step.json") if args.out == DEFAULT_OUT else Path(args.out)
    windows = json.loads(out.read_text()) if out.exists() else {}
    windows[args.label or f"{Path(args.train_run).name} @ step {result['step']}"] = result
    write_json(out, windows)
    t = result["thread_ms_per_step"]
    print(f"step {result['step_wall_s'] * 1e3:.0f} ms wall, {result['step_cpu_s'] * 1e3:.0f} ms CPU; thread ms: "
          + ", ".join(f"{k} {v:.0f}" for k, v in t.items()))
    print("loop iterations", result["loop_iterations_per_step"], "ns per pair-pixel",
          {k: round(v, 2) for k, v in result["thread_ns_per_pair_pixel"].items()},
          f"(a fused exp: {result['exp_ns_per_evaluation']:.2f} ns)")
    busy = result["ops_at_once_per_step"]
    print(f"ops running at once: none {busy['idle_ms']:.0f}, one {busy['one_busy_ms']:.0f}, two+ "
          f"{busy['two_or_more_busy_ms']:.0f} ms")
    print("rest of the step by file:", {k: round(v, 1) for k, v in list(result["rest_of_step_ms_by_file"].items())[:8]})
    print(f"wrote {out}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surfels", type=int, default=100_000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--top", type=int, default=25, help="ops printed (all are written)")
    ap.add_argument("--train-run", help="profile training steps from this run's checkpoint instead")
    ap.add_argument("--steps", type=int, default=3, help="with --train-run: steps timed and traced")
    ap.add_argument("--label", help="with --train-run: the window's name in fusion_profile_step.json")
    ap.add_argument("--one-core", action="store_true",
                    help="run pinned to one core (against an unpinned run: what the other cores buy)")
    ap.add_argument("--out", default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    if jax.default_backend() != "cpu":
        raise SystemExit("fusion_profile reads XLA:CPU's threads: run it with JAX_PLATFORMS=cpu")
    if args.train_run:
        return main_step(args)
    result = profile_camera(args.surfels, args.width, args.height, args.frames)
    result.update(machine=machine_record())
    write_json(args.out, result)
    busy = result["busy_per_frame"]
    print(f"frame {result['frame_wall_s'] * 1e3:.0f} ms wall, {result['thread_ms_per_frame']:.0f} thread-ms "
          f"({result['loop_thread_ms_per_frame']:.0f} in the compositor loop); ops running at once: none "
          f"{busy['idle_ms']:.0f}, one {busy['one_busy_ms']:.0f}, two+ {busy['two_or_more_busy_ms']:.0f} ms")
    for o in result["ops"][:args.top]:
        print(f"{o['ms_per_frame']:8.2f} ms  x{o['calls_per_frame']:<6g} {o['op']:32s} {'; '.join(o['source'])[:90]}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
