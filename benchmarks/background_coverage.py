"""How much a trained model covers the empty background of an object capture (RGBA test
images, e.g. NeRF-synthetic lego): rendered alpha over the pixels whose image alpha is ~0,
next to each test view's PSNR. A model that fills the background with surfels of the
background colour scores well on its training views and hides the object from new ones.

    python benchmarks/background_coverage.py runs/lego30k --name lego_background_unmasked

Works on finished runs (point_cloud.ply) and unfinished ones (the checkpoint). Writes
benchmarks/results/NAME.json and NAME.png (ground truth, render, |error| x 4 and rendered alpha
of the worst test views).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ghsplat_jax.io_utils import save_figure, write_json
from ghsplat_jax.raster.render import render
from ghsplat_jax.train.run_dir import load_run, load_training_data

RESULTS = Path(__file__).parent / "results"
EMPTY = 0.01  # image alpha below this is background
VISIBLE = 0.05  # rendered alpha above this over the background is a visible cover
PANEL_VIEWS = 3


def view_coverage(rgb: np.ndarray, alpha: np.ndarray, view) -> dict:
    empty = view.alpha < EMPTY
    mse = float(np.mean((rgb - view.image) ** 2))
    return dict(name=view.name, psnr=float(-10 * np.log10(max(mse, 1e-12))), background_fraction=float(empty.mean()),
                background_alpha_mean=float(alpha[empty].mean()) if empty.any() else 0.0,
                background_covered=float((alpha[empty] > VISIBLE).mean()) if empty.any() else 0.0)


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
    if not views or any(v.alpha is None for v in views):
        raise SystemExit(f"{args.run}: its test views have no alpha channel; nothing to measure")
    per_view, renders = [], []
    for view in views:
        out = render(surfels, view.camera, config.raster)
        rgb, alpha = np.asarray(out.rgb), np.asarray(out.alpha)
        per_view.append(view_coverage(rgb, alpha, view))
        renders.append((rgb, alpha))
    mean = {k: float(np.mean([v[k] for v in per_view])) for k in per_view[0] if k != "name"}
    result = dict(run=str(args.run), step=config.steps if finished else meta["step"],
                  finished=finished, surfels=int(surfels.num), normal_loss_alpha_mask=config.normal_loss_alpha_mask,
                  lambda_normal=config.lambda_normal, empty_below=EMPTY, visible_above=VISIBLE, mean=mean,
                  views=per_view)
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
          f"{mean['background_alpha_mean']:.3f}, covered {100 * mean['background_covered']:.1f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
