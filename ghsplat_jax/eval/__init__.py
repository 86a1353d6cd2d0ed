"""Evaluation: image metrics, per-run evaluation with renders, Table-1 reports, charts and
the experiment runner."""

from ghsplat_jax.eval.metrics import image_metrics, summarize

__all__ = ["image_metrics", "summarize"]
