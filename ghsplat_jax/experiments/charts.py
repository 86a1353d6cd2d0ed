"""Charts of a run set: PSNR against training time and against surfel count.

Each chart is a PNG and, beside it, the JSON of the series it plots (name.json), so the
numbers behind a picture can be read and checked. Figures are `matplotlib.figure.Figure`
objects: no pyplot, no global backend switch.
"""

from __future__ import annotations

import re
from pathlib import Path

from ghsplat_jax.experiments.labels import annotate_points
from ghsplat_jax.io_utils import machine_kind, save_figure, write_json

CHARTS = (  # file stem, x key, y key, x label, y label
    ("psnr_vs_time", "train_seconds", "psnr", "training time (s)", "PSNR (dB)"),
    ("psnr_vs_count", "num_gaussians", "psnr", "surfels", "PSNR (dB)"),
)


def scatter_series(rows: list[dict], x: str, y: str) -> dict[str, list[dict]]:
    """{variant: [{"scene", "x", "y"}, ...]} of the rows that have both values, variants sorted; a
    run on an accelerator also names its "device", since its times are not a CPU's."""
    series: dict[str, list[dict]] = {}
    for r in rows:
        if r.get(x) is not None and r.get(y) is not None:
            point = {"scene": r["scene"], "x": r[x], "y": r[y]}
            if r.get("device") not in (None, "cpu"):
                point["device"] = r["device"]
            series.setdefault(r.get("variant") or "", []).append(point)
    return dict(sorted(series.items()))


MARKERS = ("o", "s", "^", "D", "v", "P", "X")


def variant_style(i: int) -> dict:
    """The i-th series' colour and marker: 20 distinct colours (tab20's strong shades, then its
    light ones), and the markers in turn, so neighbouring series differ in shape as well."""
    from matplotlib import colormaps

    shade = (2 * i) % 20 + (i // 10) % 2
    return {"color": colormaps["tab20"](shade), "marker": MARKERS[i % len(MARKERS)]}


def scatter_figure(series: dict[str, list[dict]], xlabel: str, ylabel: str, title: str = "", log_x: bool = False):
    """One marker per run, one colour and marker per variant. Points are labelled by scene, or by
    variant when every point is of one scene (an ablation), where a scene label says nothing."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.6, 4.4), dpi=120)
    ax = fig.subplots()
    one_scene = len({p["scene"] for points in series.values() for p in points}) == 1
    xy, labels = [], []
    for i, (variant, points) in enumerate(series.items()):
        ax.scatter([p["x"] for p in points], [p["y"] for p in points], label=variant or None, s=36, zorder=3,
                   **variant_style(i))
        for p in points:
            label = variant if one_scene and variant else p["scene"]
            labels.append(f"{label} ({p['device']})" if "device" in p else label)
            xy.append((p["x"], p["y"]))
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if title:
        ax.set_title(title)
    if any(series):
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the points, not over them
    fig.tight_layout()
    annotate_points(ax, xy, labels)
    return fig


def split_label(ylabel: str, rows: list[dict]) -> str:
    """The y label with the views it was measured on: "PSNR (dB), test views"."""
    splits = sorted({r["split"] for r in rows if r.get("split")})
    return f"{ylabel}, {' or '.join(splits)} views" if splits else ylabel


TIME_AXES = ("train_seconds",)  # an axis in seconds compares one kind of machine only


def device_slug(device: str) -> str:
    """A device's name as a file name's part: "NVIDIA H200" -> "nvidia_h200"."""
    return re.sub(r"[^a-z0-9]+", "_", device.lower()).strip("_")


def by_machine(rows: list[dict]) -> dict[str, list[dict]]:
    """{kind of machine (io_utils.machine_kind): rows}, the kind with most CPU rows first."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(machine_kind(r, rows), []).append(r)
    return dict(sorted(groups.items(), key=lambda kv: ((kv[1][0].get("device") or "cpu") != "cpu", -len(kv[1]))))


def write_charts(rows: list[dict], folder, title: str = "") -> list[Path]:
    """The PNG charts of CHARTS that have data, each with its series as JSON beside it. A time
    axis draws one kind of machine (by_machine): the first kind's runs in STEM.png, another's in
    STEM_KIND.png (a GPU's seconds against a CPU's, or one CPU's against another's, compare
    nothing but the machines)."""
    folder = Path(folder)
    made = []
    for stem, x, y, xlabel, ylabel in CHARTS:
        groups = by_machine(rows) if x in TIME_AXES else {"": rows}
        for i, (kind, part) in enumerate(groups.items()):
            series = scatter_series(part, x, y)
            if not series:
                continue
            name = stem if i == 0 else f"{stem}_{device_slug(kind)}"
            label = title if x not in TIME_AXES or len(groups) == 1 else f"{title}: runs on {kind}"
            # the one kind of machine a time axis draws
            meta = {"device": part[0].get("device") or "cpu", "machine": kind} if x in TIME_AXES else {}
            write_json(folder / f"{name}.json", {"x": x, "y": y, "title": label, **meta, "series": series})
            fig = scatter_figure(series, xlabel, split_label(ylabel, part), label, log_x=True)
            made.append(save_figure(fig, folder / f"{name}.png", dpi=120))
    return made


def pareto_front(points: list[tuple[float, float]]) -> list[bool]:
    """Which (cost, quality) points no other point beats: cost no higher and quality no lower,
    one of them strictly."""
    return [not any(c2 <= c and q2 >= q and (c2 < c or q2 > q) for c2, q2 in points) for c, q in points]


AXIS_LABELS = {"step_seconds": "median step time (s)", "interleaved_step_seconds": "median step time, interleaved (s)",
               "train_seconds": "training time (s)", "psnr": "PSNR (dB)"}


def pareto_figure(points: list[tuple[float, float]], variants: list[str], on_front: list[bool], xlabel: str,
                  ylabel: str, title: str, reference: str = "default"):
    """(cost, quality) per variant on a log cost axis: the front as a step line, the points off it
    faded, the `reference` variant ringed, each point labelled by its variant."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.4), dpi=120)
    ax = fig.subplots()
    front = sorted(p for p, f in zip(points, on_front) if f)
    ax.step([c for c, _ in front], [q for _, q in front], where="post", color="0.5", lw=1, label="Pareto front")
    for i, ((c, q), variant, f) in enumerate(zip(points, variants, on_front)):  # off the front: faded
        ax.scatter(c, q, s=40, zorder=3, alpha=1.0 if f else 0.4, **variant_style(i))
        if variant == reference:
            ax.scatter(c, q, s=160, facecolors="none", edgecolors="C3", zorder=4, label=f"{reference} (chosen)")
    ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    annotate_points(ax, points, variants)
    return fig


def write_pareto_charts(rows: list[dict], folder, title: str = "", cost: str = "step_seconds",
                        quality: str = "psnr", reference: str = "default", stem: str = "pareto") -> list[Path]:
    """Per scene with two or more variants on one device: quality against cost, the Pareto front
    drawn and the `reference` variant (the chosen defaults) ringed, in STEM_SCENE.png; STEM.json
    says which variants are on it, and which scenes were left out for mixing devices. A scene's
    chart from an earlier report that this one no longer draws is deleted, so no stale front stays."""
    folder = Path(folder)
    by_scene: dict[str, list[dict]] = {}
    for r in rows:
        if r.get(cost) is not None and r.get(quality) is not None:
            by_scene.setdefault(r["scene"], []).append(r)
    summary, made = {}, []
    for scene, runs in sorted(by_scene.items()):
        if len(runs) < 2:
            continue
        devices = sorted({str(r.get("device")) for r in runs})  # "None": a run from before metrics named it
        hosts = sorted({r["host"] for r in runs if r.get("host")})
        if len(devices) > 1 or len(hosts) > 1:  # a GPU's step time against a CPU's (or two CPUs') draws no front
            what = f"devices ({', '.join(devices)})" if len(devices) > 1 else f"machines ({'; '.join(hosts)})"
            summary[scene] = {"left_out": f"its runs ran on different {what}"}
            continue
        points = [(r[cost], r[quality]) for r in runs]
        on_front = pareto_front(points)
        summary[scene] = {r["variant"]: {"cost": r[cost], "quality": r[quality], "on_front": f}
                          for r, f in zip(runs, on_front)}
        fig = pareto_figure(points, [r["variant"] for r in runs], on_front,
                            AXIS_LABELS.get(cost, cost.replace("_", " ")),
                            split_label(AXIS_LABELS.get(quality, quality), runs),
                            f"{title}: {scene}" if title else scene, reference)
        made.append(save_figure(fig, folder / f"{stem}_{scene}.png", dpi=120))
    for scene in {r["scene"] for r in rows}:  # a front an earlier report drew and this one does not
        if (chart := folder / f"{stem}_{scene}.png") not in made:
            chart.unlink(missing_ok=True)
    if summary:
        made.append(write_json(folder / f"{stem}.json", {"cost": cost, "quality": quality, "reference": reference,
                                                        "scenes": summary}))
    return made
