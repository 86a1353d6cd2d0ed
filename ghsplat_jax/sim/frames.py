"""Rigid transforms and a small tf tree (numpy, float64).

Conventions: REP-103 body frames (x forward, y left, z up); optical frames in the
OpenCV convention (z forward, x right, y down). A transform named `a_from_b` maps
points in frame b to frame a. Quaternions here are ROS's x-y-z-w (geometry_msgs), named
`quat_xyzw` at every use; the package's own w-x-y-z ones convert in core.quaternions.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.core import quaternions

# Columns: the optical axes (x right, y down, z forward) written in the body frame.
LINK_FROM_OPTICAL_R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def make_transform(rotation=None, translation=None) -> np.ndarray:
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = np.asarray(rotation, np.float64)
    if translation is not None:
        T[:3, 3] = np.asarray(translation, np.float64)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, np.float64)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros_like(T)
    out[..., :3, :3] = np.swapaxes(R, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    out[..., 3, 3] = 1.0
    return out


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), the URDF/ROS fixed-axis convention."""
    return quaternions.from_euler_xyz([roll, pitch, yaw])


def from_xyz_rpy(xyz, rpy) -> np.ndarray:
    return make_transform(rpy_matrix(*rpy), xyz)


def planar(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """map_from_base of a ground robot at (x, y) heading yaw."""
    c, s = np.cos(yaw), np.sin(yaw)
    return make_transform([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], [x, y, z])


def quat_xyzw(T_or_R: np.ndarray) -> np.ndarray:
    """The x-y-z-w quaternion (ROS order, w >= 0) of a rotation or transform."""
    R = np.asarray(T_or_R, np.float64)[..., :3, :3]
    return quaternions.wxyz_to_xyzw(quaternions.from_rotation_matrix(R))


def from_pose(position, quat_xyzw_, unit_tol: float = 1e-3) -> np.ndarray:
    """4x4 from a position and an x-y-z-w quaternion; raises ValueError on NaN or non-unit q."""
    p = np.asarray(position, np.float64)
    q = np.asarray(quat_xyzw_, np.float64)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ValueError("pose has non-finite values")
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > unit_tol:
        raise ValueError(f"quaternion norm {norm:.6f} is not 1")
    return make_transform(quaternions.to_rotation_matrix_np(quaternions.xyzw_to_wxyz(q)), p)


def yaw_of(T: np.ndarray) -> float:
    R = np.asarray(T)[:3, :3]
    return float(np.arctan2(R[1, 0], R[0, 0]))


def world_to_cam(map_from_optical: np.ndarray) -> np.ndarray:
    """The rasterizer's world_to_cam (float32) for an optical frame's pose in the map."""
    return invert(map_from_optical).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Transform:
    """parent_from_child; `stamp` in simulated seconds (None for static transforms)."""

    parent: str
    child: str
    matrix: np.ndarray
    stamp: float | None = None


class TfTree:
    """A tree of named frames; each frame has at most one parent (as in tf2)."""

    def __init__(self, transforms: list[Transform] = ()):
        self._edges: dict[str, Transform] = {}
        for t in transforms:
            self.set(t)

    def set(self, t: Transform) -> None:
        old = self._edges.get(t.child)
        if old is not None and old.parent != t.parent:
            raise ValueError(f"frame {t.child!r} already has parent {old.parent!r}, not {t.parent!r}")
        if t.parent == t.child:
            raise ValueError(f"frame {t.child!r} cannot be its own parent")
        self._edges[t.child] = t
        self._root_path(t.child)  # rejects cycles

    @property
    def frames(self) -> set[str]:
        return set(self._edges) | {t.parent for t in self._edges.values()}

    def _root_path(self, frame: str) -> list[str]:
        path = [frame]
        while path[-1] in self._edges:
            path.append(self._edges[path[-1]].parent)
            if len(path) > len(self._edges) + 1:
                raise ValueError(f"tf cycle through {frame!r}")
        return path

    def _root_from(self, frame: str) -> np.ndarray:
        T = np.eye(4)
        for child in self._root_path(frame)[:-1]:
            T = self._edges[child].matrix @ T
        return T

    def lookup(self, target: str, source: str) -> np.ndarray:
        """target_from_source."""
        for f in (target, source):
            if f not in self.frames:
                raise KeyError(f"unknown frame {f!r}")
        if self._root_path(target)[-1] != self._root_path(source)[-1]:
            raise KeyError(f"frames {target!r} and {source!r} are not connected")
        return invert(self._root_from(target)) @ self._root_from(source)

    def edges(self) -> list[Transform]:
        return list(self._edges.values())
