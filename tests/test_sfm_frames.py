"""Keyframe selection for video input: sharp frames, a minimum baseline apart."""

from __future__ import annotations

import numpy as np
import pytest

from ghsplat_jax.sfm.frames import FrameOptions, score_frames, select_frames

cv2 = pytest.importorskip("cv2")

SHIFT = 4  # pixels per frame
BLURRED = set(range(20, 26))


def test_select_frames_spacing_and_blur():
    sharp = np.full(100, 100.0)
    sharp[[10, 11, 30]] = 5.0  # blurred
    step = np.full(100, 0.01)
    step[0] = 0.0
    keys = select_frames(sharp, step, FrameOptions(min_baseline=0.05, window=3))
    assert keys[0] == 0
    assert not set(keys) & {10, 11, 30}
    assert all(b - a >= 5 for a, b in zip(keys, keys[1:]))  # baseline 0.05 = 5 steps
    assert all(b - a <= 5 + 3 for a, b in zip(keys, keys[1:]))  # chosen within the window
    thinned = select_frames(sharp, step, FrameOptions(min_baseline=0.05, window=3, max_frames=5))
    assert len(thinned) == 5 and set(thinned) <= set(keys)
    # A blurred stretch longer than the window: the first sharp frame after it.
    sharp[40:48] = 5.0
    keys = select_frames(sharp, step, FrameOptions(min_baseline=0.05, window=3))
    assert not set(keys) & set(range(40, 48)) and 48 in keys
    # Fast motion (every step already a baseline) keeps every sharp frame.
    fast = np.full(30, 0.08)
    assert select_frames(np.full(30, 100.0), fast, FrameOptions(min_baseline=0.05)) == list(range(30))
    # A tracking loss (inf step) starts a new keyframe at once.
    step[50] = np.inf
    assert 50 in select_frames(sharp, step, FrameOptions(min_baseline=0.5, window=1))


def _texture(rng, height, width):
    noise = rng.random((height, width)).astype(np.float32)
    tex = sum(cv2.GaussianBlur(noise, (0, 0), s) * s for s in (1, 3, 9))
    tex = (tex - tex.min()) / (tex.max() - tex.min()) * 255
    return cv2.cvtColor(tex.astype(np.uint8), cv2.COLOR_GRAY2BGR)


@pytest.fixture
def pan_video(tmp_path):
    """A camera panning over a texture at SHIFT px per frame, some frames badly blurred."""
    rng = np.random.default_rng(0)
    tex = _texture(rng, 160, 60 * SHIFT + 200)
    path = tmp_path / "pan.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 12.5, (200, 150))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG video")
    for i in range(60):
        frame = np.ascontiguousarray(tex[5:155, i * SHIFT : i * SHIFT + 200])
        if i in BLURRED:
            frame = cv2.GaussianBlur(frame, (0, 0), 6)
        writer.write(frame)
    writer.release()
    return path


def test_scores_follow_motion_and_blur(pan_video):
    sharp, step = score_frames(pan_video, FrameOptions(analysis_width=200))
    assert len(sharp) == 60
    diagonal = np.hypot(200, 150)
    clean = [i for i in range(1, 60) if i not in BLURRED and i - 1 not in BLURRED]
    assert np.allclose(step[clean] * diagonal, SHIFT, atol=0.5)  # flow measures the pan
    assert sharp[sorted(BLURRED)].max() < 0.3 * np.median(sharp)
    keys = select_frames(sharp, step, FrameOptions(min_baseline=0.1))
    assert not set(keys) & BLURRED
    gaps = np.diff(keys) * SHIFT / diagonal  # true baseline between kept frames
    assert gaps.min() >= 0.1 - 1e-9 and gaps.max() <= 0.1 + (5 + len(BLURRED)) * SHIFT / diagonal + 1e-9
    assert len(keys) >= 6


def test_video_input_writes_selected_frames(pan_video, tmp_path):
    from ghsplat_jax.sfm.pipeline import SfmOptions, resolve_input

    out = tmp_path / "out"
    options = SfmOptions(frame_options=FrameOptions(min_baseline=0.1, analysis_width=200), progress=False)
    timings = {}
    root, names, info = resolve_input(pan_video, out, options, timings)
    assert root == out / "frames"
    assert names == sorted(p.name for p in root.iterdir())
    assert info["num_frames"] == 60 and info["num_selected"] == len(names) >= 6
    assert [int(n[6:12]) for n in names] == info["selected_indices"]
    assert cv2.imread(str(root / names[0])).shape == (150, 200, 3)
    assert "frame_selection" in timings


def test_frame_folder_is_thinned_in_place(pan_video, tmp_path):
    from ghsplat_jax.sfm.frames import iter_frames
    from ghsplat_jax.sfm.pipeline import SfmOptions, resolve_input

    folder = tmp_path / "frames"
    folder.mkdir()
    for i, frame in enumerate(iter_frames(pan_video)):
        cv2.imwrite(str(folder / f"{i:04d}.png"), frame)
    options = SfmOptions(select_frames=True, progress=False,
                         frame_options=FrameOptions(min_baseline=0.1, analysis_width=200))
    root, names, info = resolve_input(folder, tmp_path / "out", options, {})
    assert root == folder  # frames are used where they are, not copied
    assert info["num_frames"] == 60 and 6 <= len(names) < 20
    assert names == [f"{i:04d}.png" for i in info["selected_indices"]]
    assert not {f"{i:04d}.png" for i in BLURRED} & set(names)
