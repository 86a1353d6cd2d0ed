"""Procedural textures (float32 RGB in [0, 1], shape (S, S, 3)).

Texture convention: u runs along image columns, v up the image (row 0 is v = 1), so a
texel is at (col, row) = (u * S, (1 - v) * S). Noise is FFT-filtered white noise, which
is periodic, so ground textures tile without seams.
"""

from __future__ import annotations

import numpy as np


def periodic_noise(rng: np.random.Generator, size: int, feature_px: float) -> np.ndarray:
    """(size, size) periodic smooth noise in [0, 1] with features about `feature_px` wide."""
    white = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    f2 = f[:, None] ** 2 + f[None, :] ** 2
    smooth = np.fft.ifft2(np.fft.fft2(white) * np.exp(-f2 * (np.pi * feature_px) ** 2 / 2)).real
    smooth -= smooth.min()
    return smooth / max(smooth.max(), 1e-12)


def fractal_noise(rng: np.random.Generator, size: int, feature_px: float, octaves: int = 4) -> np.ndarray:
    total, weight = np.zeros((size, size)), 0.0
    for k in range(octaves):
        amp = 0.5 ** k
        total += amp * periodic_noise(rng, size, max(feature_px / 2 ** k, 0.5))
        weight += amp
    return total / weight


def _mix(a, b, t):
    t = np.asarray(t)[..., None]
    return np.asarray(a) * (1 - t) + np.asarray(b) * t


def _uv_to_px(u, v, size):
    return (np.asarray(u) * size, (1 - np.asarray(v)) * size)


def leaf_texture(rng: np.random.Generator, size: int, lobes: int) -> np.ndarray:
    """A cucumber-like blade: mottled green, palmate main veins from the petiole junction,
    pinnate secondary veins and a fine reticulate network.

    Matches the leaf mesh UVs (geometry.leaf_blade): the junction at (u, v) = (0.5, 0.04),
    the tip toward v = 1.
    """
    import cv2

    s = size
    base = np.array([0.20, 0.42, 0.12]) * rng.uniform(0.9, 1.1, 3)
    light = np.array([0.36, 0.58, 0.20])
    mottle = fractal_noise(rng, s, s / 10)
    img = _mix(base * 0.8, base * 1.15, mottle)

    # fine reticulate network: thin ridges of band-passed noise
    net = periodic_noise(rng, s, s / 40)
    ridge = np.exp(-((net - 0.5) / 0.035) ** 2)
    img = _mix(img, light * 0.9, 0.25 * ridge)

    veins = np.zeros((s, s), np.float32)
    origin = np.array(_uv_to_px(0.5, 0.04, s))
    spread = np.deg2rad(np.linspace(-110, 110, lobes)) + rng.normal(0, 0.04, lobes)
    for angle in spread:
        length = 0.9 * s * (1.0 - 0.35 * abs(angle) / np.pi)
        direction = np.array([np.sin(angle), -np.cos(angle)])  # image y points down
        end = origin + direction * length
        cv2.line(veins, tuple(np.round(origin * 16).astype(int)), tuple(np.round(end * 16).astype(int)),
                 1.0, max(1, s // 90), cv2.LINE_AA, shift=4)
        # pinnate secondaries on both sides, shorter toward the vein's end
        for t in np.arange(0.12, 0.9, 0.11):
            p = origin + direction * length * t
            for side in (-1, 1):
                a2 = angle + side * np.deg2rad(rng.uniform(35, 50))
                d2 = np.array([np.sin(a2), -np.cos(a2)])
                q = p + d2 * length * (1 - t) * rng.uniform(0.25, 0.4)
                cv2.line(veins, tuple(np.round(p * 16).astype(int)), tuple(np.round(q * 16).astype(int)),
                         0.6, 1, cv2.LINE_AA, shift=4)
    veins = cv2.GaussianBlur(veins, (0, 0), max(s / 400, 0.5))
    img = _mix(img, light * 1.1, np.clip(veins, 0, 1) * 0.75)
    return np.clip(img, 0, 1).astype(np.float32)


def soil_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """Brown soil with darker damp patches and small stones; tiles seamlessly."""
    import cv2

    s = size
    img = _mix([0.33, 0.24, 0.16], [0.48, 0.37, 0.26], fractal_noise(rng, s, s / 6, 5))
    img = _mix(img, [0.24, 0.18, 0.12], 0.5 * np.clip((periodic_noise(rng, s, s / 8) - 0.55) * 4, 0, 1))  # damp
    img = img * (0.85 + 0.3 * periodic_noise(rng, s, 1.0)[..., None])  # grain
    stones = np.zeros((s, s), np.float32)
    for _ in range(s // 2):
        c = rng.uniform(0, s, 2)
        axes = rng.uniform(0.6, 2.5, 2) * s / 256
        shade = rng.uniform(0.3, 1.0)
        for dx in (-s, 0, s):  # draw wrapped copies so the tile stays seamless
            for dy in (-s, 0, s):
                cv2.ellipse(stones, (int(c[0] + dx), int(c[1] + dy)),
                            (max(1, int(axes[0])), max(1, int(axes[1]))),
                            rng.uniform(0, 180), 0, 360, shade, -1, cv2.LINE_AA)
    img = _mix(img, [0.62, 0.58, 0.52], stones * 0.8)
    return np.clip(img, 0, 1).astype(np.float32)


def cover_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """White woven ground cover with dirt smudges."""
    s = size
    y, x = np.mgrid[0:s, 0:s] / s
    weave = 0.5 + 0.25 * np.sin(2 * np.pi * 48 * x) * np.sign(np.sin(2 * np.pi * 48 * y))
    img = _mix([0.70, 0.71, 0.70], [0.86, 0.87, 0.85], weave)
    dirt = fractal_noise(rng, s, s / 5)
    return np.clip(_mix(img, [0.45, 0.40, 0.33], 0.5 * np.clip(dirt - 0.45, 0, 1) * 2), 0, 1).astype(np.float32)


def plastic_texture(rng: np.random.Generator, size: int, colour) -> np.ndarray:
    """Grow-bag plastic: a flat colour with soft wrinkles and streaks."""
    s = size
    wrinkles = fractal_noise(rng, s, s / 8)
    streaks = periodic_noise(rng, s, s / 30)
    img = np.asarray(colour)[None, None] * (0.82 + 0.2 * wrinkles[..., None] + 0.06 * streaks[..., None])
    return np.clip(img, 0, 1).astype(np.float32)


def stem_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """Green stem with lengthwise ridges (v runs along the stem)."""
    s = size
    y, x = np.mgrid[0:s, 0:s] / s
    ridges = 0.5 + 0.5 * np.sin(2 * np.pi * 6 * x + 0.8 * periodic_noise(rng, s, s / 8))
    img = _mix([0.22, 0.40, 0.13], [0.42, 0.60, 0.24], 0.6 * ridges + 0.4 * fractal_noise(rng, s, s / 12))
    return np.clip(img, 0, 1).astype(np.float32)


def metal_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """Galvanised steel: grey with spangles."""
    s = size
    img = _mix([0.48, 0.50, 0.52], [0.70, 0.72, 0.74], 0.5 * fractal_noise(rng, s, s / 10) +
               0.5 * (periodic_noise(rng, s, s / 25) > 0.5))
    return np.clip(img, 0, 1).astype(np.float32)


def flower_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """Yellow petals, a darker centre (centre of the texture is the flower centre)."""
    s = size
    y, x = (np.mgrid[0:s, 0:s] + 0.5) / s - 0.5
    r = np.hypot(x, y)
    img = _mix([0.98, 0.85, 0.15], [0.85, 0.62, 0.05], np.clip(1 - r / 0.15, 0, 1))
    img = img * (0.9 + 0.1 * periodic_noise(rng, s, s / 20)[..., None])
    return np.clip(img, 0, 1).astype(np.float32)


def tag_texture(tag_id: int, cell_px: int = 16) -> np.ndarray:
    """AprilTag 36h11 marker with two white cells of quiet zone around the black border.

    The black border spans 8 of the 12 cells, so a printed plate of side P carries a tag
    of (black-border) size P * 8 / 12.
    """
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, int(tag_id), 8 * cell_px, borderBits=1)
    plate = np.pad(marker, 2 * cell_px, constant_values=255).astype(np.float32) / 255.0
    plate = 0.04 + 0.92 * plate  # printed paper: neither pure black nor white
    return np.repeat(plate[..., None], 3, axis=-1)


TAG_PLATE_RATIO = 12 / 8  # plate side / black-border side
