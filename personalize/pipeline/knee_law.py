"""The knee's correlative law: flexion slopes fitted from IK with free knee translations, intercept fused.

The law t = S q + c (`kinematics.mechanisms.correlative`) of each knee: its
flexion slopes are fitted from IK of the dynamic trials with the knee
translations free, kept when physiological (`KNEE_LAW_LIMITS`), else the
default law; its intercept (the standing knee translation) is the fusion of the
MRI's (zero: the fused knee centre is the standing one) and the fitted law's at
the standing pose (`personalize.parameter_fusion.fuse_knee_standing_translation`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from lowerlimb.errors import FitError, InputError
from lowerlimb.estimates import Gaussian

from ..fusion import Fused
from ..parameter_fusion import fuse_knee_standing_translation

__all__ = ["KNEE_LAW_LIMITS", "fit_knee_laws", "KneeIntercept", "fuse_knee_intercepts"]


KNEE_LAW_LIMITS = {"tx_flexion": (0.0, 0.008), "ty_flexion": (-0.005, 0.0005), "any": 0.010}


def fit_knee_laws(pm, trials: list, say=lambda m: None, standing: dict | None = None) -> dict:
    """Knee laws fitted from IK with free knee translations, or the default law.

    Model: the personalised model without its knee couplings (translations
    free within +-3 cm); IK of `trials` (internal frame, mapped into the model's ground by ``pm.G``);
    then per side the least-squares law
    t = c_flex flexion + c_0 (`kinematics.mechanisms.correlative_fit.fit_law`).
    Skin markers move over the bones by more than the knee translations, so a
    fitted law is kept only when its slopes are physiological
    (`KNEE_LAW_LIMITS`); otherwise the default law is used.  Only the
    flexion slopes are fitted (the ab/adduction and rotation excursions of
    gait and crouching are a few degrees: their slopes would be noise).

    `standing`, when given, receives per side the fitted law's knee translation at the
    standing pose and its covariance from the fit, ``(t (3,) m, cov (3, 3) m²)``: the motion
    estimate of the law's intercept (`fuse_knee_intercepts`), as a `Gaussian`.

    Returns
    -------
    dict side -> (CorrelativeLaw, provenance text)
    """
    from kinematics.algorithms.ik import solve_ik
    from kinematics.mechanisms.correlative import CorrelativeLaw
    from kinematics.mechanisms.correlative_fit import fit_law

    from ..model_builder import default_knee_law, trial_in_ground

    free = pm.model.with_couplings(None)
    sides = list(pm.knee_laws)
    A = {s: [] for s in sides}
    D = {s: [] for s in sides}
    for t in trials:
        say(f"knee law: IK with free knee translations on {Path(t.source).name}")
        r = solve_ik(free, trial_in_ground(pm, t))
        for s in sides:
            A[s].append(r.q[:, [free.coordinate_index(f"knee_{n}_{s}") for n in ("flexion", "adduction", "rotation")]])
            D[s].append(r.q[:, [free.coordinate_index(f"knee_{n}_{s}") for n in ("tx", "ty", "tz")]])
    out = {}
    for s in sides:
        default = default_knee_law(s)
        if not trials:
            out[s] = (default, "default law (no dynamic trial)")
            continue
        try:
            fit = fit_law(np.concatenate(A[s])[:, :1], np.concatenate(D[s]), default.independent[:1], default.dependent,
                          joint=f"knee_{s}")
        except (InputError, FitError) as exc:
            out[s] = (default, f"default law (fit failed: {exc})")
            continue
        if standing is not None:
            q = np.array([[pm.standing_q[pm.model.coordinate_index(f"knee_flexion_{s}")]]])
            standing[s] = Gaussian(fit.predict(q)[0], np.diag(fit.predict_sd(q)[0] ** 2))
        sl = fit.slopes[:, 0]
        lim = KNEE_LAW_LIMITS
        ok = (lim["tx_flexion"][0] <= sl[0] <= lim["tx_flexion"][1] and lim["ty_flexion"][0] <= sl[1] <= lim["ty_flexion"][1]
              and np.all(np.abs(sl) <= lim["any"]))
        text = "tx {:+.1f}, ty {:+.1f}, tz {:+.1f} mm/rad of flexion".format(*(1e3 * sl))
        if ok:
            # flexion slopes fitted; ab/adduction and rotation excursions in gait are too small to fit theirs;
            # zero translation in the static pose (the model's knee centre is the fused one)
            coef = np.column_stack([sl, default.slopes[:, 1:], np.zeros(3)])
            law = CorrelativeLaw(joint=default.joint, independent=default.independent, dependent=default.dependent,
                                 coefficients=coef, independent_units=default.independent_units,
                                 dependent_units=default.dependent_units)
            out[s] = (law, f"flexion slopes fitted from IK with free knee translations ({text}); "
                           "ab/adduction and rotation slopes default")
        else:
            out[s] = (default, f"default law: the fitted slopes are not physiological ({text}; soft-tissue artefact)")
    return out


@dataclass(frozen=True)
class KneeIntercept:
    """The knee law's intercept (standing translation tx, ty, tz, knee frame, m): motion estimate and fused."""

    motion: Gaussian
    fused: Fused

    def summary(self) -> dict:
        return {"mri": [0.0, 0.0, 0.0], "motion": self.motion.mean.tolist(), "motion_cov": self.motion.cov.tolist(),
                "fused": self.fused.summary(), "components": ["knee_tx (anterior)", "knee_ty (proximal)", "knee_tz (lateral)"],
                "meaning": "knee law intercept: tibia translation at the standing pose, knee frame axes, m"}


def fuse_knee_intercepts(laws: dict, standing: dict, joints: dict) -> tuple[dict, dict, dict]:
    """Each fitted law's intercept fused with the MRI's (`fuse_knee_standing_translation`).

    MRI: 0 with the knee centre's detection covariance, isotropic equivalent (the law's axes are the knee
    frame's); motion: the fitted law at the standing pose (`standing`, from `fit_knee_laws`).

    Returns
    -------
    laws : side -> (CorrelativeLaw with the fused intercept, provenance text); intercepts : side -> `KneeIntercept`;
    sources : ``knee_law_<side>`` -> provenance text
    """
    out, intercepts, sources = {}, {}, {}
    for s, (law, text) in laws.items():
        if s in standing and f"knee_{s}" in joints:
            Ck = joints[f"knee_{s}"].origin_cov
            f = fuse_knee_standing_translation(np.trace(Ck) / 3 * np.eye(3), standing[s].mean, standing[s].cov)
            C = np.array(law.coefficients, float)
            C[:, -1] = f.mean
            law = replace(law, coefficients=C)
            intercepts[s] = KneeIntercept(standing[s], f)
            text += ("; standing translation (intercept) fused: " + " / ".join(f"{1e3 * v:+.2f}" for v in f.mean)
                     + f" mm (MRI weight {f.shares[0]:.2f})")
        out[s] = (law, text)
        sources[f"knee_law_{s}"] = text
    return out, intercepts, sources
