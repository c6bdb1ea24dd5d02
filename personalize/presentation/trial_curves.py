"""Curves of one trial against time: joint angles and joint moments, left red and right green (Vicon).

The figures of ``personalize markers`` (``angles.png``) and ``personalize
dynamics`` (``moments.png``): one panel per joint and component, time (s) on
x, the unit in the y labels.  Matplotlib with the Agg backend; files are
written atomically, nothing is shown.
"""
from __future__ import annotations

import os
from typing import Mapping

import numpy as np

__all__ = ["MOMENT_JOINTS", "plot_angles", "plot_moments"]

from personalize.presentation.gait_plots import SIDE_COLOURS

SIDES = (("r", SIDE_COLOURS["R"]), ("l", SIDE_COLOURS["L"]))

#: (coordinate stem, panel title) of the moment panels, gait2392 names and signs
MOMENT_JOINTS = (("hip_flexion", "hip_flexion"), ("hip_adduction", "hip_adduction"), ("hip_rotation", "hip_rotation"),
                 ("knee_angle", "knee_angle (gait2392: + extension)"), ("ankle_angle", "ankle_angle (+ dorsiflexion)"),
                 ("subtalar_angle", "subtalar_angle (+ inversion)"))

_ANGLE_COMPONENTS = {"hip": ("flexion", "adduction", "internal rotation"),
                     "knee": ("flexion", "adduction", "internal rotation"),
                     "ankle": ("dorsiflexion", "inversion", "internal rotation")}


def _figure(size):
    from personalize.presentation.html_report import new_figure

    fig = new_figure(*size)
    fig.set_layout_engine("constrained")
    return fig


def _save(fig, path: str | os.PathLike) -> None:
    from personalize.presentation.html_report import save_png

    save_png(fig, path, dpi=110)


def plot_angles(path: str | os.PathLike, time: np.ndarray, angles: Mapping[str, np.ndarray]) -> None:
    """3 x 3 grid (hip, knee, ankle x three components) of the right and left joint angles (degrees).

    Parameters
    ----------
    path : PNG file to write
    time : (F,) s
    angles : ``hip_r``, ``knee_r``, ``ankle_r`` and ``_l`` -> (F, 3) rad, Plug-in-Gait
        conventions (flexion / dorsiflexion, adduction / inversion, internal rotation)
    """
    fig = _figure((11, 8))
    axes = fig.subplots(3, 3, sharex=True)
    for i, j in enumerate(("hip", "knee", "ankle")):
        for k in range(3):
            ax = axes[i, k]
            for s, colour in SIDES:
                ax.plot(time, np.degrees(angles[f"{j}_{s}"][:, k]), color=colour, lw=1.2, label=s.upper())
            ax.set_title(f"{j} {_ANGLE_COMPONENTS[j][k]}", fontsize=9)
            ax.ticklabel_format(axis="y", useOffset=False, style="plain")
            lo, hi = ax.get_ylim()
            if hi - lo < 2.0:          # a component fixed by the model (e.g. a hinge knee): show it flat
                mid = 0.5 * (lo + hi)
                ax.set_ylim(mid - 1.0, mid + 1.0)
            ax.grid(alpha=0.3)
            if k == 0:
                ax.set_ylabel("deg")
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=8)
    _save(fig, path)


def plot_moments(path: str | os.PathLike, result) -> None:
    """2 x 3 grid of the hip, knee, ankle and subtalar moments (N m/kg) against time.

    Parameters
    ----------
    path : PNG file to write
    result : `kinematics.gait.inverse_dynamics` trial result: ``time`` (F,) s,
        ``coordinates`` (n_q names), ``tau_per_kg`` (F, n_q) N m/kg
    """
    fig = _figure((11, 6.5))
    axes = fig.subplots(2, 3, sharex=True).ravel()
    for ax, (stem, title) in zip(axes, MOMENT_JOINTS):
        for s, colour in SIDES:
            name = f"{stem}_{s}"
            if name in result.coordinates:
                ax.plot(result.time, result.tau_per_kg[:, result.coordinates.index(name)], color=colour, lw=1.2,
                        label=s.upper())
        ax.set_title(f"{title} moment", fontsize=9)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.grid(alpha=0.3)
    for ax in axes[3:]:
        ax.set_xlabel("time (s)")
    for ax in axes[::3]:
        ax.set_ylabel("N m/kg")
    axes[0].legend(fontsize=8)
    _save(fig, path)
