"""Dataset readers (COLMAP, NeRF transforms.json, LLFF), image I/O, train/test splits and
Gaussian PLY files (ply.py: training writes them, evaluation, scene tools and the simulator
read them).

    from ghsplat_jax.data import load_dataset
    ds = load_dataset("../shared/datasets/llff_fern", downscale=8)
    ds.train[0].image, ds.train[0].camera

pycolmap is not needed; OpenImageIO and cv2 are imported only when images are read.
"""

from ghsplat_jax.data.dataset import Dataset, View, detect_format, load_dataset
from ghsplat_jax.data.errors import DatasetError, DatasetWarning

__all__ = ["Dataset", "DatasetError", "DatasetWarning", "View", "detect_format", "load_dataset"]
