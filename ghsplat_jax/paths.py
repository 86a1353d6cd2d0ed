"""Where the shared reference datasets live (never copied into the repo)."""

from __future__ import annotations

import os
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parent.parent


def datasets_root() -> Path:
    """$GHSPLAT_DATASETS, else ../shared/datasets beside the repository root."""
    return Path(os.environ.get("GHSPLAT_DATASETS", _REPO_ROOT.parent / "shared" / "datasets"))
