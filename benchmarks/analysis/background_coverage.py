"""How much a trained model covers the empty background of an object capture (RGBA test
images, e.g. NeRF-synthetic lego): rendered alpha over the pixels whose image alpha is ~0,
next to each test view's PSNR. A model that fills the background with surfels of the
background colour scores well on its training views and hides the object from new ones.

    python benchmarks/analysis/background_coverage.py runs/lego30k --name lego_background_unmasked

`normal_loss_alpha_mask` is recorded as null for a run whose config predates the setting (its
code had no mask).

Works on finished runs (point_cloud.ply) and unfinished ones (the checkpoint). Writes
benchmarks/results/NAME.json and NAME.png (ground truth, render, |error| x 4 and rendered alpha
of the worst test views).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402

from ghsplat_jax.eval.metrics import COVERED_ABOVE, EMPTY_BELOW, background_cover, image_metrics
from ghsplat_jax.io_utils import save_figure, write_json
from ghsplat_jax.raster.render import render
from ghsplat_jax.train.config import settings_missing_from
from ghsplat_jax.train.run_dir import CONFIG_NAME, load_run, load_training_data

PANEL_VIEWS = 3


def panel(rows: list[np.ndarray], path: Path, title: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 3 * len(rows)))
    axes = fig.subplots(len(rows), 1, squeeze=False)[:, 0]
    for ax, row in zip(axes, rows):
        ax.imshow(np.clip(row, 0, 1))
        ax.axis("off")
    axes[0].set_title(title + "\nground truth | render | |error| x 4 | rendered alpha")
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="training run folder")
    ap.add_argument("--name", required=True, help="results name (benchmarks/results/NAME.json/.png)")
    ap.add_argument("--views", type=int, default=0, help="first N test views (0: all)")
    args = ap.parse_args(argv)

    config, surfels, meta, finished = load_run(args.run)
    dataset = load_training_data(config)
    views = dataset.test[: args.views or None]
    if not views:
        raise SystemExit(f"{args.run}: no test views")
    per_view, renders = [], []
    for view in views:
        out = render(surfels, view.camera, config.raster)
        rgb, alpha = np.asarray(out.rgb), np.asarray(out.alpha)
        cover = background_cover(alpha, view.alpha)
        if not cover:
            raise SystemExit(f"{args.run}: test view {view.name} has no alpha channel or no empty background; "
                             "nothing to measure")
        per_view.append(dict(name=view.name, **image_metrics(rgb, view.image), **cover))
        renders.append((rgb, alpha))
    mean = {k: float(np.mean([v[k] for v in per_view])) for k in per_view[0] if k != "name"}
    predates = settings_missing_from(Path(args.run) / CONFIG_NAME)  # the run's code had no such setting
    result = dict(run=str(args.run), step=config.steps if finished else meta["step"],
                  finished=finished, surfels=int(surfels.num), config_predates=predates,
                  normal_loss_alpha_mask=(None if "normal_loss_alpha_mask" in predates
                                          else config.normal_loss_alpha_mask),
                  lambda_normal=config.lambda_normal, empty_below=EMPTY_BELOW, covered_above=COVERED_ABOVE, mean=mean,
                  views=per_view, machine=machine_record())
    RESULTS.mkdir(exist_ok=True)
    write_json(RESULTS / f"{args.name}.json", result)
    worst = np.argsort([v["psnr"] for v in per_view])[:PANEL_VIEWS]
    rows = []
    for i in worst:
        (rgb, alpha), view = renders[i], views[i]
        err = np.repeat(np.abs(rgb - view.image).mean(-1, keepdims=True) * 4, 3, -1)
        rows.append(np.concatenate([view.image, rgb, err, np.repeat(alpha[..., None], 3, -1)], 1))
    panel(rows, RESULTS / f"{args.name}.png",
          f"{args.run} at step {result['step']}: test PSNR {mean['psnr']:.2f} dB, background covered "
          f"{100 * mean['background_covered']:.0f}% (worst {PANEL_VIEWS} views)")
    print(f"{args.name}: step {result['step']}, test PSNR {mean['psnr']:.2f} dB, background alpha "
          f"{mean['background_alpha']:.3f}, covered {100 * mean['background_covered']:.1f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
