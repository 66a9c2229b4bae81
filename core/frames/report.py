"""Error-against-run-time reports: the PSNR-vs-seconds history as JSON and as a plot image."""
from __future__ import annotations

import json
from pathlib import Path

from core.util.atomic import atomic_path, atomic_write_text


def write_history(path: str | Path, history: list[dict], extra: dict | None = None) -> Path:
    path = Path(path)
    atomic_write_text(path, json.dumps({"history": history, **(extra or {})}, indent=1))
    return path


def plot_curves(path: str | Path, curves: dict[str, list[dict]], title: str, x: str = "seconds",
                ys: tuple[str, ...] = ("psnr", "psnr_object")) -> Path:
    """One line per (curve, metric): curves {label: history rows}. Writes a PNG (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    styles = {"psnr": "-", "psnr_object": "--"}
    for label, rows in curves.items():
        for y in ys:
            pts = [(r[x], r[y]) for r in rows if r.get(y) is not None]
            if pts:
                ax.plot(*zip(*pts), styles.get(y, ":"), marker=".", label=f"{label} {y.replace('_', ' ')}")
    ax.set_xlabel("training time (s)" if x == "seconds" else x)
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
