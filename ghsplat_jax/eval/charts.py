"""Charts of a run set: PSNR against training time and against surfel count.

Each chart is a PNG and, beside it, the JSON of the series it plots (name.json), so the
numbers behind a picture can be read and checked. Figures are `matplotlib.figure.Figure`
objects: no pyplot, no global backend switch.
"""

from __future__ import annotations

from pathlib import Path

from ghsplat_jax.io_utils import save_figure, write_json

CHARTS = (  # file stem, x key, y key, x label, y label
    ("psnr_vs_time", "train_seconds", "psnr", "training time (s)", "PSNR (dB)"),
    ("psnr_vs_count", "num_gaussians", "psnr", "surfels", "PSNR (dB)"),
)


def scatter_series(rows: list[dict], x: str, y: str) -> dict[str, list[dict]]:
    """{variant: [{"scene", "x", "y"}, ...]} of the rows that have both values, variants sorted."""
    series: dict[str, list[dict]] = {}
    for r in rows:
        if r.get(x) is not None and r.get(y) is not None:
            series.setdefault(r.get("variant") or "", []).append({"scene": r["scene"], "x": r[x], "y": r[y]})
    return dict(sorted(series.items()))


def scatter_figure(series: dict[str, list[dict]], xlabel: str, ylabel: str, title: str = "", log_x: bool = False):
    """One marker per run, one colour per variant, labelled by scene."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.4), dpi=120)
    ax = fig.subplots()
    for i, (variant, points) in enumerate(series.items()):
        ax.scatter([p["x"] for p in points], [p["y"] for p in points], label=variant or None, color=f"C{i}", s=36,
                   zorder=3)
        for p in points:
            ax.annotate(p["scene"], (p["x"], p["y"]), textcoords="offset points", xytext=(4, 3), fontsize=7)
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if title:
        ax.set_title(title)
    if any(series):
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def write_charts(rows: list[dict], folder, title: str = "") -> list[Path]:
    """The PNG charts of CHARTS that have data, each with its series as JSON beside it."""
    folder = Path(folder)
    made = []
    for stem, x, y, xlabel, ylabel in CHARTS:
        series = scatter_series(rows, x, y)
        if not series:
            continue
        write_json(folder / f"{stem}.json", {"x": x, "y": y, "title": title, "series": series})
        made.append(save_figure(scatter_figure(series, xlabel, ylabel, title, log_x=True), folder / f"{stem}.png",
                                dpi=120))
    return made
