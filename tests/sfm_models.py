"""Small exact SfM models for the checks' tests: pycolmap's synthesize_dataset (no feature
extraction or mapping), and a way to move a view's pose while its observations stay."""

from __future__ import annotations

import numpy as np
import pytest


def synthetic_model(frames: int = 12, database=None):
    """An exact model of `frames` views of 300 points (written into `database` too when given:
    its features, matches and verified pairs)."""
    pycolmap = pytest.importorskip("pycolmap")
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=1, num_cameras_per_rig=1, num_frames_per_rig=frames, num_points3D=300,
        camera_width=640, camera_height=480, camera_params=[600.0, 320.0, 240.0, 0.0],
        num_points2D_without_point3D=0)
    if hasattr(pycolmap, "set_random_seed"):
        pycolmap.set_random_seed(0)
    return pycolmap.synthesize_dataset(options, database)


def move_view(reconstruction, image_id: int, shift=(0.0, 0.0, 0.0), turn_deg: float = 0.0,
              about_world: bool = False) -> str:
    """Move a view's pose in the model (its observations stay): shifted centre, turned about its
    own y axis (or about the world's with `about_world`)."""
    import pycolmap

    image = reconstruction.images[image_id]
    frame = reconstruction.frames[image.frame_id]
    w2c = frame.rig_from_world.matrix()
    a = np.radians(turn_deg)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rotation = w2c[:, :3] @ turn.T if about_world else turn @ w2c[:, :3]
    centre = -w2c[:, :3].T @ w2c[:, 3] + np.asarray(shift)
    frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre)
    return image.name
