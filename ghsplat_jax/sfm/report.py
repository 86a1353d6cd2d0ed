"""What the SfM report says: reconstruction statistics and plain advice when images fail."""

from __future__ import annotations

import math

import numpy as np

from ghsplat_jax.sfm import diagnose, second_estimate

# `ghsplat sfm` exit status by outcome (verdict)
EXIT_BAD_INPUT = 1
EXIT_TOO_FEW_REGISTERED = 3
EXIT_FOLDED = 4
EXIT_INCONSISTENT = 5


def _finite(value) -> float | None:
    """A JSON-safe float: None instead of NaN or inf (reports never hold NaNs)."""
    value = float(value)
    return value if math.isfinite(value) else None


def track_length_stats(lengths: np.ndarray) -> dict:
    if len(lengths) == 0:
        return {"mean": None, "median": None, "min": None, "max": None, "p90": None}
    return {
        "mean": _finite(np.mean(lengths)),
        "median": _finite(np.median(lengths)),
        "min": int(np.min(lengths)),
        "max": int(np.max(lengths)),
        "p90": _finite(np.percentile(lengths, 90)),
    }


def reconstruction_stats(reconstruction) -> dict:
    """Point count, mean reprojection error (px), track lengths, observations per image."""
    lengths = np.array([p.track.length() for p in reconstruction.points3D.values()], int)
    return {
        "num_points3D": int(reconstruction.num_points3D()),
        "mean_reprojection_error_px": _finite(reconstruction.compute_mean_reprojection_error()),
        "track_length": track_length_stats(lengths),
        "mean_observations_per_image": _finite(reconstruction.compute_mean_observations_per_reg_image()),
    }


def match_graph_stats(graph) -> dict:
    """How many other photos each photo matched (verified pairs of a `MatchGraph`): a chain
    (about two partners each) gives tracks of two views, which incremental mapping cannot grow."""
    partners = np.zeros(len(graph.names), int)
    for i, j in graph.pairs:
        partners[i] += 1
        partners[j] += 1
    return {
        "num_pairs": len(graph.pairs),
        "partners_median": _finite(np.median(partners)) if len(partners) else None,
        "partners_min": int(partners.min()) if len(partners) else None,
        "unmatched_images": [name for name, k in zip(graph.names, partners) if k == 0],
        "keypoints_median": _finite(np.median([len(k) for k in graph.keypoints])) if graph.keypoints else None,
    }


def failure_advice(options, num_images: int, num_registered: int, graph_stats: dict | None = None) -> list[str]:
    """What to try when SfM registered too few images, most likely fix first."""
    tips = []
    chain = bool(graph_stats) and graph_stats["partners_median"] is not None and graph_stats["partners_median"] <= 2
    if chain:
        tips.append(f"each photo matched only {graph_stats['partners_median']:g} others (median): SfM maps "
                    "points seen in three or more photos, so take photos closer together (each should "
                    "overlap the next two by 60-80%; for video lower --min-baseline)")
    unmatched = (graph_stats or {}).get("unmatched_images") or []
    if unmatched:
        tips.append(f"{len(unmatched)} photos matched no other photo ({', '.join(unmatched[:5])}"
                    f"{', ...' if len(unmatched) > 5 else ''}): they share no view with the rest")
    features = (graph_stats or {}).get("keypoints_median")
    if features is not None and features < 0.5 * options.max_features:
        tips.append(f"the photos gave a median of {features:g} SIFT features each (--max-features allows "
                    f"{options.max_features}): a lower --sift-peak-threshold (now {options.sift_peak_threshold:.3g}, "
                    "e.g. a third of it) finds more on low-contrast foliage; check the model's accuracy, as "
                    "weaker views register too")
    if options.matching != "sequential":
        tips.append("video or an ordered walk along the row: try --matching sequential "
                    f"(each frame against its {options.sequential_overlap} neighbours)")
    else:
        tips.append("try --matching exhaustive (every pair) or raise --overlap")
    if not chain:
        tips.append("capture with more overlap between neighbouring views (60-80%); for video "
                    "lower --min-baseline so more frames are kept")
    if options.max_size is None or options.max_size > 1000:
        tips.append("try smaller images, e.g. --max-size 1000 (less noise, fewer foliage mismatches)")
    else:
        tips.append("try larger images (raise --max-size) or more features (--max-features)")
    tips.append("try the other mapper (--mapper global or --mapper incremental)")
    if options.camera_mode != "per-image":
        tips.append("if the images come from different cameras or zoom settings, use --camera-mode per-image")
    if num_registered == 0 and num_images < 5:
        tips.insert(0, f"only {num_images} images: SfM needs several overlapping views")
    return tips


def summary_text(report: dict) -> str:
    """A few plain lines for the terminal."""
    n, k = report["num_images"], report.get("num_registered", 0)
    lines = []
    frames = report.get("frame_selection")
    if frames:
        lines.append(f"Selected {frames['num_selected']} of {frames['num_frames']} frames "
                     f"(sharp, at least {frames['min_baseline']} of the diagonal apart).")
    lines.append(f"Registered {k} of {n} images ({100.0 * k / max(n, 1):.0f}%).")
    if report.get("unreadable_images"):
        lines.append(f"Could not read: {', '.join(report['unreadable_images'][:20])}.")
    missing = report.get("unregistered_images", [])
    if missing:
        shown = ", ".join(missing[:20]) + (f" and {len(missing) - 20} more" if len(missing) > 20 else "")
        lines.append(f"Not registered: {shown}.")
    if report.get("num_reconstructions", 0) > 1:
        lines.append(f"The images split into {report['num_reconstructions']} separate models "
                     f"(sizes {report['reconstruction_sizes']}); the largest was kept.")
    if report.get("mean_reprojection_error_px") is not None:
        lines.append(f"{report['num_points3D']} points, mean reprojection error "
                     f"{report['mean_reprojection_error_px']:.3f} px, mean track length "
                     f"{report['track_length']['mean']:.2f}.")
    lines.extend(_fold_lines(report))
    check = report.get("cross_check")
    if check:
        dropped = check.get("dropped", [])
        lines.append(f"Cross-check: {check['num_confirmed']} of {check['num_views'] + len(dropped)} views re-localised "
                     "with themselves left out"
                     + (f"; {len(dropped)} landed elsewhere or could not be confirmed and were left out "
                        f"({', '.join(dropped[:10])}{', ...' if len(dropped) > 10 else ''})."
                        if dropped else "; none lands elsewhere."))
    if report.get("second_estimate"):
        lines.append("Second estimate: " + second_estimate.summary(report["second_estimate"]) + ".")
    alignment = report.get("alignment", {})
    if alignment.get("method") == "greenhouse":
        lines.append(f"Aligned: up from {alignment['up_source']}, row from {alignment['row_source']}, "
                     f"row end by {alignment['sign_rule']}, scale {alignment['scale']:.4g} "
                     f"({alignment['scale_source']}).")
    if report.get("diagnosis"):
        lines.append("Why " + ("so few images registered:" if report.get("status") in ("partial", "failed")
                               else "some images were not registered:"))
        lines.extend(f"  - {line}" for line in diagnose.lines(report["diagnosis"]))
    if report.get("advice"):
        lines.append("What to try:")
        lines.extend(f"  - {tip}" for tip in report["advice"])
    timings = report.get("timings_s", {})
    if timings:
        lines.append("Timings: " + ", ".join(f"{k} {v:.1f}s" for k, v in timings.items()))
    return "\n".join(lines)


def _fold_lines(report: dict) -> list[str]:
    """What the pair filter did and what the fold check found."""
    lines = []
    dis = report.get("disambiguation", {})
    if dis.get("method") == "auto" and dis.get("used", "none") != "none":
        lines.append(f"The plain model looked folded ({'; '.join(dis['first_pass']['reasons'])}); "
                     f"mapped again through the {dis['used']} pair filter.")
    elif dis.get("method") in ("order", "tracks"):
        lines.append(f"Pair filter {dis['method']}: {dis.get('num_pairs_removed', 0)} of "
                     f"{dis.get('num_pairs', 0)} verified pairs left out.")
    diag = report.get("fold_diagnostics")
    if diag and diag.get("trimmed_at_seams"):
        cut = diag["trimmed_at_seams"]
        lines.append(f"The model looked folded ({'; '.join(cut['reasons_before'])}); cut at its seams, "
                     f"{len(cut['dropped'])} views left out, the rest passes the fold check.")
    if diag:
        neighbours = diag.get("neighbour_pairs")
        if neighbours:
            lines.append(f"Fold check: {neighbours['num_contradicted']} of {neighbours['num_checked']} "
                         "neighbour pairs contradict the poses"
                         + (" (FOLD SUSPECTED)." if diag["fold_suspected"] else "."))
        elif diag["fold_suspected"]:
            lines.append("Fold check: FOLD SUSPECTED (" + "; ".join(diag["reasons"]) + ").")
    return lines


def verdict(status: str, fold_reasons: list[str], registered: int, num_images: int, needed: float,
            out, diagnosis: list[dict] | None = None, second: dict | None = None) -> tuple[int, str | None]:
    """(exit code, the message `ghsplat sfm` prints on stderr, or None) for a run's status; a
    refusal for too few registered images names the likely causes (`diagnosis`, diagnose.py), an
    inconsistent model the views the second estimate places elsewhere (`second`, second_estimate.py)."""
    if status == "ok":
        return 0, None
    if status == "inconsistent":
        why = second_estimate.summary(second) if second else "the global mapper's second estimate disagrees"
        return EXIT_INCONSISTENT, (f"ghsplat sfm: {why}; the model is in {out} for inspection only: do not train "
                                   "on it (--no-second-estimate to accept it)")
    if status == "folded":
        return EXIT_FOLDED, (f"ghsplat sfm: the model looks folded ({'; '.join(fold_reasons)}); it is in {out} for "
                             "inspection only: do not train on it (--no-fold-check to accept it)")
    message = (f"ghsplat sfm: only {registered} of {num_images} images registered "
               f"(below --min-registered-fraction {needed})")
    if diagnosis:
        message += "\nLikely cause" + ("s" if len(diagnosis) > 1 else "") + ":\n" + "\n".join(
            f"  - {line}" for line in diagnose.lines(diagnosis))
    return EXIT_TOO_FEW_REGISTERED, message
