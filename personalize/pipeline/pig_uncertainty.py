r"""The Plug-in-Gait static estimates' covariance from the placement error of the markers they are built on.

Plug-in-Gait's knee and ankle centres (chord function) and its knee and
torsioned-tibia axes hang on the thigh and shank wands being in the plane of
the joint centres and the epicondyle/malleolus markers.  How much a
misplaced marker moves them depends on the subject's geometry: with a wand
on the skin a few centimetres from the knee marker, a 10 mm error of the knee
marker turns the knee centre by tens of degrees (realistic phantoms on real
bones: 19-48 mm knee and 48-55 mm ankle centre errors, 30-68 deg ankle axes,
against the 5-8 mm and 6 deg the fixed sds claimed).  The covariance is
therefore propagated through the reconstruction itself, per subject:

.. math::

    \Sigma_c = \sum_m J_m\, \sigma_m^2 I_3\, J_m^T + \sigma_0^2 I_3, \qquad
    J_m = \frac{\partial c}{\partial x_m}

with :math:`J_m` by forward differences (step `STEP`, m) of one Plug-in-Gait
reconstruction whose frames are the static median pose and its perturbed
copies (each frame is reconstructed independently), :math:`\sigma_m` the
placement sd of marker m (`LANDMARK_SD` for palpated landmarks,
`WAND_SD` for the wand/skin markers THI and TIB) and :math:`\sigma_0` the
fixed sd calibrated on phantoms (`motion.PIG_CENTRE_SD`).  A direction
:math:`u` (axis column) gets :math:`\Sigma_u` the same way and the angle sd
:math:`\sqrt{\operatorname{tr}\Sigma_u / 2}` (rad), combined with the fixed
sd in quadrature.
"""
from __future__ import annotations

import numpy as np

from kinematics.io.markers import MarkerTrial
from lowerlimb.estimates import Gaussian

from .motion import PIG_CENTRE_SD, has_pig_markers

__all__ = ["LANDMARK_SD", "WAND_SD", "STEP", "PigUncertainty", "pig_uncertainty", "pig_centre_propagated",
           "pig_axis_sd_deg"]

#: m, sd (3-D, per axis) of a palpated Plug-in-Gait landmark marker (ASIS, PSIS, sacrum, knee, ankle, heel, toe):
#: Della Croce, Cappozzo & Kerrigan 1999 (Med Biol Eng Comput 37:155), inter-examiner rms 6-21 mm over the pelvis
#: and lower-limb landmarks; 8 mm, a mid value
LANDMARK_SD = 0.008
#: m, sd of a thigh or shank wand marker off the plane Plug-in-Gait assumes for it (placed by eye; assumed)
WAND_SD = 0.010
#: m, forward-difference step
STEP = 1e-4

_SUFFIXES = ("ASI", "PSI", "SACR", "THI", "KNE", "TIB", "ANK", "HEE", "TOE")
_CACHE: dict = {}


class PigUncertainty:
    """Propagated covariances of one static reconstruction: centres ``{"knee_r": (3, 3) m²}``, axes
    ``{"femur_r": (3, 3)}`` (the segment's y column: the knee axis; ``tibia_torsioned_r``: the ankle axis)."""

    def __init__(self, centres: dict, axes: dict):
        self.centres = centres
        self.axes = axes


def _marker_sd(name: str) -> float | None:
    base = name[1:] if name[:1] in "RL" and name[1:] in _SUFFIXES else name
    if base not in _SUFFIXES:
        return None
    return WAND_SD if base in ("THI", "TIB") else LANDMARK_SD


def pig_uncertainty(trial: MarkerTrial, subject) -> PigUncertainty:
    """`PigUncertainty` of the Plug-in-Gait reconstruction of the static `trial` (see the module docstring)."""
    from kinematics.gait.reconstruction import reconstruct

    med = np.nanmedian(trial.positions, axis=0)                           # (M, 3)
    cols = [(j, a, sd) for j, n in enumerate(trial.names) if (sd := _marker_sd(n)) is not None
            and np.all(np.isfinite(med[j])) for a in range(3)]
    frames = np.repeat(med[None], 1 + len(cols), axis=0)
    for k, (j, a, _) in enumerate(cols):
        frames[1 + k, j, a] += STEP
    base = MarkerTrial(trial.names, np.repeat(med[None], 3, axis=0), trial.rate, np.arange(3) / trial.rate,
                       trial.source, trial.extra)
    pert = MarkerTrial(trial.names, frames, trial.rate, np.arange(len(frames)) / trial.rate, trial.source, trial.extra)
    rec = reconstruct(pert, "pig", static=base, subject=subject, check_static=False)
    var = np.array([sd**2 for _, _, sd in cols])

    def cov_of(x: np.ndarray) -> np.ndarray:                               # x: (1 + K, 3)
        J = (x[1:] - x[0]) / STEP                                           # (K, 3): d x / d (marker, axis)
        return (J.T * var) @ J

    centres = {k: cov_of(np.asarray(v, float)) for k, v in rec.centres.items()}
    axes = {k: cov_of(np.asarray(seg.axes, float)[:, :, 1]) for k, seg in rec.segments.items()}
    return PigUncertainty(centres, axes)


def _of(ctx) -> PigUncertainty | None:
    """The propagation for ``ctx.pig``, computed once per reconstruction (the last one is kept, with a reference
    to it, so that another subject's reconstruction can never be taken for it)."""
    if ctx.pig is None:
        return None
    if _CACHE.get("pig") is not ctx.pig:
        view = getattr(ctx, "view", None)
        trial = next((t for t in (ctx.inputs.static, getattr(view, "static", None))
                      if t is not None and has_pig_markers(t)), None)
        if trial is None:
            return None
        _CACHE.clear()
        _CACHE.update(pig=ctx.pig, value=pig_uncertainty(trial, ctx.inputs.subject))
    return _CACHE["value"]


def pig_centre_propagated(ctx, joint: str, side: str) -> Gaussian:
    """Plug-in-Gait knee/ankle centre of ``ctx.pig`` (median over the static frames) with Σ_c of the module docstring."""
    mean = np.median(ctx.pig.centres[f"{joint}_{side}"], axis=0)
    u = _of(ctx)
    C = PIG_CENTRE_SD[joint]**2 * np.eye(3)
    if u is not None:
        C = C + u.centres[f"{joint}_{side}"]
    return Gaussian(mean, C)


def pig_axis_sd_deg(ctx, segment: str, fixed_sd_deg: float) -> float:
    """sd (deg) of the y axis of the Plug-in-Gait static segment `segment`: propagated ⊕ `fixed_sd_deg`."""
    u = _of(ctx)
    if u is None or segment not in u.axes:
        return float(fixed_sd_deg)
    prop = np.degrees(np.sqrt(max(np.trace(u.axes[segment]) / 2.0, 0.0)))
    return float(np.hypot(prop, fixed_sd_deg))
