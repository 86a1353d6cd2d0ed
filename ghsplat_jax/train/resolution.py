"""Fewer pixels a step: the training images at 1/2^k scale for the first steps (DashGaussian,
CVPR 2025), raised to full resolution at the pace of the images' spectral energy; and at full
resolution, optionally, windows of the images instead of whole ones.

Scales are powers of two and images are box-filtered (the mean of each 2^k x 2^k block; a
remainder of rows or columns is cropped), so a pixel of the small image covers exactly its
block and the intrinsics only scale: K' = diag(1/f, 1/f, 1) K. A window only moves the
principal point: K' = K - (x0, y0) on (cx, cy).
"""

from __future__ import annotations

import numpy as np


def box_downscale(images: np.ndarray, factor: int) -> np.ndarray:
    """(N,H,W,C) images averaged over factor x factor blocks (bottom and right remainders cropped)."""
    if factor == 1:
        return images
    n, h, w, c = images.shape
    hh, ww = h // factor, w // factor
    crop = images[:, :hh * factor, :ww * factor]
    return crop.reshape(n, hh, factor, ww, factor, c).mean(axis=(2, 4))


def scale_intrinsics(Ks: np.ndarray, factor: int) -> np.ndarray:
    """(N,3,3) intrinsics of images downscaled by `factor` (pixel centres at j + 0.5 stay exact)."""
    s = np.diag([1.0 / factor, 1.0 / factor, 1.0]).astype(np.float32)
    return np.einsum("ij,njk->nik", s, np.asarray(Ks, np.float32))


def energy_kept(images: np.ndarray, factor: int) -> float:
    """The fraction of the images' spectral energy (their mean removed) below the Nyquist
    frequency of a `factor`-times smaller image: what that scale can show of them."""
    gray = np.asarray(images, np.float64)[..., :3].mean(axis=-1)
    gray = gray - gray.mean(axis=(1, 2), keepdims=True)
    power = np.abs(np.fft.fft2(gray)) ** 2
    fy = np.abs(np.fft.fftfreq(gray.shape[1]))[:, None]
    fx = np.abs(np.fft.fftfreq(gray.shape[2]))[None, :]
    inside = (fy < 0.5 / factor) & (fx < 0.5 / factor)
    total = power.sum()
    return float(power[:, inside].sum() / total) if total > 0 else 1.0


def spectrum_schedule(images: np.ndarray, until: int, energy: float = 0.8, min_side: int = 32,
                      sample: int = 8) -> list[tuple[int, int]]:
    """[(first step, factor)] from the coarsest scale to 1: start at the coarsest power-of-two
    factor that keeps `energy` of the spectrum with images of at least `min_side` pixels; leave
    scale f at step `until` x (the energy f keeps), so each scale trains for the share of the
    energy it adds (the first scale for all it shows). Full resolution from `until`. `sample`
    images (evenly spaced) stand for all."""
    h, w = images.shape[1:3]
    pick = images[np.linspace(0, len(images) - 1, min(sample, len(images))).astype(int)]
    factors, f = [], 2
    while min(h, w) // f >= min_side:
        factors.append(f)
        f *= 2
    kept = {f: energy_kept(pick, f) for f in factors}
    start = next((f for f in reversed(factors) if kept[f] >= energy), None)
    if start is None or until <= 0:
        return [(0, 1)]
    coarse = [start >> k for k in range(start.bit_length() - 2)]  # start, ..., 4: the scales left before 2
    schedule = [(0, start)]
    for i, f in enumerate(coarse):  # leave f for f/2, strictly in order and before `until`
        leave = min(max(int(round(until * kept[f])), schedule[-1][0] + 1), until - (len(coarse) - i))
        schedule.append((leave, f // 2))
    return schedule + [(until, 1)]


def factor_at(schedule: list[tuple[int, int]], step: int) -> int:
    """The scale factor of `step` (0-based)."""
    factor = schedule[0][1]
    for first, f in schedule:
        if step >= first:
            factor = f
    return factor


def crop_windows(width: int, height: int, tiles: int) -> list[tuple[int, int, int, int]]:
    """tiles x tiles windows (x0, y0, w, h), row by row, all of one size (one compiled step),
    that together cover a width x height image: w = ceil(width / tiles), the first at the left
    edge, the last at the right, the others evenly between (they overlap by under a window's
    pixel when the size does not divide). tiles = 1: the whole image."""
    w, h = -(-width // tiles), -(-height // tiles)
    starts = lambda size, n: [round(i * (size - n) / (tiles - 1)) if tiles > 1 else 0  # noqa: E731
                              for i in range(tiles)]
    return [(x0, y0, w, h) for y0 in starts(height, h) for x0 in starts(width, w)]


def crop_stack(images: np.ndarray, Ks: np.ndarray, tiles: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(N x T windows (N*T,h,w,C), their intrinsics, w, h): window t of view v at index v*T + t."""
    n, height, width = images.shape[:3]
    windows = crop_windows(width, height, tiles)
    crops = np.stack([images[:, y0:y0 + h, x0:x0 + w] for x0, y0, w, h in windows], axis=1)
    shift = np.zeros((len(windows), 3, 3), np.float32)
    shift[:, 0, 2] = [x0 for x0, _, _, _ in windows]
    shift[:, 1, 2] = [y0 for _, y0, _, _ in windows]
    crop_Ks = np.asarray(Ks, np.float32)[:, None] - shift[None]
    _, _, w, h = windows[0]
    return crops.reshape((-1,) + crops.shape[2:]), crop_Ks.reshape(-1, 3, 3), w, h
