"""Pose refinement against pose noise: the stability study's training cases (its synthetic row,
its [prepare] and [train] settings from experiments/stability.toml) trained from noisy training
poses with `pose_refine` off and on. Per run: the median and mean test PSNR (test views keep
their exact poses) and, with refinement, how far the refined training cameras are from the
true ones (centre error in % of the scene extent, and rotation error) against the noise put in.
Writes benchmarks/results/pose_refine.json and .png (--out).

    JAX_PLATFORMS=cpu python benchmarks/robustness/pose_refine.py --noise 0.01 0.02
    # on 2 cores, the runs in two processes, then the report from the rows they kept:
    python benchmarks/robustness/pose_refine.py --noise 0.02 --refine off --out /tmp/a.json &
    python benchmarks/robustness/pose_refine.py --noise 0.02 --refine on --no-baseline --out /tmp/b.json
    python benchmarks/robustness/pose_refine.py --noise 0.02
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py
from record import RESULTS, ROOT, machine_record  # noqa: E402


def centre(w2c) -> np.ndarray:
    w2c = np.asarray(w2c, np.float64)
    return -w2c[:3, :3].T @ w2c[:3, 3]


def rotation_deg(a, b) -> float:
    R = np.asarray(a, np.float64)[:3, :3] @ np.asarray(b, np.float64)[:3, :3].T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def pose_errors(views, truth: dict, extent: float) -> dict:
    """Median and max centre error (% of extent) and rotation error (deg) of `views` against `truth`."""
    c = [100 * np.linalg.norm(centre(v.camera.world_to_cam) - centre(truth[v.name])) / extent for v in views]
    r = [rotation_deg(v.camera.world_to_cam, truth[v.name]) for v in views]
    return {"centre_err_pct_median": float(np.median(c)), "centre_err_pct_max": float(np.max(c)),
            "rotation_err_deg_median": float(np.median(r)), "rotation_err_deg_max": float(np.max(r))}


def toward_truth(out: Path, cfg, truth: dict) -> dict:
    """How the refined centres moved against the move that undoes the noise: the median cosine
    of the two directions (1: straight toward the true centre) and the median length ratio."""
    from ghsplat_jax.train.pose import refined_world_to_cam
    from ghsplat_jax.train.run_dir import POSE_NAME, load_training_data

    pose = json.loads((out / POSE_NAME).read_text())
    noisy = {v.name: v.camera.world_to_cam for v in load_training_data(cfg).train}
    cos, ratio = [], []
    for r in pose["views"]:
        want = centre(truth[r["name"]]) - centre(noisy[r["name"]])
        got = centre(refined_world_to_cam(noisy[r["name"]], r["delta"], pose["scene_extent"])) - centre(
            noisy[r["name"]])
        cos.append(float(want @ got / max(np.linalg.norm(want) * np.linalg.norm(got), 1e-12)))
        ratio.append(float(np.linalg.norm(got) / max(np.linalg.norm(want), 1e-12)))
    return {"shift_cos_median": float(np.median(cos)), "shift_length_ratio_median": float(np.median(ratio))}


def _settings(config: dict) -> dict:
    """What a run's row depends on: the pose rates only when it refines."""
    pose = ("pose_lr_rot", "pose_lr_trans", "pose_refine_from")
    return {k: v for k, v in config.items() if config.get("pose_refine") or k not in pose}


def run_case(cfg, out: Path, truth: dict) -> dict:
    """One run's row, or the row saved in OUT/row.json by an earlier run of the same config."""
    from ghsplat_jax.io_utils import write_json

    saved = out / "row.json"
    got = json.loads(saved.read_text()) if saved.is_file() else {}
    if _settings(got.get("config") or {}) == _settings(cfg.to_dict()):
        row = got["row"]
    else:
        row = _run_case(cfg, out, truth)
        write_json(saved, {"config": cfg.to_dict(), "row": row})
    if cfg.pose_refine and cfg.pose_noise > 0:
        row["toward_truth"] = toward_truth(out, cfg, truth)
    return row


def _run_case(cfg, out: Path, truth: dict) -> dict:
    from ghsplat_jax.eval.evaluate import evaluate
    from ghsplat_jax.train.pose import refine_views
    from ghsplat_jax.train.run_dir import PER_VIEW_NAME, load_training_data
    from ghsplat_jax.train.trainer import train

    ds = load_training_data(cfg)  # pose_noise moves every training centre by exactly that fraction
    t = time.perf_counter()
    result = train(cfg, out, dataset=ds)
    seconds = time.perf_counter() - t
    metrics = evaluate(result.surfels, ds, cfg, out, result.train_seconds, result.steps, save_renders=False)
    per_view = json.loads((out / PER_VIEW_NAME).read_text())
    test = [r["psnr"] for r in per_view if r["split"] == "test"]
    row = dict(pose_noise=cfg.pose_noise, pose_refine=cfg.pose_refine, steps=result.steps, seconds=seconds,
               num_gaussians=metrics["num_gaussians"], test_psnr_median=float(np.median(test)),
               test_psnr_mean=metrics["test"]["psnr"], train_views=len(ds.train), test_views=len(ds.test))
    extent = float(ds.scene_extent)
    row["before"] = pose_errors(ds.train, truth, extent)
    if result.pose is not None:
        row["after"] = pose_errors(refine_views(ds.train, result.pose["views"], result.pose["scene_extent"]),
                                   truth, extent)
        row["corrections"] = result.pose["summary"]
    return row


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for refine, colour in ((False, "tab:gray"), (True, "tab:green")):
        sel = sorted((r for r in rows if r["pose_refine"] == refine), key=lambda r: r["pose_noise"])
        axes[0].plot([100 * r["pose_noise"] for r in sel], [r["test_psnr_median"] for r in sel], "o-", color=colour,
                     label="pose refinement " + ("on" if refine else "off"))
    on = sorted((r for r in rows if r["pose_refine"] and r["pose_noise"] > 0), key=lambda r: r["pose_noise"])
    x = np.arange(len(on))
    axes[1].bar(x - 0.2, [r["before"]["centre_err_pct_median"] for r in on], 0.4, color="tab:gray", label="given")
    axes[1].bar(x + 0.2, [r["after"]["centre_err_pct_median"] for r in on], 0.4, color="tab:green", label="refined")
    axes[1].set_xticks(x, [f"{100 * r['pose_noise']:g}%" for r in on])
    axes[0].set(xlabel="training pose noise (% of scene extent)", ylabel="median test PSNR (dB)")
    axes[1].set(xlabel="training pose noise", ylabel="median centre error (% of extent)")
    for ax in axes:
        ax.legend()
        ax.grid(alpha=0.3)
    fig.suptitle("Pose refinement on the stability study's row")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--noise", type=float, nargs="+", default=[0.01, 0.02], help="pose noise, fractions of the extent")
    p.add_argument("--refine", nargs="+", choices=("off", "on"), default=["off", "on"],
                   help="which runs (two processes can share the work: each run's row is kept in its folder)")
    p.add_argument("--no-baseline", action="store_true", help="no runs from exact poses")
    p.add_argument("--baseline-refine", action="store_true", help="also refine the exact poses (off: refinement "
                                                                    "runs only on noisy ones)")
    p.add_argument("--steps", type=int, help="training steps (default: the study's [train] steps)")
    p.add_argument("--lr", type=float, default=3e-3, help="pose_lr_rot and pose_lr_trans")
    p.add_argument("--refine-from", type=int, default=100, help="pose_refine_from")
    p.add_argument("--work", default=str(ROOT / "runs" / "pose_refine"), help="scratch folder for the runs")
    p.add_argument("--out", default=str(RESULTS / "pose_refine.json"))
    args = p.parse_args(argv)

    from ghsplat_jax.experiments.stability import prepare_row
    from ghsplat_jax.io_utils import code_revision, write_json
    from ghsplat_jax.train.config import TrainConfig, apply_overrides
    from ghsplat_jax.train.run_dir import load_training_data

    machine = machine_record()
    spec = tomllib.loads((ROOT / "experiments" / "stability.toml").read_text())
    work = Path(args.work)
    row = prepare_row(spec.get("prepare", {}), work / "row")
    base = apply_overrides(TrainConfig(), spec["train"], "stability.toml [train]")
    base = base.replace(data=str(row), progress=False, save_test_renders=False, checkpoint_every=0,
                        pose_lr_rot=args.lr, pose_lr_trans=args.lr, pose_refine_from=args.refine_from,
                        **({"steps": args.steps} if args.steps else {}))
    truth = {v.name: np.asarray(v.camera.world_to_cam) for v in load_training_data(base).train}
    rows = []
    for noise in ([] if args.no_baseline else [0.0]) + list(args.noise):
        for refine in [r == "on" for r in args.refine if noise > 0 or r == "off" or args.baseline_refine]:
            cfg = base.replace(pose_noise=noise, pose_refine=refine)
            r = run_case(cfg, work / f"noise{noise:g}_{'on' if refine else 'off'}", truth)
            rows.append(r)
            print(f"noise {100 * noise:g}% refine {'on ' if refine else 'off'}: test PSNR median "
                  f"{r['test_psnr_median']:.2f} dB, centre error {r['before']['centre_err_pct_median']:.2f}% -> "
                  f"{r.get('after', r['before'])['centre_err_pct_median']:.2f}% ({r['seconds']:.0f} s)", flush=True)
    out = Path(args.out)
    result = {"what": "stability-study row, training poses moved by pose_noise x extent (centres only), "
                      "pose_refine off vs on; test views exact",
              "settings": {"steps": base.steps, "pose_lr_rot": args.lr, "pose_lr_trans": args.lr,
                           "pose_refine_from": args.refine_from, "prepare": spec.get("prepare", {})},
              "rows": rows, "machine": machine, "code_revision": code_revision()}
    write_json(out, result)
    plot(rows, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
