"""Photo beside render: each finished run's test views as its evaluation saved them
(RUN/renders/test/NAME.png), beside the photo at the size the run trained at and their
absolute difference (x3), captioned with the view's PSNR from RUN/per_view.json.

    python benchmarks/analysis/render_gallery.py runs/auto_real/aloe/auto runs/auto_real/llff_fern/auto \
        --out benchmarks/results/auto_recipe/real/gallery.png

Writes the PNG and a JSON beside it (the runs, their views and PSNR, the machine and revision).
Reads what the runs wrote and their datasets; renders nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/
from record import ROOT, machine_record  # noqa: E402


def run_views(run: Path) -> list[dict]:
    """The run's test views: {name, photo, render (HxWx3 float in [0, 1]), psnr}."""
    from ghsplat_jax.data.images import read_image
    from ghsplat_jax.train.config import load_config
    from ghsplat_jax.train.run_dir import load_training_data

    config = load_config(run / "config.toml").replace(progress=False)
    psnr = {r["name"]: r["psnr"] for r in json.loads((run / "per_view.json").read_text()) if r["split"] == "test"}
    views = []
    for view in load_training_data(config).test:
        path = run / "renders" / "test" / f"{Path(view.name).stem}.png"
        if not path.is_file():
            raise SystemExit(f"{run}: no test render {path.name} (evaluated without save_test_renders?)")
        views.append({"name": view.name, "photo": np.asarray(view.image)[..., :3],
                      "render": read_image(path)[0][..., :3], "psnr": psnr.get(view.name)})
    return views


def draw(runs: dict[str, list[dict]], out: Path) -> None:
    """One row per view: photo, render, difference."""
    from matplotlib.figure import Figure

    from ghsplat_jax.io_utils import save_figure

    rows = [(label, v) for label, views in runs.items() for v in views]
    fig = Figure(figsize=(10, 2.6 * len(rows)))
    axes = fig.subplots(len(rows), 3, squeeze=False)
    for (label, v), ax in zip(rows, axes):
        diff = np.clip(3.0 * np.abs(v["photo"] - v["render"]), 0.0, 1.0)
        titles = (f"{label}, {v['name']}: photo", f"render ({v['psnr']:.2f} dB)", "|photo - render| x 3")
        for a, image, title in zip(ax, (v["photo"], v["render"], diff), titles):
            a.imshow(np.clip(image, 0.0, 1.0))
            a.set_title(title, fontsize=8)
            a.axis("off")
    fig.tight_layout()
    save_figure(fig, out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders (config.toml, per_view.json, renders/)")
    ap.add_argument("--out", type=Path, required=True, help="the PNG to write (a .json beside it)")
    args = ap.parse_args(argv)
    from ghsplat_jax.io_utils import code_revision, write_json

    # Labelled by folder relative to the checkout (SCENE/VARIANT alone can name two runs).
    folders = {(str(run.resolve().relative_to(ROOT)) if run.resolve().is_relative_to(ROOT) else str(run)): run
               for run in args.runs}
    runs = {label: run_views(run) for label, run in folders.items()}
    draw(runs, args.out)
    write_json(args.out.with_suffix(".json"), {
        "machine": machine_record(start_backend=False), "code_revision": code_revision(),
        "runs": {label: {"folder": label, "views": [{"name": v["name"], "psnr": v["psnr"]} for v in views]}
                 for label, views in runs.items()}})
    print(f"wrote {args.out} and {args.out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
