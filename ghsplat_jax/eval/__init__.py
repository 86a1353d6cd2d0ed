"""Evaluation: image metrics and per-run evaluation with renders (experiments/ collects the
runs into reports and charts)."""

from ghsplat_jax.eval.metrics import image_metrics, summarize

__all__ = ["image_metrics", "summarize"]
