"""`ghsplat compose`: build a greenhouse scene PLY (and its tags file) from a layout TOML."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

HELP = "assemble row segments, floor/wall surfels and AprilTag markers from a layout TOML into one PLY and a tags file"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("layout", metavar="LAYOUT.toml", help="layout file (see ghsplat_jax/scene/layout.py)")
    p.add_argument("--out", required=True, metavar="scene.ply", help="output PLY (written atomically)")
    p.add_argument("--tags", metavar="tags.json",
                   help="marker ground-truth poses (default: beside --out as <stem>.tags.json when markers exist)")
    p.add_argument("--config", metavar="NAME", help="apply [configurations.NAME] (overrides the layout's choice)")
    p.add_argument("--viewer-compatible", action="store_true", help="3DGS-viewer layout: add scale_2 = log(1e-6)")
    p.add_argument("--summary", action="store_true", help="print a JSON summary (counts, footprints)")


def main(args) -> int:
    from ghsplat_jax.data.ply import PlyError, save_ply
    from ghsplat_jax.scene.compose import compose
    from ghsplat_jax.scene.layout import load_layout
    from ghsplat_jax.scene.tags import save_tags, tags_beside

    out = Path(args.out)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = lambda msg, *a, **k: print(f"ghsplat compose: warning: {msg}", file=sys.stderr)
            result = compose(load_layout(args.layout, args.config))
    except (PlyError, ValueError, FileNotFoundError) as exc:  # LayoutError is a ValueError
        print(f"ghsplat compose: error: {exc}", file=sys.stderr)
        return 2
    save_ply(result.surfels, out, viewer_compatible=args.viewer_compatible)
    if result.tags:
        tags_path = Path(args.tags) if args.tags else tags_beside(out)
        save_tags(tags_path, result.tags)
        print(f"ghsplat compose: wrote {len(result.tags)} marker poses to {tags_path}", file=sys.stderr)
    print(f"ghsplat compose: wrote {out} ({result.surfels.num} surfels)", file=sys.stderr)
    if args.summary:
        print(json.dumps(result.summary(), indent=2))
    return 0
