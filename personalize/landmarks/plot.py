"""Picture of one bone: surface, fitted primitives and landmarks from two views (matplotlib, Agg)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .common import BoneLandmarks

__all__ = ["plot_bone"]


def _view_axes(res: BoneLandmarks, V: np.ndarray) -> np.ndarray:
    for key in ("anatomical", "isb", "foot", "articular"):
        if key in res.frames:
            return np.asarray(res.frames[key]["rotation"], float)
    c = V.mean(axis=0)
    _, _, vt = np.linalg.svd(V - c, full_matrices=False)
    return np.column_stack([vt[1], vt[0], np.cross(vt[1], vt[0])])


def plot_bone(mesh, res: BoneLandmarks, path: Path, max_points: int = 4000) -> None:
    """Write a PNG with a frontal (Z-Y) and a sagittal (X-Y) view of the bone (mm)."""
    from matplotlib.patches import Circle

    from personalize.presentation.html_report import new_figure, save_png   # Agg canvas, no pyplot state

    V = np.asarray(mesh.vertices, float)
    R = _view_axes(res, V)
    o = V.mean(axis=0)
    step = max(1, len(V) // max_points)
    Q = (V[::step] - o) @ R * 1e3
    fig = new_figure(10, 6)
    axs = fig.subplots(1, 2)
    views = (("frontal (Z right, Y up)", 2, 1), ("sagittal (X anterior, Y up)", 0, 1))
    for ax, (title, i, j) in zip(axs, views):
        ax.scatter(Q[:, i], Q[:, j], s=0.3, c="0.7", rasterized=True)
        for name, fit in res.fits.items():
            if fit.get("type") == "sphere":
                c = (np.asarray(fit["centre"]) - o) @ R * 1e3
                ax.add_patch(Circle((c[i], c[j]), fit["radius"] * 1e3, fill=False, color="tab:blue", lw=1))
            elif fit.get("type") == "cylinder":
                p = (np.asarray(fit["point"]) - o) @ R * 1e3
                d = np.asarray(fit["axis"]) @ R
                seg = np.array([p - 40 * d, p + 40 * d])
                ax.plot(seg[:, i], seg[:, j], color="tab:green", lw=1)
        for name, lm in res.landmarks.items():
            p = (lm.position - o) @ R * 1e3
            ax.plot(p[i], p[j], "o", color="tab:red", ms=3)
            ax.annotate(name, (p[i], p[j]), fontsize=6)
        for name, a in res.axes.items():
            p = (a.point - o) @ R * 1e3
            d = a.direction @ R
            seg = np.array([p, p + 50 * d])
            ax.plot(seg[:, i], seg[:, j], color="tab:orange", lw=1)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("mm")
    flags = ", ".join(res.flags) if res.flags else "no flags"
    fig.suptitle(f"{res.bone} ({flags})", fontsize=10)
    fig.tight_layout()
    save_png(fig, path, dpi=90)
