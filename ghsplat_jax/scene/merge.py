"""Merge surfel sets: one SH degree (pad with zeros or truncate, said in a warning), and
no silent mixing of 3DGS files (three scales, flattened on read) with 2DGS ones."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ghsplat_jax.core.surfels import Surfels

POLICIES = ("pad", "truncate")


class MixedFormatError(ValueError):
    """3DGS and 2DGS files merged without the explicit flag."""


def set_sh_degree(s: Surfels, degree: int) -> Surfels:
    """Zero-pad (higher bands contribute nothing) or truncate (drop the highest bands)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0-3, got {degree}")
    s = s.to_numpy()
    k = (degree + 1) ** 2 - 1
    rest = s.sh_rest
    if rest.shape[1] >= k:
        rest = rest[:, :k]
    else:
        rest = np.concatenate([rest, np.zeros((s.num, k - rest.shape[1], 3), rest.dtype)], axis=1)
    return Surfels(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh_dc,
                   np.ascontiguousarray(rest))


def common_degree(degrees: list[int], policy: str) -> int:
    if policy not in POLICIES:
        raise ValueError(f"SH policy must be one of {POLICIES}, got {policy!r}")
    return max(degrees) if policy == "pad" else min(degrees)


def merge(parts: list[Surfels], policy: str = "pad", names: list[str] | None = None,
          degree: int | None = None) -> Surfels:
    """Concatenate surfel sets at one SH degree: the highest ('pad') or lowest ('truncate')
    of the inputs unless `degree` is given; a warning names every set that changes."""
    if not parts:
        raise ValueError("nothing to merge")
    names = names or [f"input {i}" for i in range(len(parts))]
    degrees = [p.sh_degree for p in parts]
    target = common_degree(degrees, policy) if degree is None else degree
    changed = [f"{n} (degree {d})" for n, d in zip(names, degrees) if d != target]
    if changed:
        verb = "zero-padded" if all(d < target for d in degrees if d != target) else (
            "truncated" if all(d > target for d in degrees if d != target) else "padded/truncated")
        warnings.warn(f"SH degrees differ ({sorted(set(degrees))}); {verb} to degree {target} "
                      f"(policy '{policy}'): {', '.join(changed)}", stacklevel=2)
    fixed = [set_sh_degree(p, target) for p in parts]
    return Surfels(*(np.concatenate([getattr(p, f) for p in fixed], axis=0)
                     for f in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")))


def load_many(paths: list[str | os.PathLike], allow_mixed_3dgs: bool = False, finite: bool = True
              ) -> tuple[list[Surfels], list[str]]:
    """Load PLYs; 3DGS files mixed with 2DGS ones raise MixedFormatError unless allowed.
    `finite=False` also loads surfels with NaN or Inf values (for callers that drop them)."""
    from ghsplat_jax.data.ply import is_3dgs_file, load_ply

    paths = [Path(p) for p in paths]
    kinds = {p: is_3dgs_file(p) for p in paths}  # raises PlyError for bad files
    three = [str(p) for p, k in kinds.items() if k]
    if three and len(three) < len(paths) and not allow_mixed_3dgs:
        raise MixedFormatError(
            f"refusing to mix 3DGS files (three scales: {', '.join(three)}) with 2DGS files; "
            f"their third axis is dropped on read, so pass the explicit flag to merge anyway")
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        return [load_ply(p, finite) for p in paths], [str(p) for p in paths]
