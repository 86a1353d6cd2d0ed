"""Train/test splits: the dataset's own, or every N-th image in sorted file order."""

from __future__ import annotations

import numpy as np

from ghsplat_jax.data.errors import DatasetError

SPLITS = ("auto", "every", "dataset", "all")


def split_indices(
    names: list[str], predefined: list[str] | None, split: str = "auto", test_every: int = 8
) -> tuple[list[int], list[int], str]:
    """(train indices, test indices, rule used).

    auto: the dataset's own split where it has one (NeRF-synthetic train/test files),
    else "every". every: indices 0, N, 2N, ... of the names in sorted order are test
    views (the LLFF/NeRF/3DGS "llffhold" convention). dataset: the dataset's own or an
    error. all: every view trains, no test views.
    """
    if split not in SPLITS:
        raise DatasetError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    if split == "dataset" and predefined is None:
        raise DatasetError("split='dataset' asked for, but this dataset defines no train/test split")
    if split in ("auto", "dataset") and predefined is not None:
        train = [i for i, part in enumerate(predefined) if part != "test"]
        test = [i for i, part in enumerate(predefined) if part == "test"]
        return train, test, "dataset"
    if split == "all":
        return list(range(len(names))), [], "all"
    if int(test_every) != test_every or test_every < 1:
        raise DatasetError(f"test_every must be a positive integer, got {test_every!r}")
    order = sorted(range(len(names)), key=lambda i: names[i])
    test = sorted(order[:: int(test_every)])
    chosen = set(test)
    return [i for i in range(len(names)) if i not in chosen], test, "every"


def subsample(indices: list[int], max_views: int | None) -> list[int]:
    """At most `max_views` of `indices`, evenly spaced (an orbit stays an orbit)."""
    if max_views is None:
        return list(indices)
    if int(max_views) != max_views or max_views < 1:
        raise DatasetError(f"max_views must be a positive integer or None, got {max_views!r}")
    if len(indices) <= max_views:
        return list(indices)
    picks = np.unique(np.round(np.linspace(0, len(indices) - 1, int(max_views))).astype(int))
    return [indices[i] for i in picks]
