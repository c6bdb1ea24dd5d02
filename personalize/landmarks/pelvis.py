"""Pelvis: acetabular sphere centres, ASIS, PSIS, pubic symphysis and the ISB frame.

Orientation from the bone alone:

* medio-lateral line = through the two acetabular sphere centres (found by
  Hough voting of the concave sockets along the normals, refined by robust
  sphere fits on the lunate surfaces);
* superior = side of the iliac wings: the surface centroid lies well above
  the line of the hip centres;
* anterior = the side of the pubic symphysis (the lowest bone near the
  mid-sagittal plane lies in front of the hip centres; the coccyx, also in
  that plane, is behind and higher), confirmed by the femurs when present;
* the anterior pelvic plane is then refined as the plane touching both ASIS
  and the symphysis (convex-hull support, as in Kai et al. 2014).
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError
from lowerlimb.geometry import unit

from .common import FLAG_LOW_CONFIDENCE, BoneLandmarks, Landmark
from .shape_fits import (hough_centres, isotropic_cov, perpendicular, principal_axes, refine_sphere, size_unit,
                         sphere_centre_cov, sphere_fit_json)
from .surface import Surface, extreme_vertex

__all__ = ["detect_pelvis"]

ACETABULUM_RADII = np.arange(0.016, 0.0341, 0.0015)
#: m, the medio-lateral extent below which the pelvis is taken as smaller than an adult's and every length of
#: the search (socket radii, distances, bands) shrinks with it: a bit below the narrowest adult pelvis of the
#: real sets (ICL-MRI 261, LHDL-CT 293, TLEM2-MRI 270, MC22 259 mm, with or without the sacrum), so adults keep
#: the constants they were chosen on and a child's pelvis (7-10 years: 150-200 mm) is searched at its own size
ADULT_PELVIS_WIDTH = 0.255


def detect_pelvis(surface: Surface, name: str = "pelvis", anterior_hint: np.ndarray | None = None) -> BoneLandmarks:
    """Detect pelvic landmarks (metres, any pose).

    Parameters
    ----------
    surface : Surface
    name : str
    anterior_hint : (3,) array, optional
        Anterior direction of the femurs, used to confirm the pelvis' own cue.
    """
    res = BoneLandmarks(bone=name, side=None)
    V, Nrm, A = surface.vertices, surface.normals, surface.areas
    cen = (A @ V) / A.sum()
    u = size_unit(V, principal_axes(V, A)[1][:, 0], ADULT_PELVIS_WIDTH, res, "wide")
    peaks = hough_centres(V, Nrm, u * ACETABULUM_RADII, inward=True, tol=0.0015 * u, n_peaks=8, min_separation=0.03 * u)
    fits = []
    for _, c0, r0 in peaks:
        try:
            f, sel = refine_sphere(V, Nrm, c0, r0, band=max(0.002 * u, 0.08 * r0), convex=False, min_cos=0.7)
        except FitError:
            continue
        if not 0.014 * u < f.radius < 0.04 * u or sel.sum() < 50:
            continue
        if any(np.linalg.norm(np.asarray(f.centre) - g[0].centre) < 0.03 * u for g in fits):
            continue
        fits.append((f, sel))
    # the two sockets: the pair of candidates far apart (> 10 cm in an adult) with most support
    pair = None
    for i in range(len(fits)):
        for j in range(i + 1, len(fits)):
            d = np.linalg.norm(fits[i][0].centre - fits[j][0].centre)
            if 0.1 * u < d < 0.3 * u:
                s = fits[i][1].sum() + fits[j][1].sum()
                if pair is None or s > pair[0]:
                    pair = (s, i, j)
    if pair is None:
        res.flag(FLAG_LOW_CONFIDENCE, "two acetabula not found")
        return res
    (fa, sa), (fb, sb) = fits[pair[1]], fits[pair[2]]
    ca, cb = np.asarray(fa.centre, float), np.asarray(fb.centre, float)
    mid = 0.5 * (ca + cb)
    ml = unit(cb - ca)
    sup = unit(perpendicular(cen - mid, ml))
    # anterior: lowest mid-sagittal bone = symphysis
    mids = np.abs((V - mid) @ ml) < 0.015 * u
    w = np.cross(sup, ml)
    low = mids & (((V - mid) @ sup) < -0.01 * u)
    ant = None
    if low.sum() > 10:
        k = np.flatnonzero(low)[np.argmin(((V[low] - mid) @ sup))]
        ant = w if (V[k] - mid) @ w > 0 else -w
    if anterior_hint is not None:
        hint = unit(perpendicular(anterior_hint, ml))
        if ant is None:
            ant = w if hint @ w > 0 else -w
        else:
            # the femurs' anterior direction is the stronger cue (the symphysis
            # cue is confused by the coccyx when the sacrum is included)
            ant = w if hint @ w > 0 else -w
    if ant is None:
        res.flag(FLAG_LOW_CONFIDENCE, "pelvic anterior direction not found")
        ant = w
    right = np.cross(ant, sup)
    (cr, fr, sr), (cl, fl, sl) = ((ca, fa, sa), (cb, fb, sb)) if (ca - cb) @ right > 0 else ((cb, fb, sb), (ca, fa, sa))
    res.landmarks["acetabulum_centre_r"] = Landmark(cr.copy(), sphere_centre_cov(fr))
    res.landmarks["acetabulum_centre_l"] = Landmark(cl.copy(), sphere_centre_cov(fl))
    res.scalars["acetabulum_radius_r"] = float(fr.radius)
    res.scalars["acetabulum_radius_l"] = float(fl.radius)
    res.scalar_sd["acetabulum_radius_r"] = float(np.sqrt(max(np.asarray(fr.covariance)[3, 3], 0.0)))
    res.scalar_sd["acetabulum_radius_l"] = float(np.sqrt(max(np.asarray(fl.covariance)[3, 3], 0.0)))
    for lab, f, s in (("r", fr, sr), ("l", fl, sl)):
        res.fits[f"acetabulum_{lab}"] = sphere_fit_json(f, int(s.sum()))
    noise = float(max(fr.rms, fl.rms))

    # ---- anterior pelvic plane: ASIS (both) and symphysis, iterated -----------------
    x = (V - mid) @ right
    hgt = (V - mid) @ sup
    for _ in range(3):
        r_mask = (x > 0.03 * u) & (hgt > 0.02 * u)
        l_mask = (x < -0.03 * u) & (hgt > 0.02 * u)
        s_mask = (np.abs(x) < 0.02 * u) & (hgt < 0.0)
        if not (r_mask.any() and l_mask.any() and s_mask.any()):
            break
        kr = extreme_vertex(surface, ant, r_mask)
        kl = extreme_vertex(surface, ant, l_mask)
        ks = extreme_vertex(surface, ant, s_mask)
        n = np.cross(V[kr] - V[ks], V[kl] - V[ks])
        n = unit(n if n @ ant > 0 else -n)
        if np.allclose(n, ant, atol=1e-9):
            break
        ant = unit(perpendicular(n, right))
        sup = np.cross(right, ant)
        hgt = (V - mid) @ sup
    # ---- ISB frame (Wu et al. 2002), iterated with the landmarks that define it ---------
    # ASIS = most anterior points of each iliac wing along the ISB X axis, PSIS
    # the most posterior ones about the ASIS level, symphysis = most anterior
    # mid-sagittal point below the hip centres; X lies in the plane of ASIS and
    # PSIS, perpendicular to the inter-ASIS axis Z.
    X = ant
    Z = right
    kpr = kpl = None
    for _ in range(5):
        Y = np.cross(Z, X)
        o_h = (V - mid) @ Y
        r_mask = (x > 0.03 * u) & (o_h > 0.02 * u)
        l_mask = (x < -0.03 * u) & (o_h > 0.02 * u)
        kr = extreme_vertex(surface, X, r_mask)
        kl = extreme_vertex(surface, X, l_mask)
        o = 0.5 * (V[kr] + V[kl])
        Z_new = unit(V[kr] - V[kl])
        ya = (V - o) @ Y
        half = 0.5 * float(np.linalg.norm(V[kr] - V[kl]))
        zz = (V - o) @ Z_new
        kpr_new = kpl_new = None
        for sgn in (1.0, -1.0):
            # iliac wing behind the sacro-iliac joint: 30-75 % of the ASIS half-distance
            # from the midline (the sacrum and coccyx lie within the inner quarter)
            # ... and well above the hip centres (the lower sacrum is not)
            m = (sgn * zz > 0.3 * half) & (sgn * zz < 0.75 * half) & (np.abs(ya) < 0.035 * u) \
                & ((V - mid) @ Y > 0.6 * ((o - mid) @ Y))
            if m.any():
                k = extreme_vertex(surface, -X, m)
                if sgn > 0:
                    kpr_new = k
                else:
                    kpl_new = k
        if kpr_new is None or kpl_new is None:
            X_new = unit(perpendicular(X, Z_new))
        else:
            X_new = unit(perpendicular(o - 0.5 * (V[kpr_new] + V[kpl_new]), Z_new))
        done = np.allclose(X_new, X, atol=1e-10) and np.allclose(Z_new, Z, atol=1e-10)
        X, Z, kpr, kpl = X_new, Z_new, kpr_new, kpl_new
        x = (V - mid) @ Z
        if done:
            break
    Y = np.cross(Z, X)
    s_mask = (np.abs((V - o) @ Z) < 0.02 * u) & (((V - mid) @ Y) < 0.0)
    ks = extreme_vertex(surface, X, s_mask) if s_mask.any() else None
    sd_lm = np.hypot(noise, 0.002)
    res.landmarks["RASI"] = Landmark(V[kr].copy(), isotropic_cov(sd_lm))
    res.landmarks["LASI"] = Landmark(V[kl].copy(), isotropic_cov(sd_lm))
    if ks is not None:
        res.landmarks["SYMP"] = Landmark(V[ks].copy(), isotropic_cov(sd_lm))
    for name, k in (("RPSI", kpr), ("LPSI", kpl)):
        if k is not None:
            res.landmarks[name] = Landmark(V[k].copy(), isotropic_cov(np.hypot(noise, 0.003)))
    if kpr is None or kpl is None:
        missing = " and ".join(n for n, k in (("RPSI", kpr), ("LPSI", kpl)) if k is None)
        res.flag(FLAG_LOW_CONFIDENCE, f"{missing} not found; pelvic X from the anterior pelvic plane")
    res.frames["isb"] = {"origin": o, "rotation": np.column_stack([X, Y, Z])}
    res.frames["anatomical"] = {"origin": mid, "rotation": np.column_stack([ant, sup, right])}
    return res
