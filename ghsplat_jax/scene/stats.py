"""Per-file statistics of a surfel set, as a JSON-ready dict."""

from __future__ import annotations

import numpy as np

from ghsplat_jax.core.surfels import Surfels


def _histogram(values: np.ndarray, bins) -> dict:
    counts, edges = np.histogram(values, bins=bins)
    return {"edges": [round(float(e), 6) for e in edges], "counts": counts.astype(int).tolist()}


def statistics(s: Surfels, bins: int = 10) -> dict:
    """Count, SH degree, bounds (min/max and 1-99 % percentiles), opacity and scale histograms.

    Non-finite surfels are counted and left out of the other figures.
    """
    from ghsplat_jax.scene.edit import finite_mask

    s = s.to_numpy()
    ok = finite_mask(s)
    out = {"count": int(s.num), "non_finite": int((~ok).sum()), "sh_degree": int(s.sh_degree)}
    f = s.take(np.flatnonzero(ok))
    if f.num == 0:
        return out
    x = f.means.astype(np.float64)
    opacity = 1.0 / (1.0 + np.exp(-f.opacity_logits.astype(np.float64)))
    max_scale = np.exp(f.log_scales.astype(np.float64).max(axis=1))
    out["bounds"] = {"min": x.min(0).tolist(), "max": x.max(0).tolist(),
                     "p01": np.percentile(x, 1, axis=0).tolist(),
                     "p99": np.percentile(x, 99, axis=0).tolist()}
    out["opacity"] = {"mean": float(opacity.mean()), "median": float(np.median(opacity)),
                      "histogram": _histogram(opacity, np.linspace(0.0, 1.0, bins + 1))}
    log10 = np.log10(np.maximum(max_scale, 1e-12))
    lo, hi = np.floor(log10.min()), np.ceil(log10.max())
    out["max_scale_m"] = {"median": float(np.median(max_scale)), "max": float(max_scale.max()),
                          "log10_histogram": _histogram(log10, np.linspace(lo, max(hi, lo + 1), bins + 1))}
    return out
