"""Optimal fibre and tendon slack lengths of the personalised muscles (Modenese, Ceseracciu, Reggiani & Lloyd 2016,
J Biomech 49:141, "Estimation of musculotendon parameters for scaled and subject specific musculoskeletal models
using an optimization technique").

A muscle's normalised fibre length ``l̃ = l_f / l_o`` over the range of motion is kept the generic model's.
With a rigid tendon and constant-thickness pennation (``l_f sin α = l_o sin α_o``), at each sampled posture i

    L_g,i = l_s + l_f,i cos α_i,   l_f,i = sqrt((L_g,i - l_s)² + (l_o sin α_o)²),   l̃_i = l_f,i / l_o,

and ``cos α_i = sqrt(1 - (sin α_o / l̃_i)²)`` depends on ``l̃_i`` alone, so the subject's MTU lengths ``L_s,i``
at the equivalent postures (`poses.CoordinateMap`) give a problem linear in the unknowns:

    L_s,i = l_s' + (l̃_i cos α_i) l_o'      (least squares over i, l_o' > 0, l_s' >= 0; scipy ``lsq_linear``).

Postures: `N_POSES` Latin-hypercube samples (fixed seed) of the leg's coordinates over `SAMPLE_RANGES`
(gait2392's coordinate names, degrees) each clipped to the generic coordinate's range; postures where the
generic fibre would be slack (``L_g <= l_s``) or ``l̃`` outside [`LT_MIN`, `LT_MAX`] are left out.  A muscle whose
``l̃ cos α`` barely varies over the kept postures (spread below `MIN_SPREAD`: the problem is then degenerate)
keeps the generic ``l_o / l_s`` ratio, both scaled by the mean MTU length ratio, as OpenSim's ScaleTool does.
"""
from __future__ import annotations

import numpy as np

__all__ = ["calibrate_lengths", "mtu_lengths", "sample_poses", "SAMPLE_RANGES", "N_POSES"]

#: gait2392 coordinate (base name) -> sampled interval, degrees
SAMPLE_RANGES = {"hip_flexion": (-30.0, 90.0), "hip_adduction": (-30.0, 20.0), "hip_rotation": (-30.0, 30.0),
                 "knee_angle": (-110.0, 0.0), "ankle_angle": (-30.0, 25.0), "subtalar_angle": (-20.0, 20.0),
                 "mtp_angle": (-30.0, 30.0)}
N_POSES = 120
LT_MIN, LT_MAX = 0.4, 1.8
MIN_SPREAD = 0.02


def sample_poses(generic_model, sides, n: int = N_POSES, seed: int = 0) -> list[dict]:
    """`n` generic postures (coordinate name -> rad): a Latin hypercube over `SAMPLE_RANGES` of each side."""
    from scipy.stats import qmc

    cs = generic_model.getCoordinateSet()
    names, lo, hi = [], [], []
    for s in sides:
        for base, (a, b) in SAMPLE_RANGES.items():
            c = cs.get(f"{base}_{s}")
            names.append(c.getName())
            lo.append(max(np.radians(a), c.getRangeMin()))
            hi.append(min(np.radians(b), c.getRangeMax()))
    u = qmc.LatinHypercube(d=len(names), seed=seed).random(n)
    X = np.asarray(lo) + u * (np.asarray(hi) - np.asarray(lo))
    return [dict(zip(names, row)) for row in X]


def mtu_lengths(model, muscles, poses: list[dict], state=None) -> np.ndarray:
    """(n_poses, n_muscles) MTU path lengths (m) of `muscles` (names) at `poses` (coordinate name -> value; the
    couplers' dependent coordinates follow, `poses.set_pose`)."""
    from .poses import _couplers, set_pose

    state = model.initSystem() if state is None else state
    couplers = _couplers(model)
    ms = model.getMuscles()
    mus = [ms.get(n) for n in muscles]
    out = np.empty((len(poses), len(mus)))
    for i, q in enumerate(poses):
        set_pose(model, state, q, couplers)
        out[i] = [m.getLength(state) for m in mus]
    return out


def calibrate_lengths(generic_model, subject_model, muscles, cmap, sides, *, n: int = N_POSES,
                      seed: int = 0) -> dict:
    """Re-estimated (l_o, l_s) of each muscle (module docstring), set on `subject_model`'s muscles.

    generic_model, subject_model : opensim.Model (initialised; the subject's holds `muscles`); cmap :
    `poses.CoordinateMap`.  Returns muscle -> {"optimal_fiber_length", "tendon_slack_length" (m), "generic_...",
    "method" ("optimised" | "scaled"), "poses" (kept), "rms_mm" (fit residual of the MTU lengths)}.
    """
    from scipy.optimize import lsq_linear

    gposes = sample_poses(generic_model, sides, n, seed)
    sposes = [cmap.subject_pose(q) for q in gposes]
    Lg = mtu_lengths(generic_model, muscles, gposes)
    Ls = mtu_lengths(subject_model, muscles, sposes)
    out = {}
    gms, sms = generic_model.getMuscles(), subject_model.getMuscles()
    for k, name in enumerate(muscles):
        g = gms.get(name)
        lo, ls, a0 = g.getOptimalFiberLength(), g.getTendonSlackLength(), g.getPennationAngleAtOptimalFiberLength()
        h = lo * np.sin(a0)
        d = Lg[:, k] - ls
        keep = d > 0
        lf = np.sqrt(np.where(keep, d, 0.0) ** 2 + h**2)
        lt = lf / lo
        keep &= (lt >= LT_MIN) & (lt <= LT_MAX)
        c = np.where(keep, d / lo, 0.0)            # l̃ cos α = (L_g - l_s) / l_o
        row = {"generic_optimal_fiber_length": lo, "generic_tendon_slack_length": ls, "poses": int(keep.sum())}
        if keep.sum() >= 5 and np.ptp(c[keep]) >= MIN_SPREAD:
            M = np.column_stack([c[keep], np.ones(keep.sum())])
            sol = lsq_linear(M, Ls[keep, k], bounds=([1e-3, 0.0], [np.inf, np.inf]))
            lo_s, ls_s = (float(v) for v in sol.x)
            row.update(method="optimised", rms_mm=1e3 * float(np.sqrt(np.mean((M @ sol.x - Ls[keep, k]) ** 2))))
        else:
            r = float(Ls[:, k].mean() / Lg[:, k].mean())
            lo_s, ls_s = lo * r, ls * r
            row.update(method="scaled")
        m = sms.get(name)
        m.setOptimalFiberLength(lo_s)
        m.setTendonSlackLength(ls_s)
        row.update(optimal_fiber_length=lo_s, tendon_slack_length=ls_s)
        out[name] = row
    return out
