"""Every reader under corrupted input (hypothesis): flipped bytes, truncation, duplicated lines
and properties, absurd header counts, NaN and Inf. A reader either returns finite values or
raises the project's own error naming the file (or topic) and the problem; nothing hangs and no
header count sizes memory on its own (peak Python/numpy allocation is bounded per example)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import struct
import tracemalloc

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ghsplat_jax.data.errors import DatasetError

# GHSPLAT_FUZZ_EXAMPLES=2000 runs a longer, randomised search (the default is fixed and quick:
# 100 examples a reader in `make test-all`, 25 in `make test`, whose runner sets GHSPLAT_SUITE=fast).
DEFAULT_EXAMPLES = "25" if os.environ.get("GHSPLAT_SUITE") == "fast" else "100"
EXAMPLES = int(os.environ.get("GHSPLAT_FUZZ_EXAMPLES", DEFAULT_EXAMPLES))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize="GHSPLAT_FUZZ_EXAMPLES" not in os.environ,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
MAX_PEAK_BYTES = 64 * 2**20
MAX_SECONDS = 20


@contextlib.contextmanager
def bounded():
    """Fail on a hang (SIGALRM) or on a large allocation (tracemalloc sees numpy's too)."""
    def timeout(*_):
        raise TimeoutError(f"reader took more than {MAX_SECONDS} s")

    old = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(MAX_SECONDS)
    tracemalloc.start()
    try:
        yield
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert peak < MAX_PEAK_BYTES, f"reader allocated {peak / 2**20:.0f} MiB"


def expect(call, error: type[Exception], names: str):
    """The result of `call`, or None when it raised `error` whose text names `names`."""
    with bounded():
        try:
            return call()
        except error as exc:
            assert names in str(exc), f"error does not name {names!r}: {exc}"
            return None


# ------------------------------------------------------------------------------ mutations

ABSURD = ["99999999999999999999", "4294967296", "-1", "1e9", "abc", "nan", "inf", "-inf", "0", ""]


@st.composite
def byte_mutation(draw, data: bytes) -> bytes:
    """Flip bytes, truncate, insert or duplicate a slice of `data`."""
    data = bytearray(data)
    kind = draw(st.sampled_from(["flip", "truncate", "insert", "duplicate"]))
    n = len(data)
    if kind == "flip":
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, n - 1))
            data[i] ^= draw(st.integers(1, 255))
    elif kind == "truncate":
        data = data[: draw(st.integers(0, n - 1))]
    elif kind == "insert":
        i = draw(st.integers(0, n))
        data[i:i] = draw(st.binary(min_size=1, max_size=16))
    else:
        i = draw(st.integers(0, n - 1))
        j = draw(st.integers(i, min(n, i + 64)))
        data[j:j] = data[i:j]
    return bytes(data)


@st.composite
def text_mutation(draw, text: str) -> str:
    """Swap a number for an absurd one (NaN, Inf, huge, negative, not a number), duplicate or
    drop a line, or fall back to a byte mutation."""
    kind = draw(st.sampled_from(["number", "number", "dup_line", "drop_line", "bytes"]))
    if kind == "number":
        spans = [m.span() for m in re.finditer(r"-?\d+(\.\d+)?(e-?\d+)?", text)]
        a, b = draw(st.sampled_from(spans))
        return text[:a] + draw(st.sampled_from(ABSURD)) + text[b:]
    lines = text.splitlines(keepends=True)
    i = draw(st.integers(0, len(lines) - 1))
    if kind == "dup_line":
        return "".join(lines[: i + 1] + [lines[i]] + lines[i + 1:])
    if kind == "drop_line":
        return "".join(lines[:i] + lines[i + 1:])
    return draw(byte_mutation(text.encode())).decode("utf-8", "replace")


def finite(*arrays) -> bool:
    return all(np.all(np.isfinite(np.asarray(a, np.float64))) for a in arrays)


# ------------------------------------------------------------------------------------ PLY

def _ply_bytes(fmt: str = "binary_little_endian") -> bytes:
    from ghsplat_jax.core.surfels import Surfels
    from ghsplat_jax.data.ply import surfels_to_vertices

    rng = np.random.default_rng(0)
    n = 4
    s = Surfels(rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=(n, 2)), rng.normal(size=n),
                rng.normal(size=(n, 3)), rng.normal(size=(n, 3, 3)))
    v = surfels_to_vertices(s)
    header = f"ply\nformat {fmt} 1.0\ncomment fuzz\nelement vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in v.dtype.names) + "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(x)) for x in row) + "\n" for row in v.tolist())
        return (header + body).encode()
    return header.encode() + v.tobytes()


@st.composite
def ply_mutation(draw, fmt: str) -> bytes:
    data = _ply_bytes(fmt)
    head, sep, body = data.partition(b"end_header\n")
    lines = head.decode().splitlines(keepends=True)
    kind = draw(st.sampled_from(["dup_property", "count", "nan", "bytes", "header_text"]))
    if kind == "dup_property":
        props = [i for i, line in enumerate(lines) if line.startswith("property")]
        i = draw(st.sampled_from(props))
        lines.insert(draw(st.sampled_from(props)), lines[i])
    elif kind == "count":
        i = next(i for i, line in enumerate(lines) if line.startswith("element vertex"))
        lines[i] = f"element vertex {draw(st.sampled_from(ABSURD))}\n"
    elif kind == "nan" and fmt != "ascii":
        v = bytearray(body)
        i = draw(st.integers(0, len(v) // 4 - 1)) * 4
        v[i:i + 4] = struct.pack("<f", draw(st.sampled_from([np.nan, np.inf, -np.inf])))
        body = bytes(v)
    elif kind == "nan":
        body = re.sub(rb"-?\d+\.\d+(e-?\d+)?", draw(st.sampled_from([b"nan", b"inf", b"1e999"])), body, count=1)
    elif kind == "header_text":
        return draw(text_mutation(head.decode())).encode() + sep + body
    else:
        return draw(byte_mutation(data))
    return "".join(lines).encode() + sep + body


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_ply_reader_under_fuzz(tmp_path, fmt):
    from ghsplat_jax.data.ply import PlyError, load_ply

    path = tmp_path / "fuzz.ply"

    @FUZZ
    @given(ply_mutation(fmt))
    def check(data):
        path.write_bytes(data)
        s = expect(lambda: load_ply(path), PlyError, "fuzz.ply")
        if s is not None:
            assert finite(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh_dc, s.sh_rest)

    check()


def test_ply_errors_found_by_a_new_user(tmp_path):
    """The two failures of the issue: a property listed twice, a corrupt vertex count."""
    from ghsplat_jax.data.ply import PlyError, load_ply

    data = _ply_bytes()
    path = tmp_path / "twice.ply"
    path.write_bytes(data.replace(b"property float x\n", b"property float x\nproperty float x\n", 1))
    with pytest.raises(PlyError, match=r"twice\.ply: header line \d+: vertex property 'x' is listed twice"):
        load_ply(path)
    path = tmp_path / "count.ply"
    path.write_bytes(data.replace(b"element vertex 4\n", b"element vertex 4x\n"))
    with pytest.raises(PlyError, match=r"count\.ply: .*vertex count '4x' is not a non-negative integer"):
        load_ply(path)
    path.write_bytes(data.replace(b"element vertex 4\n", b"element vertex 99999999999999999\n"))
    with pytest.raises(PlyError, match="truncated"):
        load_ply(path)


# --------------------------------------------------------------------------------- COLMAP

_K = (20.0, 21.0, 12.5, 8.75)
_POSES = [((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 3.0)), ((0.9238795, 0.0, 0.3826834, 0.0), (0.1, 0.0, 3.0))]


def _colmap_text() -> dict[str, str]:
    images = "# image list\n" + "".join(
        f"{i + 1} {' '.join(map(str, q))} {' '.join(map(str, t))} 1 img{i}.png\n1.5 2.5 1\n"
        for i, (q, t) in enumerate(_POSES))
    return {"cameras.txt": "# cameras\n1 PINHOLE 24 18 " + " ".join(map(str, _K)) + "\n",
            "images.txt": images,
            "points3D.txt": "1 0.1 0.2 0.3 255 128 0 0.5 1 0\n2 -0.5 0.25 1.0 10 20 30 0.1 2 0\n"}


def _colmap_binary() -> dict[str, bytes]:
    cameras = struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, 24, 18) + struct.pack("<4d", *_K)
    images = struct.pack("<Q", len(_POSES))
    for i, (q, t) in enumerate(_POSES):
        images += struct.pack("<i7di", i + 1, *q, *t, 1) + f"img{i}.png".encode() + b"\0"
        images += struct.pack("<Q", 1) + struct.pack("<ddq", 1.5, 2.5, 1)
    points = struct.pack("<Q", 2)
    for k, (xyz, rgb) in enumerate([((0.1, 0.2, 0.3), (255, 128, 0)), ((-0.5, 0.25, 1.0), (10, 20, 30))]):
        points += struct.pack("<Q3d3BdQ", k + 1, *xyz, *rgb, 0.5, 1) + struct.pack("<ii", 1, 0)
    return {"cameras.bin": cameras, "images.bin": images, "points3D.bin": points}


def _check_scene(spec):
    for f in spec.frames:
        assert finite(f.K, f.world_to_cam) and 0 < f.width <= 100_000 and 0 < f.height <= 100_000
        assert f.dist is None or finite(f.dist)
    assert finite(spec.points)


@pytest.mark.parametrize("kind", ["binary", "text"])
def test_colmap_reader_under_fuzz(tmp_path, kind):
    from ghsplat_jax.data.colmap import read_colmap

    files = _colmap_binary() if kind == "binary" else _colmap_text()
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    names = sorted(files)

    @FUZZ
    @given(st.sampled_from(names), st.data())
    def check(target, data):
        for name, content in files.items():
            (model / name).write_bytes(content.encode() if isinstance(content, str) else content)
        content = files[target]
        mutated = (data.draw(text_mutation(content)).encode() if isinstance(content, str)
                   else data.draw(byte_mutation(content)))
        (model / target).write_bytes(mutated)
        spec = expect(lambda: read_colmap(tmp_path, 1.0), DatasetError, str(model))
        if spec is not None:
            _check_scene(spec)

    check()


# ------------------------------------------------------------------------ transforms.json

def _transforms() -> str:
    frames = []
    for i, (_q, t) in enumerate(_POSES):
        c2w = np.eye(4)
        c2w[:3, 3] = t
        frames.append({"file_path": f"images/img{i}", "transform_matrix": c2w.tolist(), "fl_x": 20.0 + i})
    meta = {"camera_model": "OPENCV", "fl_x": 20.0, "fl_y": 21.0, "cx": 12.5, "cy": 8.75, "w": 24, "h": 18,
            "k1": 0.01, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames}
    return json.dumps(meta, indent=1)


@st.composite
def json_mutation(draw, text: str) -> str:
    """Text mutations plus type confusion: a value replaced by another JSON type."""
    if draw(st.booleans()):
        return draw(text_mutation(text))
    meta = json.loads(text)
    table = draw(st.sampled_from([meta, meta["frames"][0]]))
    key = draw(st.sampled_from(sorted(table)))
    table[key] = draw(st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(),
                                st.text(max_size=8), st.lists(st.floats(), max_size=5), st.just({})))
    return json.dumps(meta)


def test_transforms_reader_under_fuzz(tmp_path):
    from ghsplat_jax.data.images import write_image
    from ghsplat_jax.data.nerf import read_transforms

    for i in range(len(_POSES)):
        write_image(tmp_path / "images" / f"img{i}.png", np.zeros((18, 24, 3), np.float32))
    base = _transforms()

    @FUZZ
    @given(json_mutation(base))
    def check(text):
        (tmp_path / "transforms.json").write_text(text, encoding="utf-8", errors="replace")
        spec = expect(lambda: read_transforms(tmp_path, 1.0), DatasetError, str(tmp_path))
        if spec is not None:
            _check_scene(spec)

    check()


# ------------------------------------------------------------------------------------ LLFF

def test_llff_reader_under_fuzz(tmp_path):
    import io

    from ghsplat_jax.data.llff import read_llff

    (tmp_path / "images").mkdir()
    for i in range(3):
        (tmp_path / "images" / f"img{i}.png").write_bytes(b"")  # only listed, never decoded here
    rows = []
    for i in range(3):
        pose = np.concatenate([np.eye(3)[:, [1, 0, 2]] * [1, 1, -1], [[0.1 * i], [0], [0]], [[18], [24], [20]]], 1)
        rows.append(np.concatenate([pose.ravel(), [0.5, 10.0]]))
    buf = io.BytesIO()
    np.save(buf, np.array(rows))
    base = buf.getvalue()
    header_end = base.index(b"\n") + 1

    @st.composite
    def mutation(draw):
        kind = draw(st.sampled_from(["bytes", "header", "nan"]))
        if kind == "header":  # absurd shapes and dtypes in the .npy header
            head = base[:header_end].decode("latin1")
            head = draw(st.sampled_from([
                head.replace("(3, 17)", "(99999999999, 17)"), head.replace("(3, 17)", "(3, 99999999999)"),
                head.replace("(3, 17)", "(3,)"), head.replace("'<f8'", "'|O'"), head.replace("'<f8'", "'<U9'"),
                head.replace("False", "True"), head[:20] + "x" + head[21:]]))
            return head.encode("latin1") + base[header_end:]
        if kind == "nan":
            data = bytearray(base)
            i = header_end + draw(st.integers(0, 3 * 17 - 1)) * 8
            data[i:i + 8] = struct.pack("<d", draw(st.sampled_from([np.nan, np.inf, -1.0, 0.0, 1e300])))
            return bytes(data)
        return draw(byte_mutation(base))

    @FUZZ
    @given(mutation())
    def check(data):
        (tmp_path / "poses_bounds.npy").write_bytes(data)
        spec = expect(lambda: read_llff(tmp_path, 1.0), DatasetError, str(tmp_path))
        if spec is not None:
            _check_scene(spec)

    check()


# ------------------------------------------------------------------------ layout and experiment TOML

_LAYOUT = """\
sh_policy = "pad"
overlap = "warn"
configuration = "wide"

[[rows]]
name = "row1"
source = "seg.ply"
scale = 1.0
position = [0.0, 0.0, 0.0]
yaw_deg = 0.0
repeat = 2
crop_box = [[-1, -1, -0.1], [1, 1, 2]]

[[surfaces]]
kind = "box"
min = [-1, -2, -0.02]
max = [10, 6, 0.0]
faces = ["+z"]
spacing = 0.05
colour = [0.35, 0.3, 0.25]

[[markers]]
id = 0
size = 0.16
position = [4.0, 1.0, 0.5]
facing = [-1, 0, 0]

[configurations.wide]
rows = ["row1", "row1"]
row_spacing = 1.6
repeat = 3
segment_gap = 0.05
"""


def _toml_values():
    return st.one_of(st.none().map(lambda _: "x"), st.booleans(), st.integers(-2**63, 2**63 - 1), st.floats(),
                     st.text(max_size=6), st.lists(st.floats(), max_size=4), st.dictionaries(st.text(max_size=3),
                                                                                           st.integers(), max_size=2))


@st.composite
def toml_mutation(draw, text: str) -> str:
    """Text mutations, or one value of the parsed file replaced by another TOML type."""
    import tomllib

    import tomli_w

    if draw(st.booleans()):
        return draw(text_mutation(text))
    data = tomllib.loads(text)
    tables = [data] + [t for v in data.values() if isinstance(v, list) for t in v if isinstance(t, dict)]
    tables += [t for v in data.values() if isinstance(v, dict) for t in v.values() if isinstance(t, dict)]
    table = draw(st.sampled_from(tables))
    table[draw(st.sampled_from(sorted(table)))] = draw(_toml_values())
    return tomli_w.dumps(data)


def test_layout_reader_under_fuzz(tmp_path):
    from ghsplat_jax.scene.layout import LayoutError, load_layout

    (tmp_path / "seg.ply").write_bytes(_ply_bytes())
    path = tmp_path / "layout.toml"
    path.write_text(_LAYOUT)
    assert load_layout(path).rows  # the unmutated layout is valid

    @FUZZ
    @given(toml_mutation(_LAYOUT))
    def check(text):
        path.write_text(text, encoding="utf-8", errors="replace")
        layout = expect(lambda: load_layout(path), LayoutError, "layout.toml")
        if layout is not None:
            for r in layout.rows:
                assert finite(r.position, r.scale, r.yaw_deg) and 1 <= r.repeat <= 10_000
            for m in layout.markers:
                assert finite(m.world_from_tag, m.size)

    check()


def test_experiment_reader_under_fuzz(tmp_path):
    from pathlib import Path

    from ghsplat_jax.experiments.runner import load_experiment
    from ghsplat_jax.train.config import ConfigError

    base = (Path(__file__).parents[1] / "experiments" / "quick_cpu.toml").read_text()
    path = tmp_path / "exp.toml"

    @FUZZ
    @given(toml_mutation(base))
    def check(text):
        path.write_text(text, encoding="utf-8", errors="replace")
        exp = expect(lambda: load_experiment(path), ConfigError, "exp.toml")
        if exp is not None:
            for run in exp.runs:
                assert all(np.isfinite(v) for v in vars(run.config).values() if isinstance(v, float))

    check()


# ------------------------------------------------------------------------------ DDS messages

def test_dds_messages_under_fuzz():
    from ghsplat_jax.sim import messages
    from ghsplat_jax.sim.camera_sensor import CameraModel
    from ghsplat_jax.transport import dds_types as D
    from ghsplat_jax.transport.dds_node import camera_from_request, pose_from_sample

    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 0.5]
    pose = D.payload(D.to_dds(messages.pose_stamped(T, 3.25, "cam_optical")))
    model = CameraModel.from_fov("cam_optical", 64, 48, 70.0)
    request = D.payload(D.make_request(model.info(0.0), 7, 1))

    @FUZZ
    @given(st.sampled_from(["pose", "request"]), st.data())
    def check(which, data):
        raw = data.draw(byte_mutation(pose if which == "pose" else request))
        cls, topic = (D.PoseStamped_, "/camera_pose") if which == "pose" else (D.SetCameraInfo_Request_,
                                                                               "/register_camera")

        def read():
            sample = D.decode(cls, raw, topic)
            return pose_from_sample(sample) if which == "pose" else camera_from_request(sample)

        out = expect(read, messages.MessageError, topic)
        if out is not None and which == "pose":
            assert finite(out[1], out[2])
        elif out is not None:
            assert finite(out.K) and 8 <= out.width <= 8192

    check()

    @FUZZ
    @given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=7, max_size=7))
    def check_values(values):
        s = D.PoseStamped_(D.Header_(D.Time_(1, 0), "cam_optical"),
                           D.Pose_(D.Point_(*values[:3]), D.Quaternion_(*values[3:])))
        out = expect(lambda: pose_from_sample(s), messages.MessageError, "/camera_pose")
        if out is not None:
            assert finite(out[1])

    check_values()
