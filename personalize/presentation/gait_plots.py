"""Gait-lab plots: joint angles, moments and powers per % gait cycle, and the foot element's fit.

Drawn as clinical gait reports (Vicon Polygon / Plug-in-Gait reports) draw
them: one panel per joint (rows) and plane (columns), % gait cycle on x,
left side red and right side green, mean with a ±1 sd band, a vertical line
at each side's toe off (end of stance), zero line, units in the y labels.
Matplotlib with the Agg backend; nothing is shown, files are written.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from personalize.presentation.html_report import new_figure, save_png

__all__ = [
    "ANGLE_PANELS",
    "MOMENT_PANELS",
    "SIDE_COLOURS",
    "plot_foot_angle_fit",
    "plot_gait_grid",
    "plot_power_row",
]

SIDE_COLOURS = {"L": "#d62728", "R": "#2ca02c"}  # Vicon: left red, right green
SIDE_NAMES = {"L": "left", "R": "right"}

ANGLE_PANELS = {
    "hip": ("Hip flexion (+) / extension", "Hip adduction (+) / abduction", "Hip internal (+) / external rotation"),
    "knee": ("Knee flexion (+) / extension", "Knee varus (+) / valgus", "Knee internal (+) / external rotation"),
    "ankle": ("Ankle dorsiflexion (+) / plantarflexion", "Ankle inversion (+) / eversion",
              "Foot internal (+) / external rotation"),
}
MOMENT_PANELS = {
    "hip": ("Hip extensor (+) moment", "Hip abductor (+) moment", "Hip rotator moment"),
    "knee": ("Knee extensor (+) moment", "Knee abductor (+) moment", "Knee rotator moment"),
    "ankle": ("Ankle plantarflexor (+) moment", "Ankle inverter/everter moment", "Ankle rotator moment"),
}


def _figure(width: float, height: float):
    # a Figure on its own Agg canvas: no pyplot state, no backend switched under a notebook user
    return new_figure(width, height)


def _panel(ax, stats: dict, name: str, k: int | None, unit: str, title: str):
    for side in ("L", "R"):
        st = stats.get((name, side))
        if st is None:
            continue
        c = SIDE_COLOURS[side]
        m = st.mean if k is None else st.mean[:, k]
        sd = st.sd if k is None else st.sd[:, k]
        m, sd = np.ravel(m), np.ravel(sd)
        ax.plot(st.percent, m, color=c, lw=1.6, label=f"{SIDE_NAMES[side]} (n={st.n_cycles})")
        if np.isfinite(sd).any():
            ax.fill_between(st.percent, m - sd, m + sd, color=c, alpha=0.18, lw=0)
        toe_off = np.nanmean(st.stance_percent) if np.isfinite(st.stance_percent).any() else np.nan
        if np.isfinite(toe_off):
            ax.axvline(toe_off, color=c, ls="--", lw=1.0)
    ax.axhline(0.0, color="0.6", lw=0.6)
    ax.set_xlim(0, 100)
    ax.set_title(title, fontsize=9)
    ax.set_ylabel(unit, fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(True, color="0.9", lw=0.5)


def plot_gait_grid(path: str | os.PathLike, stats: dict, quantity: str, unit: str, *,
                   joints=("hip", "knee", "ankle"), title: str = "") -> Path:
    """A joints × planes grid of one quantity (``"angle"`` or ``"moment"``) per % gait cycle.

    Parameters
    ----------
    path : output image (.png / .pdf / .svg)
    stats : dict (``f"{joint}_{quantity}"``, side) -> `kinematics.gait.gait_cycles.CycleStatistics`
        with 3 components (sagittal, frontal, transverse), already in `unit`
    quantity : ``"angle"`` or ``"moment"`` (selects the panel titles)
    unit : y-axis unit, e.g. ``"deg"`` or ``"N mm/kg"``
    """
    titles = ANGLE_PANELS if quantity == "angle" else MOMENT_PANELS
    fig = _figure(10, 2.6 * len(joints))
    axes = fig.subplots(len(joints), 3, sharex=True, squeeze=False)
    for r, joint in enumerate(joints):
        for k in range(3):
            _panel(axes[r, k], stats, f"{joint}_{quantity}", k, unit, titles[joint][k])
    for ax in axes[-1]:
        ax.set_xlabel("% gait cycle", fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title or f"Joint {quantity}s (mean ± 1 sd; dashed: toe off)", fontsize=10)
    fig.tight_layout()
    return save_png(fig, path, dpi=120)


def plot_power_row(path: str | os.PathLike, stats: dict, unit: str = "W/kg", *, joints=("hip", "knee", "ankle"),
                   title: str = "Joint powers (generation +)") -> Path:
    """Total joint power per % gait cycle, one panel per joint; `stats` keys (``f"{joint}_power"``, side)."""
    fig = _figure(10, 2.8)
    axes = fig.subplots(1, len(joints), squeeze=False)
    for k, joint in enumerate(joints):
        _panel(axes[0, k], stats, f"{joint}_power", None, unit, f"{joint.capitalize()} power")
        axes[0, k].set_xlabel("% gait cycle", fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path, dpi=120)


def plot_foot_angle_fit(path: str | os.PathLike, phases: list[dict], *, title: str = "") -> Path:
    """Measured and simulated hind-foot sagittal angle (Tändl et al. 2010, Fig. 9), one panel per stance.

    Parameters
    ----------
    phases : list of dict with ``label`` (str), ``percent`` (m,) % of stance, ``measured`` and
        ``simulated`` (m,) degrees (toes up positive)
    """
    n = max(len(phases), 1)
    fig = _figure(3.6 * n, 3.0)
    axes = fig.subplots(1, n, squeeze=False, sharey=True)
    for ax, ph in zip(axes[0], phases):
        ax.plot(ph["percent"], ph["measured"], "k-", lw=1.5, label="measured")
        ax.plot(ph["percent"], ph["simulated"], "--", color="#1f77b4", lw=1.5, label="simulated")
        ax.set_title(ph["label"], fontsize=9)
        ax.set_xlabel("% stance", fontsize=8)
        ax.grid(True, color="0.9", lw=0.5)
        ax.tick_params(labelsize=7)
    axes[0, 0].set_ylabel("hind foot to ground, sagittal (deg, toes up +)", fontsize=8)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(title or "Foot element: measured and simulated hind-foot orientation", fontsize=10)
    fig.tight_layout()
    return save_png(fig, path, dpi=120)
