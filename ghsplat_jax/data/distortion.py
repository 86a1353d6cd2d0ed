"""Undistortion of OpenCV-model lens distortion to a pinhole camera (cv2, imported lazily).

Our K puts pixel centres at +0.5 (as COLMAP and instant-ngp do); OpenCV puts them
at integers, so principal points shift by 0.5 on the way in and out of cv2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def has_distortion(dist: np.ndarray | None) -> bool:
    return dist is not None and bool(np.any(np.asarray(dist) != 0))


@dataclass(frozen=True)
class Undistorter:
    """Remap tables from a pinhole image (K `new_K`) into the distorted source image."""

    new_K: np.ndarray  # (3,3) pinhole intrinsics of the undistorted image, our convention
    map_x: np.ndarray  # (H,W) float32 source column of each output pixel, OpenCV convention
    map_y: np.ndarray

    def __call__(self, image: np.ndarray) -> np.ndarray:
        import cv2

        # Bilinear like COLMAP's undistorter; replicate the border for the sliver of
        # pixels the optimal-K estimate leaves just outside the source.
        return cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def make_undistorter(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> Undistorter:
    """Undistort to the same size with a K chosen so that every output pixel sees the source.

    `dist` is in OpenCV order (k1, k2, p1, p2[, k3[, k4, k5, k6]]), which is also the
    meaning of COLMAP's RADIAL/OPENCV/FULL_OPENCV and instant-ngp's parameters.
    """
    import cv2

    to_cv = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]], np.float64)
    K_cv = to_cv @ np.asarray(K, np.float64)
    dist = np.asarray(dist, np.float64)
    new_cv, _ = cv2.getOptimalNewCameraMatrix(K_cv, dist, (width, height), 0.0, (width, height))
    map_x, map_y = cv2.initUndistortRectifyMap(K_cv, dist, None, new_cv, (width, height), cv2.CV_32FC1)
    return Undistorter(np.linalg.inv(to_cv) @ new_cv, map_x, map_y)
