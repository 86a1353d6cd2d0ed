"""Image I/O through OpenImageIO: 8/16-bit PNG/JPG/TIFF and float EXR, alpha, area resize.

Colour is returned *premultiplied* by alpha (the form EXR stores and the one that
filters correctly); `composite` puts it over a background. OpenImageIO is imported
lazily and is the only image reader and writer (OpenCV misreads grey + alpha files).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ghsplat_jax.data.errors import DatasetError
from ghsplat_jax.io_utils import atomic_path

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".hdr", ".webp")


def is_image_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS and not path.name.startswith(".")


def list_images(folder: Path) -> list[Path]:
    """Image files directly in `folder`, in sorted file-name order."""
    return sorted((p for p in folder.iterdir() if is_image_file(p)), key=lambda p: p.name)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding pixels."""
    import OpenImageIO as oiio

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
    pixels, alpha_channel, unassociated = _read_oiio(path)
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


def _read_oiio(path: Path):
    import OpenImageIO as oiio

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
    """Write (H,W) or (H,W,C) pixels atomically; the file format comes from the suffix.

    The one image writer of the project. Integer arrays (uint8, uint16) are stored as they
    are; float arrays are values in [0, 1] for integer files (OpenImageIO rounds them) and
    any finite values for float files. `dtype` is the stored type: "uint8", "uint16",
    "half" or "float"; by default the array's own integer type, else float for EXR and
    uint8 otherwise. C=4 is colour with straight alpha: integer formats (PNG, TIFF) store it
    straight, EXR premultiplied, and `read_image` gives colour x alpha back from either. A
    single float channel is named Z (every such file here is a depth map). Non-finite values
    are refused.
    """
    import OpenImageIO as oiio

    path = Path(path)
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        image = image.astype(np.float32, copy=False)
        if not np.all(np.isfinite(image)):
            raise ValueError(f"refusing to write {path}: non-finite pixel values")
    dtype = dtype or (image.dtype.name if image.dtype.kind == "u" else
                      "float" if path.suffix.lower() == ".exr" else "uint8")
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
    elif image.shape[2] == 1 and dtype in ("half", "float"):
        spec.channelnames = ("Z",)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise OSError(f"{path}: cannot write image ({_oiio_message(oiio.geterror())})")
        ok = out.write_image(np.ascontiguousarray(image))
        out.close()
        if not ok:
            raise OSError(f"{path}: cannot write image ({_oiio_message(out.geterror())})")
    return path


def read_pixels(path: str | Path) -> np.ndarray:
    """The pixels of a file as stored (native dtype, not premultiplied; (H, W) for one
    channel): the exact inverse of `write_image` for integer arrays and float EXR."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise DatasetError(f"{path}: cannot read image ({_oiio_message(buf.geterror())})")
    pixels = buf.get_pixels(buf.spec().format)
    return pixels[..., 0] if pixels.shape[-1] == 1 else pixels
