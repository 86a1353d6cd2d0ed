"""The one error type of the dataset readers."""

from __future__ import annotations


class DatasetError(ValueError):
    """A dataset that cannot be loaded as asked; the message names the file and the problem."""


class DatasetWarning(UserWarning):
    """Something skipped while loading (for example frames whose image is missing)."""
