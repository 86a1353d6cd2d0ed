"""Per-op profile of a simulated camera frame on XLA:CPU: where the thread time goes.

Every compiled op (fusion, dot, sort, scatter) of the camera's program is timed with
jax.profiler over a few frames and mapped to the source lines it came from (the compiled HLO's
stack-frame metadata). Ops inside the compositor's loop run once per batch; the rest once per
frame. The same trace says how many threads were busy at once, which is what decides whether
intra-op parallelism can pay on this machine. This rasterizer's speed depends on XLA:CPU's fusion
choices, so a change in a JAX upgrade shows up here first.

    JAX_PLATFORMS=cpu python benchmarks/fusion_profile.py --surfels 100000 --frames 3

Writes benchmarks/results/fusion_profile.json. CPU only (it reads XLA:CPU's thread names).
"""

from __future__ import annotations

import argparse
import collections
import glob
import os
import re
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import numpy as np

from ghsplat_jax.io_utils import write_json
from sim_speed import greenhouse_surfels  # noqa: E402  (benchmarks/ is the script's folder)

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
    """Milliseconds of the traced span with no, one and two or more threads running ops."""
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
            r"^(\d+) \{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", between("FileLocations", "StackFrames"), re.M)}
        frames = dict(re.findall(r"^(\d+) \{file_location_id=(\d+)", between("StackFrames", "\n\n"), re.M))
    except (IndexError, KeyError):
        return {}
    bodies = dict(re.findall(r"\n%([\w.\-]+) [^\n]*\{\n(.*?)\n\}", hlo, re.S))
    out = {}
    for line in hlo.splitlines():
        m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = ", line)
        if not m:
            continue
        call = re.search(r"calls=%([\w.\-]+)", line)
        ids = re.findall(r"stack_frame_id=(\d+)", bodies.get(call.group(1), "") if call else line)
        counts = collections.Counter(locs[frames[i]] for i in ids if frames.get(i) in locs)
        out[m.group(1)] = [loc for loc, _ in counts.most_common()]  # the lines most of the op comes from first
    return out


def profile_camera(surfels: int, width: int, height: int, frames: int) -> dict:
    from ghsplat_jax.sim import frames as frames_mod, robot as robot_mod
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
    fn = renderer._fn(width, height)
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
                thread_ms_per_frame=sum(ms.values()), loop_thread_ms_per_frame=sum(o["ms_per_frame"] for o in ops if o["in_loop"]),
                busy_per_frame={k: v / frames for k, v in busy_threads(events).items()}, ops=ops)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surfels", type=int, default=100_000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--top", type=int, default=25, help="ops printed (all are written)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "fusion_profile.json"))
    args = ap.parse_args(argv)
    if jax.default_backend() != "cpu":
        raise SystemExit("fusion_profile reads XLA:CPU's threads: run it with JAX_PLATFORMS=cpu")
    result = profile_camera(args.surfels, args.width, args.height, args.frames)
    result.update(jax=jax.__version__, cpus=os.cpu_count(), load_average=os.getloadavg()[0])
    write_json(args.out, result)
    busy = result["busy_per_frame"]
    print(f"frame {result['frame_wall_s'] * 1e3:.0f} ms wall, {result['thread_ms_per_frame']:.0f} thread-ms "
          f"({result['loop_thread_ms_per_frame']:.0f} in the compositor loop); threads busy: none "
          f"{busy['idle_ms']:.0f}, one {busy['one_busy_ms']:.0f}, two+ {busy['two_or_more_busy_ms']:.0f} ms")
    for o in result["ops"][:args.top]:
        print(f"{o['ms_per_frame']:8.2f} ms  x{o['calls_per_frame']:<6g} {o['op']:32s} {'; '.join(o['source'])[:90]}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
