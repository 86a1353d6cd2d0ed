"""Gaussian PLY files: the 2DGS layout, 3DGS files on read, a viewer-compatible variant on write.

Layout: x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0 scale_1 rot_0..3 (float32),
f_rest channel-major (all red coefficients, then green, then blue).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ghsplat_jax.core import quaternions
from ghsplat_jax.core.surfels import Surfels, sh_degree_from_rest
from ghsplat_jax.data.errors import DatasetError
from ghsplat_jax.io_utils import atomic_write

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "rot_0", "rot_1", "rot_2", "rot_3"]


class PlyError(DatasetError):
    """A PLY file that cannot be read as Gaussians; the message names the file.

    Args:
        *args: the message, as for any exception (the file's path, then what is wrong).

    Returns:
        The exception, raised by `load_ply` (a DatasetError, so a ValueError too).
    """


_MAX_HEADER_LINES = 10_000  # a real Gaussian PLY header has well under a hundred lines


def _header_line(path: Path, number: int, words: list[str], state: dict) -> None:
    """Apply one header line to `state` (format, vertex count, vertex properties)."""
    bad = lambda what: PlyError(f"{path}: header line {number}: {what}")
    if words[0] == "format":
        if len(words) < 2:
            raise bad("'format' without a format name")
        state["format"] = words[1]
    elif words[0] == "element":
        if len(words) != 3:
            raise bad(f"expected 'element NAME COUNT', got {' '.join(words)!r}")
        state["in_vertex"] = words[1] == "vertex"
        if state["in_vertex"]:
            if state["count"] is not None:
                raise bad("a second 'vertex' element")
            if not words[2].isdigit():
                raise bad(f"vertex count {words[2]!r} is not a non-negative integer")
            state["count"] = int(words[2])
        elif state["count"] is None:
            raise bad(f"element '{words[1]}' before 'vertex' is not supported")
    elif words[0] == "property" and state["in_vertex"]:
        if len(words) > 1 and words[1] == "list":
            raise bad(f"list property '{words[-1]}' in vertex element")
        if len(words) != 3:
            raise bad(f"expected 'property TYPE NAME', got {' '.join(words)!r}")
        if words[1] not in _TYPES:
            raise bad(f"unknown property type '{words[1]}'")
        if any(name == words[2] for name, _ in state["props"]):
            raise bad(f"vertex property '{words[2]}' is listed twice")
        state["props"].append((words[2], _TYPES[words[1]]))
    elif words[0] not in ("property", "obj_info"):
        raise bad(f"unknown keyword {words[0]!r}")


def _parse_header(path: Path, fh) -> tuple[str, int, list[tuple[str, str]], int]:
    if fh.readline(16).strip() != b"ply":
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic line)")
    state: dict[str, Any] = {"format": None, "count": None, "props": [], "in_vertex": False}
    for number in range(2, _MAX_HEADER_LINES):
        line = fh.readline(4096)
        if not line:
            raise PlyError(f"{path}: truncated header (no end_header)")
        words = line.decode("ascii", "replace").split()
        if not words or words[0] == "comment":
            continue
        if words[0] == "end_header":
            break
        _header_line(path, number, words, state)
    else:
        raise PlyError(f"{path}: header longer than {_MAX_HEADER_LINES} lines (no end_header)")
    fmt, count, props = state["format"], state["count"], state["props"]
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise PlyError(f"{path}: unsupported PLY format {fmt!r}")
    if count is None:
        raise PlyError(f"{path}: no vertex element")
    if not props:
        raise PlyError(f"{path}: the vertex element has no properties")
    return fmt, count, props, fh.tell()


def read_vertices(path: str | os.PathLike) -> np.ndarray:
    """The vertex element of a PLY file as a numpy structured array."""
    path = Path(path)
    if not path.is_file():
        raise PlyError(f"{path}: no such file")
    with open(path, "rb") as fh:
        fmt, count, props, offset = _parse_header(path, fh)
        if fmt == "ascii":
            return _read_ascii(path, fh, count, props)
    endian = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(n, endian + t) for n, t in props])
    size = path.stat().st_size - offset
    # Checked before anything is allocated: a header count never sizes memory on its own.
    if size < count * dtype.itemsize:
        raise PlyError(f"{path}: truncated, {size} bytes of vertex data for {count} vertices "
                       f"of {dtype.itemsize} bytes")
    return np.fromfile(path, dtype=dtype, count=count, offset=offset)


def _read_ascii(path: Path, fh, count: int, props: list[tuple[str, str]]) -> np.ndarray:
    text = fh.read().decode("ascii", "replace").split()
    need = count * len(props)
    if len(text) < need:
        raise PlyError(f"{path}: truncated, {len(text)} of {need} ascii values")
    try:
        flat = np.array(text[:need], np.float64).reshape(count, len(props))
    except ValueError as exc:
        raise PlyError(f"{path}: bad ascii vertex value ({exc})") from None
    out = np.empty(count, [(n, t) for n, t in props])
    with np.errstate(invalid="ignore", over="ignore"):  # out-of-range ints are caught by the finiteness check or wrap
        for i, (name, _) in enumerate(props):
            out[name] = flat[:, i]
    return out


def _rest_names(path: Path, names) -> list[str]:
    """f_rest_0 .. f_rest_{n-1} in index order; any other f_rest_ name is an error."""
    rest = [n for n in names if n.startswith("f_rest_")]
    expected = [f"f_rest_{i}" for i in range(len(rest))]
    if sorted(rest) != sorted(expected):
        raise PlyError(f"{path}: f_rest properties must be f_rest_0..f_rest_{len(rest) - 1}, got {rest}")
    return expected


def load_ply(path: str | os.PathLike, finite: bool = True) -> Surfels:
    """Read a 2DGS (or 3DGS) Gaussian PLY into Surfels (numpy float32 fields).

    3DGS files have three scales: the largest two are kept and a warning says so. NaN or Inf
    values are an error (they must never reach a render) unless `finite=False`, for tools
    that drop such surfels themselves (`ghsplat export`).

    Args:
        path: the PLY file (binary little- or big-endian, or ASCII).
        finite: refuse NaN or Inf values (True) or pass them through (False).

    Returns:
        Surfels with NumPy float32 fields; the SH degree follows the file's f_rest count.

    Raises:
        PlyError: the file is not a readable Gaussian PLY, or (with `finite`) holds
            non-finite values.
    """
    path = Path(path)
    v = read_vertices(path)
    names = v.dtype.names or ()  # a structured array: never None
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise PlyError(f"{path}: not a Gaussian PLY, missing properties {missing}")
    col = lambda n: np.asarray(v[n], np.float32)
    rest_names = _rest_names(path, names)
    if finite:
        _check_finite(path, v, _REQUIRED + rest_names + (["scale_2"] if "scale_2" in names else []))
    if len(rest_names) % 3:
        raise PlyError(f"{path}: {len(rest_names)} f_rest properties is not a multiple of 3")
    k = len(rest_names) // 3
    try:
        sh_degree_from_rest(k)
    except ValueError as exc:
        raise PlyError(f"{path}: {exc}") from None
    rest = np.stack([col(n) for n in rest_names], axis=1) if k else np.zeros((len(v), 0), np.float32)
    sh_rest = rest.reshape(len(v), 3, k).transpose(0, 2, 1)  # channel-major on disk
    scales = np.stack([col("scale_0"), col("scale_1")], axis=1)
    quats = np.stack([col(f"rot_{i}") for i in range(4)], axis=1)
    if "scale_2" in names:
        scales, quats = surfel_from_3dgs(np.stack([scales[:, 0], scales[:, 1], col("scale_2")], axis=1), quats)
        warnings.warn(f"{path}: 3DGS file with three scales; kept the largest two per Gaussian and "
                      f"turned its frame so the dropped (smallest) axis is the surfel normal", stacklevel=2)
    return Surfels(
        means=np.stack([col("x"), col("y"), col("z")], axis=1),
        quats=quats,
        log_scales=scales,
        opacity_logits=col("opacity"),
        sh_dc=np.stack([col(f"f_dc_{i}") for i in range(3)], axis=1),
        sh_rest=np.ascontiguousarray(sh_rest),
    )


def _check_finite(path: Path, v: np.ndarray, names: list[str]) -> None:
    """NaN or Inf (also from float64/int values that overflow float32) must never reach a render."""
    for name in names:
        with np.errstate(over="ignore", invalid="ignore"):
            bad = np.count_nonzero(~np.isfinite(np.asarray(v[name], np.float32)))
        if bad:
            raise PlyError(f"{path}: {bad} of {len(v)} vertices have a non-finite '{name}' (NaN or Inf); "
                           "`ghsplat export IN.ply --out OUT.ply` drops such surfels")


# Right-multiplied rotations that move a 3DGS Gaussian's smallest axis into the normal slot:
# dropping axis 0 -> columns (1, 2, 0), a 120-degree turn about (1,1,1); dropping axis 1 ->
# columns (0, 2, -1), a 90-degree turn about x; dropping axis 2 -> unchanged.
_TO_NORMAL = np.array([[0.5, 0.5, 0.5, 0.5], [np.sqrt(0.5), np.sqrt(0.5), 0, 0], [1.0, 0, 0, 0]])


def surfel_from_3dgs(log_scales3: np.ndarray, quats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the two largest of three scales, in axis order, and the matching rotation."""
    dropped = np.argmin(log_scales3, axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[dropped]
    scales = np.take_along_axis(log_scales3, keep, axis=1)
    product = quaternions.multiply_np(quats, _TO_NORMAL[dropped])
    return scales.astype(np.float32), product.astype(np.float32)


def is_3dgs_file(path: str | os.PathLike) -> bool:
    return "scale_2" in (read_vertices(path).dtype.names or ())


def surfels_to_vertices(s: Surfels, viewer_compatible: bool = False) -> np.ndarray:
    s = s.to_numpy()
    n, k = s.means.shape[0], s.sh_rest.shape[1]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * k)]
    names += ["opacity", "scale_0", "scale_1"] + (["scale_2"] if viewer_compatible else [])
    names += [f"rot_{i}" for i in range(4)]
    v = np.zeros(n, np.dtype([(name, "<f4") for name in names]))
    for i, axis in enumerate("xyz"):
        v[axis] = s.means[:, i]
    for i in range(3):
        v[f"f_dc_{i}"] = s.sh_dc[:, i]
    rest = s.sh_rest.transpose(0, 2, 1).reshape(n, 3 * k)
    for i in range(3 * k):
        v[f"f_rest_{i}"] = rest[:, i]
    v["opacity"] = s.opacity_logits
    v["scale_0"], v["scale_1"] = s.log_scales[:, 0], s.log_scales[:, 1]
    if viewer_compatible:
        v["scale_2"] = np.float32(np.log(1e-6))
    for i in range(4):
        v[f"rot_{i}"] = s.quats[:, i]
    return v


def save_ply(s: Surfels, path: str | os.PathLike, viewer_compatible: bool = False) -> Path:
    """Write Surfels as a binary 2DGS PLY (atomically); `viewer_compatible` adds scale_2.

    Args:
        s: the surfels to write (host or device arrays).
        path: the file to write; it is replaced atomically.
        viewer_compatible: add a thin third scale (scale_2) so that 3DGS viewers load the file.

    Returns:
        The path written, as a Path.

    Raises:
        ValueError: when a field holds NaN or Inf.
    """
    path = Path(path)
    s = s.to_numpy()
    bad = [f for f in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
           if not np.all(np.isfinite(getattr(s, f)))]
    if bad:
        raise ValueError(f"refusing to write {path}: non-finite values in {bad}")
    v = surfels_to_vertices(s, viewer_compatible)
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"element vertex {len(v)}\n"
    header += "".join(f"property float {name}\n" for name in v.dtype.names or ())
    header += "end_header\n"
    with atomic_write(path) as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
    return path


