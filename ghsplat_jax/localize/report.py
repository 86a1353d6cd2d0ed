"""The localization report: a markdown summary (detection rate against distance and
viewing angle, pose errors) and a chart, with the series it draws; `write_report` writes
RESULT.json, the chart and report.md into one folder (`ghsplat localize`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ghsplat_jax.io_utils import atomic_write, save_figure, write_json


def markdown(result: dict, title: str, plot_name: str | None) -> str:
    s = result["summary"]
    fmt = lambda v, f="{:.3f}": "n/a" if v is None else f.format(v)
    lines = [f"# {title}", "",
             f"- frames: {s['frames']}; availability (>= 1 tag detected): {fmt(s['availability'], '{:.1%}')}",
             f"- visible tag instances: {s['candidates']}; detected: {fmt(s['detection_rate'], '{:.1%}')}",
             f"- robot position error (m): median {fmt(s['position_error_m']['median'])}, "
             f"p90 {fmt(s['position_error_m']['p90'])}, max {fmt(s['position_error_m']['max'])}",
             f"- robot yaw error (deg): median {fmt(s['yaw_error_deg']['median'], '{:.2f}')}, "
             f"p90 {fmt(s['yaw_error_deg']['p90'], '{:.2f}')}, max {fmt(s['yaw_error_deg']['max'], '{:.2f}')}"]
    for label, b in s.get("by_tags_seen", {}).items():
        lines.append(f"- frames with {label} tag(s) detected: {b['frames']}; median position error "
                     f"{fmt(b['position_error_m_median'])} m, "
                     f"median yaw error {fmt(b['yaw_error_deg_median'], '{:.2f}')} deg")
    lines.append("")
    for key, name, unit in (("rate_vs_distance", "distance", "m"), ("rate_vs_angle", "viewing angle", "deg")):
        lines += [f"## Detection rate against {name}", "", f"| {name} ({unit}) | visible | detection rate |",
                  "|---|---|---|"]
        lines += [f"| {r['lo']:g}-{r['hi']:g} | {r['candidates']} | {r['detection_rate']:.1%} |" for r in s[key]]
        lines.append("")
    if plot_name:
        lines += [f"![localization]({plot_name})", ""]
    return "\n".join(lines)


def plot_series(result: dict) -> dict:
    """The numbers the localization chart draws: detection rate per distance and angle bin
    (bin centre, rate, bin width) and position / yaw error against time (NaN: no estimate)."""
    s, fr = result["summary"], result["frames"]
    bars = lambda rows: {"centre": [(r["lo"] + r["hi"]) / 2 for r in rows],  # noqa: E731
                         "rate": [r["detection_rate"] for r in rows], "width": [r["hi"] - r["lo"] for r in rows]}
    nan = lambda v: np.nan if v is None else v  # noqa: E731
    return {"rate_vs_distance": bars(s["rate_vs_distance"]), "rate_vs_angle": bars(s["rate_vs_angle"]),
            "t": [f["t"] for f in fr], "position_error": [nan(f["position_error"]) for f in fr],
            "yaw_error_deg": [nan(f["yaw_error_deg"]) for f in fr], "availability": s["availability"]}


def plot_figure(series: dict):
    """Detection rate bars (top) and pose errors over time (bottom) as a matplotlib Figure."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 7))
    ax = fig.subplots(2, 2)
    for a, key, label in ((ax[0, 0], "rate_vs_distance", "distance (m)"),
                          (ax[0, 1], "rate_vs_angle", "viewing angle (deg)")):
        bars = series[key]
        if bars["centre"]:
            a.bar(bars["centre"], bars["rate"], width=[0.9 * w for w in bars["width"]])
        a.set_xlabel(label)
        a.set_ylabel("detection rate")
        a.set_ylim(0, 1.05)
    for a, key, label in ((ax[1, 0], "position_error", "position error (m)"),
                          (ax[1, 1], "yaw_error_deg", "yaw error (deg)")):
        a.plot(series["t"], series[key], ".-")
        a.set_xlabel("time (s)")
        a.set_ylabel(label)
    fig.suptitle(f"AprilTag localization: availability {series['availability']:.0%}")
    fig.tight_layout()
    return fig


def plot(result: dict, path) -> dict:
    """Write the localization chart as PNG; returns the series it plots."""
    series = plot_series(result)
    save_figure(plot_figure(series), path, dpi=100)
    return series


def write_report(result: dict, out, title: str) -> Path:
    """localization.json, localization.png and report.md of `result` (apriltag.evaluate) in `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "localization.json", result)
    plot(result, out / "localization.png")
    with atomic_write(out / "report.md", "w") as fh:
        fh.write(markdown(result, title, "localization.png"))
    return out
