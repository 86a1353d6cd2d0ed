"""`ghsplat sfm`: camera poses and sparse points from photos or video, greenhouse-aligned.

    ghsplat sfm --images photos/ --out scene/                      # exhaustive + incremental
    ghsplat sfm --images walk.mp4 --out scene/ --matching sequential
    ghsplat sfm --images photos/ --out scene/ --camera-height 1.2  # metric scale

Exit status: 0 when at least --min-registered-fraction of the images registered,
3 when fewer did (or none), 4 when the fold diagnostics suspect a row mapped onto itself
(self-similar plants; the model is written for inspection only), 5 when the global mapper's
second estimate places views elsewhere than the model does (a bent model; written for inspection
only), 1 on bad input or settings.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "structure from motion (pycolmap) with greenhouse alignment and undistortion"



def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ghsplat_jax.sfm.disambiguate import METHODS
    from ghsplat_jax.sfm.pipeline import (
        CAMERA_MODELS,
        CAMERA_MODES,
        CAPTURE_ORDERS,
        MAPPERS,
        MATCHERS,
        SfmOptions,
    )

    parser.add_argument("--images", required=True, type=Path,
                        help="folder of images (subfolders allowed) or a video file")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder: images/, sparse/0/, sfm_report.json")
    g = parser.add_argument_group("structure from motion")
    g.add_argument("--matching", choices=MATCHERS, default="exhaustive",
                   help="exhaustive: every pair (default, as the paper); sequential: each frame "
                        "against its --overlap neighbours (video); spatial: needs EXIF GPS")
    g.add_argument("--mapper", choices=MAPPERS, default="incremental",
                   help="incremental (COLMAP) or global (GLOMAP)")
    g.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_RADIAL")
    g.add_argument("--camera-mode", choices=CAMERA_MODES, default="per-folder",
                   help="one shared camera per folder (default), one for all, or one per image")
    g.add_argument("--max-size", type=int, default=1600,
                   help="longest image side in pixels for extraction and output (0: full size)")
    g.add_argument("--max-features", type=int, default=8192, help="SIFT features per image")
    g.add_argument("--sift-peak-threshold", type=float, default=SfmOptions.sift_peak_threshold,
                   help="SIFT contrast threshold (default COLMAP's 0.02/3 = 0.00667); lower finds more features "
                        "on low-contrast foliage and registers more views, not always as accurately")
    g.add_argument("--overlap", type=int, default=10, help="neighbours per frame for sequential matching")
    g.add_argument("--min-registered-fraction", type=float, default=0.9,
                   help="exit with status 3 when fewer images than this fraction register")
    g.add_argument("--no-undistort", action="store_true",
                   help="skip undistortion (OUT/images, OUT/sparse/0 are then not written)")
    g.add_argument("--threads", type=int, default=1,
                   help="CPU threads; 1 (default) repeats exactly, -1 uses all cores (faster, but the "
                        "model can differ from run to run)")
    g.add_argument("--seed", type=int, default=0, help="random seed for repeatable runs")

    d = parser.add_argument_group("self-similar rows (disambiguation and fold checks)")
    d.add_argument("--disambiguate", choices=METHODS, default="auto",
                   help="auto (default): map every pair, and when the fold check flags the model map "
                        "again through the order filter; order: trust neighbour frames only and keep "
                        "a distant pair when its matches agree with the map of the neighbours; "
                        "tracks: drop pairs made of confusing tracks (no capture order needed); "
                        "none: plain pycolmap")
    d.add_argument("--capture-order", choices=CAPTURE_ORDERS, default="name",
                   help="name: sorted file names are the shooting order (frame folders, video); "
                        "none: unknown (no order filter: auto falls back to tracks; fewer fold checks)")
    d.add_argument("--disambiguate-window", type=int, default=None,
                   help="order filter: frames this many apart or fewer are trusted (default 1)")
    d.add_argument("--loop", action="store_true",
                   help="the capture closes a loop: the last frame is a neighbour of the first")
    d.add_argument("--no-fold-check", action="store_true",
                   help="report the fold diagnostics but do not fail the run on them")
    d.add_argument("--no-cross-check", action="store_true",
                   help="keep views that, re-localised with themselves left out, land elsewhere")
    d.add_argument("--no-second-estimate", action="store_true",
                   help="do not hold the model against the global mapper's estimate from the pairs it "
                        "confirms (a model the two place differently ends 'inconsistent', exit 5)")

    v = parser.add_argument_group("video and frame folders")
    v.add_argument("--select-frames", action="store_true",
                   help="thin a folder of video frames (always done for a video file)")
    v.add_argument("--min-baseline", type=float, default=0.05,
                   help="optical flow between kept frames, as a fraction of the image diagonal")
    v.add_argument("--blur-fraction", type=float, default=0.3,
                   help="drop frames less sharp than this times the median sharpness")
    v.add_argument("--max-frames", type=int, default=None, help="keep at most this many frames")

    a = parser.add_argument_group("alignment")
    a.add_argument("--align", choices=("greenhouse", "none"), default="greenhouse",
                   help="greenhouse: z up, row along +x, open end toward +x")
    a.add_argument("--align-config", type=Path, default=None,
                   help="TOML or JSON with any of: rotation (3x3, new_from_old), yaw_deg, flip, "
                        "scale, camera_height, known_distance ([image_a, image_b, metres])")
    a.add_argument("--align-rotation", type=float, nargs=9, metavar="R", default=None,
                   help="manual 3x3 rotation new_from_old, row-major (replaces the estimate)")
    a.add_argument("--align-yaw", type=float, default=None, help="extra turn about z, degrees")
    a.add_argument("--align-flip", action="store_true", help="turn 180 degrees about z")
    a.add_argument("--scale", type=float, default=None, help="explicit metric scale factor")
    a.add_argument("--camera-height", type=float, default=None,
                   help="true mean camera height above the ground in metres (sets the scale)")
    a.add_argument("--known-distance", nargs=3, metavar=("IMAGE_A", "IMAGE_B", "METRES"),
                   default=None, help="true distance between two cameras (sets the scale)")

    parser.add_argument("--verbose", action="store_true", help="show pycolmap's own log")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def build_options(args: argparse.Namespace):
    """SfmOptions from parsed arguments (the config file first, flags override it)."""
    import dataclasses

    import numpy as np

    from ghsplat_jax.sfm.align import AlignOptions, load_align_config
    from ghsplat_jax.sfm.disambiguate import DisambiguateOptions
    from ghsplat_jax.sfm.frames import FrameOptions
    from ghsplat_jax.sfm.pipeline import SfmOptions

    config = load_align_config(args.align_config)
    rotation = args.align_rotation if args.align_rotation is not None else config.get("rotation")
    known = args.known_distance or config.get("known_distance")
    if known is not None:
        if len(known) != 3:
            raise ValueError("known_distance needs [image_a, image_b, metres]")
        try:
            known = (str(known[0]), str(known[1]), float(known[2]))
        except ValueError as exc:
            raise ValueError(f"--known-distance: {known[2]!r} is not a distance in metres") from exc
    align = AlignOptions(
        rotation=None if rotation is None else np.asarray(rotation, float).reshape(3, 3),
        yaw_deg=float(args.align_yaw if args.align_yaw is not None else config.get("yaw_deg", 0.0)),
        flip=bool(args.align_flip or config.get("flip", False)),
        scale=args.scale if args.scale is not None else config.get("scale"),
        camera_height=args.camera_height if args.camera_height is not None else config.get("camera_height"),
        seed=args.seed,
    )
    frames = FrameOptions(min_baseline=args.min_baseline, blur_fraction=args.blur_fraction,
                          max_frames=args.max_frames)
    disambiguation = DisambiguateOptions(cyclic=args.loop)
    if args.disambiguate_window is not None:
        disambiguation = dataclasses.replace(disambiguation, window=args.disambiguate_window)
    return SfmOptions(
        disambiguate=args.disambiguate, capture_order=args.capture_order,
        disambiguate_options=disambiguation, fold_check=not args.no_fold_check,
        cross_check=not args.no_cross_check, second_estimate=not args.no_second_estimate,
        matching=args.matching, mapper=args.mapper, camera_model=args.camera_model,
        camera_mode=args.camera_mode, max_size=args.max_size or None,
        max_features=args.max_features, sift_peak_threshold=args.sift_peak_threshold,
        sequential_overlap=args.overlap,
        min_registered_fraction=args.min_registered_fraction, select_frames=args.select_frames,
        frame_options=frames, align=args.align, align_options=align,
        known_distance_names=known, undistort=not args.no_undistort,
        num_threads=args.threads, seed=args.seed, progress=not args.quiet,
    )


def main(args: argparse.Namespace) -> int:
    import pycolmap

    from ghsplat_jax.sfm.pipeline import SfmError, run_sfm
    from ghsplat_jax.sfm.report import EXIT_BAD_INPUT, summary_text, verdict

    pycolmap.logging.minloglevel = 0 if args.verbose else 2  # 2: errors only
    try:
        options = build_options(args)
        report = run_sfm(args.images, args.out, options)
    except (SfmError, ValueError) as exc:
        print(f"ghsplat sfm: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(summary_text(report))
    print(f"Report: {Path(args.out) / 'sfm_report.json'}")
    code, message = verdict(report["status"], report.get("fold_diagnostics", {}).get("reasons", []),
                            report.get("num_registered", 0), report["num_images"], options.min_registered_fraction,
                            args.out, report.get("diagnosis"), report.get("second_estimate"))
    if message:
        print(message, file=sys.stderr)
    return code
