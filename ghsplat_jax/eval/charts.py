"""Charts of a run set: PSNR against training time and against surfel count (PNG, Agg)."""

from __future__ import annotations

from pathlib import Path


def scatter(rows: list[dict], x: str, y: str, xlabel: str, ylabel: str, path, title: str = "",
            log_x: bool = False) -> Path | None:
    """One marker per run, one colour per variant, labelled by scene; None when no row has both values."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [r for r in rows if r.get(x) is not None and r.get(y) is not None]
    if not pts:
        return None
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    variants = sorted({r.get("variant") or "" for r in pts})
    for i, v in enumerate(variants):
        sel = [r for r in pts if (r.get("variant") or "") == v]
        ax.scatter([r[x] for r in sel], [r[y] for r in sel], label=v or None, color=f"C{i}", s=36, zorder=3)
        for r in sel:
            ax.annotate(r["scene"], (r[x], r[y]), textcoords="offset points", xytext=(4, 3), fontsize=7)
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if title:
        ax.set_title(title)
    if any(variants):
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)
    return path


def write_charts(rows: list[dict], folder, title: str = "") -> list[Path]:
    folder = Path(folder)
    made = [
        scatter(rows, "train_seconds", "psnr", "training time (s)", "PSNR (dB)", folder / "psnr_vs_time.png",
                title, log_x=True),
        scatter(rows, "num_gaussians", "psnr", "surfels", "PSNR (dB)", folder / "psnr_vs_count.png", title,
                log_x=True),
    ]
    return [p for p in made if p is not None]
