"""Image I/O through OpenImageIO: 8/16-bit PNG/JPG/TIFF and float EXR, alpha, area resize.

Colour is returned *premultiplied* by alpha (the form EXR stores and the one that
filters correctly); `composite` puts it over a background. OpenImageIO is imported
lazily; cv2 serves as a fallback reader (no EXR) where OpenImageIO is not installed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ghsplat_jax.data.errors import DatasetError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".hdr", ".webp")


def is_image_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS and not path.name.startswith(".")


def list_images(folder: Path) -> list[Path]:
    """Image files directly in `folder`, in sorted file-name order."""
    return sorted((p for p in folder.iterdir() if is_image_file(p)), key=lambda p: p.name)


def _oiio():
    try:
        import OpenImageIO as oiio
    except ImportError:
        return None
    return oiio


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding pixels."""
    oiio = _oiio()
    if oiio is None:
        rgb, _ = read_image(path)
        return rgb.shape[1], rgb.shape[0]
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DatasetError(f"{path}: cannot read image ({_oiio_message(oiio.geterror())})")
    spec = inp.spec()
    inp.close()
    return spec.width, spec.height


def _oiio_message(text: str) -> str:
    text = " ".join(text.split())
    return text or "unknown error"


def _to_float(pixels: np.ndarray) -> np.ndarray:
    if np.issubdtype(pixels.dtype, np.integer):
        out = pixels.astype(np.float32)
        out *= np.float32(1.0 / np.iinfo(pixels.dtype).max)
        return out
    return pixels.astype(np.float32, copy=False)


def read_image(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(rgb (H,W,3) float32 premultiplied by alpha, alpha (H,W) float32 or None).

    Integer images map to [0, 1] by their type's maximum (8 or 16 bit); float images
    (EXR) keep their values. Grey images are replicated to three channels.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: image file not found")
    oiio = _oiio()
    if oiio is None:
        pixels, alpha_channel, unassociated = _read_cv2(path)
    else:
        pixels, alpha_channel, unassociated = _read_oiio(oiio, path)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    integer = np.issubdtype(pixels.dtype, np.integer)
    pixels = _to_float(pixels)
    if not integer and not np.all(np.isfinite(pixels)):
        raise DatasetError(f"{path}: image has non-finite pixel values")
    channels = pixels.shape[2]
    alpha = None
    if alpha_channel is not None and 0 <= alpha_channel < channels:
        alpha = np.ascontiguousarray(pixels[:, :, alpha_channel])
        colour = [c for c in range(channels) if c != alpha_channel]
    else:
        colour = list(range(channels))
    colour = colour[:3] if len(colour) >= 3 else colour[:1] * 3
    rgb = pixels[:, :, :3] if colour == [0, 1, 2] else pixels[:, :, colour]
    if alpha is not None and unassociated:
        rgb = np.multiply(rgb, alpha[:, :, None], dtype=np.float32)
    return np.ascontiguousarray(rgb), alpha


def _read_oiio(oiio, path: Path):
    # Ask for the data as stored: PNG keeps straight alpha (we premultiply in float,
    # more precisely than OpenImageIO's 8-bit premultiplication); EXR is premultiplied.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise DatasetError(f"{path}: cannot read image ({_oiio_message(oiio.geterror())})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(spec.format)
        if pixels is None or inp.has_error:
            raise DatasetError(f"{path}: corrupt or truncated image ({_oiio_message(inp.geterror())})")
        unassociated = spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 1
        alpha_channel = spec.alpha_channel
        if alpha_channel < 0 and spec.nchannels in (2, 4):  # unlabelled alpha (some TIFFs):
            # the last channel, straight for integer data as PNG/TIFF writers store it
            alpha_channel = spec.nchannels - 1
            unassociated = spec.format != oiio.FLOAT and spec.format != oiio.HALF
    finally:
        inp.close()
    return np.asarray(pixels), (alpha_channel if alpha_channel >= 0 else None), unassociated


def _read_cv2(path: Path):
    import cv2

    pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise DatasetError(f"{path}: cannot read image (OpenImageIO is not installed and OpenCV failed)")
    if pixels.ndim == 3 and pixels.shape[2] >= 3:  # OpenCV is BGR(A)
        pixels = pixels[:, :, [2, 1, 0] + list(range(3, pixels.shape[2]))]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    return pixels, (channels - 1 if channels in (2, 4) else None), True


def composite(rgb: np.ndarray, alpha: np.ndarray | None, background) -> np.ndarray:
    """Premultiplied colour over a constant background, clipped to [0, 1]."""
    out = np.array(rgb, np.float32)  # one full-size buffer, then in place
    if alpha is not None:
        bg = np.asarray(background, np.float32).reshape(1, 1, 3)
        out += (1.0 - alpha[:, :, None]) * bg
    return np.clip(out, 0.0, 1.0, out=out)


def resize_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-filtered resize to (width, height) (block means for integer factors)."""
    h, w = image.shape[:2]
    if (w, h) == (width, height):
        return image
    try:
        import cv2
    except ImportError:
        cv2 = None
    if cv2 is not None and (image.ndim == 2 or image.shape[2] <= 4):
        return cv2.resize(np.ascontiguousarray(image), (width, height), interpolation=cv2.INTER_AREA)
    fx, fy = w // width, h // height
    if fx * width != w or fy * height != h:
        raise DatasetError(f"resizing {w}x{h} to {width}x{height} needs OpenCV (cv2), which is not installed")
    blocks = image.reshape((height, fy, width, fx) + image.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float32)


def write_image(path: str | Path, image: np.ndarray, dtype: str | None = None) -> Path:
    """Write (H,W) or (H,W,C) floats in [0,1] as uint8/uint16/half/float, atomically.

    dtype defaults to float for EXR and uint8 otherwise. C=4 is colour with straight alpha:
    integer formats (PNG, TIFF) store straight alpha; EXR stores premultiplied colour, so
    `read_image` gives colour x alpha back from either. Non-finite values are refused.
    """
    import os
    import tempfile

    import OpenImageIO as oiio

    path = Path(path)
    dtype = dtype or ("float" if path.suffix.lower() == ".exr" else "uint8")
    image = np.asarray(image, np.float32)
    if not np.all(np.isfinite(image)):
        raise ValueError(f"refusing to write {path}: non-finite pixel values")
    if image.ndim == 2:
        image = image[:, :, None]
    formats = {"uint8": oiio.UINT8, "uint16": oiio.UINT16, "half": oiio.HALF, "float": oiio.FLOAT}
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], image.shape[2], formats[dtype])
    if image.shape[2] == 4:
        spec.alpha_channel = 3
        if dtype in ("half", "float"):
            image = np.concatenate([image[:, :, :3] * image[:, :, 3:], image[:, :, 3:]], axis=2)
        else:
            spec.attribute("oiio:UnassociatedAlpha", 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            raise OSError(f"{path}: cannot write image ({_oiio_message(oiio.geterror())})")
        ok = out.write_image(image)
        out.close()
        if not ok:
            raise OSError(f"{path}: cannot write image ({_oiio_message(out.geterror())})")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
