"""Readings of a test curve: a run's test PSNR against its training seconds (the points of its
test_curve.jsonl, `elapsed_s` and `psnr` each, in training order).

Free of JAX, so the report scripts' README checks run without it.
"""

from __future__ import annotations


def psnr_at(curve: list[dict], seconds: float) -> float | None:
    """The last scored test PSNR at or before `seconds` of training (None: nothing scored by then)."""
    return next((p["psnr"] for p in reversed(curve) if p.get("elapsed_s") is not None and p["elapsed_s"] <= seconds),
                None)


def time_to(curve: list[dict], level: float) -> float | None:
    """Training seconds until the test PSNR first reached `level` (None: never on the curve)."""
    return next((p["elapsed_s"] for p in curve if p["psnr"] >= level), None)
