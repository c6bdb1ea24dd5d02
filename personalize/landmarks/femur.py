"""Femur landmarks: head sphere, neck, shaft, trochanter, condyles, knee axis, epicondyles.

Orientation comes from the bone alone, never from the scanner axes:

* long axis = largest principal axis of the surface;
* proximal end = the end whose cross-section is flatter (head-neck-trochanter
  block) than the roughly square condylar block; a planar cut marks a
  truncated end, which then cannot be the detected end;
* medial = the side of the femoral head centre relative to the shaft axis;
* posterior = the side towards which the condyles project from the shaft
  axis (the distal block reaches 2-4 times farther posteriorly than
  anteriorly); the anterior bow of the shaft is checked against it;
* side = chirality of (anterior, proximal, medial): for a right femur the
  medial direction is to the subject's left, ``(X x Y) . medial < 0``.

Articular primitives are found by Hough voting along surface normals
(`common.hough_centres`), then refined by robust fits on the points within a
band of the primitive (`common.refine_sphere`).
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError

from .common import (FLAG_LOW_CONFIDENCE, FLAG_NAME_MISMATCH, FLAG_TRUNCATED, Axis, BoneLandmarks, Landmark, Surface,
                     axis_sd_deg, extreme_vertex, hough_centres, line_through, long_bone_axes, orient,
                     perpendicular, refine_sphere, shaft_line, sphere_centre_cov, unit)

__all__ = ["detect_femur", "head_coverage", "find_head", "posterior_condyle_cylinder"]

HEAD_RADII = np.arange(0.012, 0.0331, 0.0015)      # adult 20-28 mm, juvenile from ~12 mm
#: the femoral head's articular cap: points within this angle of the head's pole (opposite the neck), deg; the
#: head-neck junction lies at about 130-140 deg
HEAD_CAP_DEG = 110.0
CONDYLE_RADII = np.arange(0.012, 0.0361, 0.0015)
#: condyle-centre fits use the posterior-distal arc up to 45 degrees anterior
#: of the distal direction (normal . anterior < cos 45): the centre of an oval
#: arc is ill-posed when the arc stops at the distal point, and the trochlea
#: begins farther forward (its stray points are down-weighted by the robust fit)
ANT_MAX = float(np.cos(np.radians(45.0)))


def _sphere_landmark(fit) -> Landmark:
    return Landmark(np.asarray(fit.centre, float), sphere_centre_cov(fit))


def detect_femur(surface: Surface, name: str = "femur_r") -> BoneLandmarks:
    """Detect femoral landmarks and axes on one femur surface (metres, any pose).

    Parameters
    ----------
    surface : Surface
        The femur (`common.as_surface`).
    name : str
        Canonical bone name (``femur_r`` / ``femur_l``); its side is checked
        against the side found from the bone's chirality.

    Returns
    -------
    BoneLandmarks
        Marker-named landmarks (``RTRO``, ``RKNE`` lateral and ``RMFC`` medial
        epicondyle, ``L`` prefix on the left), anatomical landmarks, axes
        (``neck_axis``, ``shaft_axis``, ``knee_axis`` pointing to the subject's
        right), scalars and the ISB frame.
    """
    V, Nrm = surface.vertices, surface.normals
    res = BoneLandmarks(bone=name, side=name[-1] if name[-2:] in ("_r", "_l") else None)
    lb = long_bone_axes(surface)
    e, h, L = lb.axis, lb.h, lb.length

    # ---- which end is proximal ---------------------------------------------------
    # Both ends intact: the flatter end is proximal.  One end cut: the intact
    # end is classified by its own flatness (head block < ~0.65 < condyles).
    if lb.cut[1] and lb.cut[-1]:
        res.flag(FLAG_TRUNCATED, "both ends of the femur are planar cuts")
        res.flag(FLAG_LOW_CONFIDENCE)
        prox_sign = 1 if lb.flatness[1] < lb.flatness[-1] else -1
    elif lb.cut[1] or lb.cut[-1]:
        intact = -1 if lb.cut[1] else 1
        res.flag(FLAG_TRUNCATED, f"femur truncated ({'distal' if lb.flatness[intact] < 0.65 else 'proximal'} part missing)")
        prox_sign = intact if lb.flatness[intact] < 0.65 else -intact
    else:
        prox_sign = 1 if lb.flatness[1] < lb.flatness[-1] else -1
        if abs(lb.flatness[1] - lb.flatness[-1]) < 0.08:
            res.flag(FLAG_LOW_CONFIDENCE, "proximal and distal femoral ends look alike")
    prox = prox_sign * e
    hp = prox_sign * h                           # height towards proximal
    top, bot = float(hp.max()), float(hp.min())
    has_prox = not lb.cut[prox_sign]
    has_dist = not lb.cut[-prox_sign]
    depth_p = min(0.25 * L, 0.11)
    depth_d = min(0.22 * L, 0.09)
    prox_region = hp > top - depth_p
    dist_region = hp < bot + depth_d

    # ---- shaft axis ----------------------------------------------------------------
    lo = bot + (0.25 * L if has_dist else 0.05 * L)
    hi = top - (0.30 * L if has_prox else 0.05 * L)
    sp, sd = shaft_line(surface, e, h * 1.0, *(sorted((prox_sign * lo, prox_sign * hi))))
    sd = orient(sd, prox)
    res.axes["shaft_axis"] = Axis(point=sp, direction=sd, sd_deg=1.0)

    # ---- femoral head --------------------------------------------------------------
    head = sel = None
    if has_prox:
        try:
            head, sel = find_head(surface, prox_region)
        except FitError as exc:
            res.flag(FLAG_LOW_CONFIDENCE, f"femoral head sphere: {exc}")
        if head is not None:
            res.landmarks["femoral_head_centre"] = _sphere_landmark(head)
            res.scalars["femoral_head_radius"] = float(head.radius)
            res.scalar_sd["femoral_head_radius"] = float(np.sqrt(max(np.asarray(head.covariance)[3, 3], 0.0)))
            res.fits["femoral_head"] = _sphere_json(head, int(sel.sum()))
    noise = float(head.rms) if head is not None else 0.0005
    if has_prox:
        cover = head_coverage(surface, head, sel) if head is not None else 0.0
        offset = 0.0
        if head is not None:
            offset = float(np.linalg.norm(perpendicular(np.asarray(head.centre) - sp, sd)))
        res.scalars["femoral_head_coverage"] = cover
        if cover < 0.4 or (head is not None and offset < 0.8 * float(head.radius)):
            # a femoral head is covered by cartilage over ~2/3 of a sphere and
            # sits on the neck, well off the shaft axis; a sphere found on a
            # tibia, talus or pelvis covers less and/or sits on the long axis
            res.flag(FLAG_NAME_MISMATCH, f"{name}: no femoral head found (sphere coverage {cover:.0%}, "
                                         f"{offset * 1e3:.0f} mm off the shaft axis); is this mesh a femur?")
            res.flag(FLAG_LOW_CONFIDENCE)

    # ---- medial / anterior / side -----------------------------------------------------
    med = None
    if head is not None:
        off = perpendicular(np.asarray(head.centre) - sp, sd)
        if np.linalg.norm(off) > 0.01:
            med = unit(off)
        else:
            res.flag(FLAG_LOW_CONFIDENCE, "femoral head centre lies on the shaft axis")
    cond = []
    if has_dist:
        # Posterior/distal facing points of the distal block vote for condyle spheres.
        pk = hough_centres(V[dist_region], Nrm[dist_region], CONDYLE_RADII, inward=False,
                           tol=0.0015, n_peaks=6, min_separation=0.015)
        cond = [p for p in pk]
    if med is None and len(cond) >= 2:
        med = unit(perpendicular(cond[0][1] - cond[1][1], sd))  # sign fixed below if possible
    if med is None:
        res.flag(FLAG_LOW_CONFIDENCE, "no medial-lateral cue (head and condyles missing)")
        med = unit(perpendicular(np.cross(sd, [1.0, 0.0, 0.0]) + 1e-3, sd))
    w = unit(np.cross(sd, med))                   # one of anterior / posterior
    post = None
    if has_dist:
        q = (V[dist_region] - sp) @ w
        ext_pos, ext_neg = float(q.max()), float(-q.min())
        post = w if ext_pos > ext_neg else -w
        if max(ext_pos, ext_neg) < 1.3 * min(ext_pos, ext_neg):
            res.flag(FLAG_LOW_CONFIDENCE, "condyles do not project clearly posteriorly")
    else:
        # Anterior bow of the shaft: mid-shaft centroid lies anterior of the line of the ends.
        bow = _bow(surface, hp, bot, top) @ w
        post = -w if bow > 0 else w
        res.flag(FLAG_LOW_CONFIDENCE, "anterior direction from shaft bow only (distal femur missing)")
    ant = -post
    z_right = np.cross(ant, sd)                   # X x Y: to the subject's right
    side = "r" if float(z_right @ med) < 0 else "l"
    named = name[-1] if name[-2:] in ("_r", "_l") else None
    if named is not None and side != named:
        if head is None:
            # no head: the medial direction was a guess; honour the name
            med = -med
            side = named
            res.notes.append(f"{name}: medial side from the name (no femoral head)")
        elif not has_dist:
            # no condyles: anterior came from the shaft bow only; honour the name
            ant = -ant
            z_right = np.cross(ant, sd)
            side = named
            res.notes.append(f"{name}: anterior direction from the name (no condyles)")
    res.side = side
    P = "R" if side == "r" else "L"
    right = z_right                                # unit already (ant, sd orthonormal)
    lat = -med

    # ---- condyles -------------------------------------------------------------------------
    if has_dist:
        # condylar block: below the condyle centres plus ~3/4 radius; the
        # femoral head radius sets the scale (juvenile and adult bones alike)
        scale = float(head.radius) if head is not None else 0.023
        cond_region = hp < bot + 1.8 * scale
        _condyles(surface, res, cond_region, dist_region, med, ant, sd, P, noise)

    # ---- neck axis and diameter --------------------------------------------------------
    if head is not None:
        _neck(surface, res, head, sp, sd, prox_region)

    # ---- greater trochanter tip: most proximal point lateral of the shaft axis -----
    if has_prox:
        lat_mask = prox_region & (((V - sp) @ lat) > 0.5 * lb.shaft_radius)
        if head is not None:
            lat_mask &= np.linalg.norm(V - head.centre, axis=1) > 1.3 * head.radius
        if lat_mask.any():
            # "most proximal" along the mechanical axis (knee centre -> head
            # centre), the femur's vertical in standing, else the shaft axis
            up = sd
            if head is not None and "intercondylar_midpoint" in res.landmarks:
                up = unit(np.asarray(head.centre) - res.landmarks["intercondylar_midpoint"].position)
            k = extreme_vertex(surface, up, lat_mask, smooth=0.001)
            res.landmarks[f"{P}TRO"] = Landmark(V[k].copy(), _iso(noise, 0.002))

    # ---- frame (ISB, Wu et al. 2002) ---------------------------------------------------
    if "femoral_head_centre" in res.landmarks and f"{P}KNE" in res.landmarks:
        hc = res.landmarks["femoral_head_centre"].position
        ke, me = res.landmarks[f"{P}KNE"].position, res.landmarks[f"{P}MFC"].position
        Y = unit(hc - 0.5 * (ke + me))
        Zr = ke - me if side == "r" else me - ke
        Z = unit(perpendicular(Zr, Y))
        X = np.cross(Y, Z)
        res.frames["isb"] = {"origin": hc.copy(), "rotation": np.column_stack([X, Y, Z])}
    res.frames["anatomical"] = {"origin": sp.copy(), "rotation": np.column_stack([ant, sd, right])}
    return res


def find_head(surface: Surface, region: np.ndarray):
    """Femoral-head sphere in ``region``: Hough vote, band refinement, articular refit.

    Returns ``(fit, selected_mask)`` or ``(None, None)`` when no sphere is voted.
    """
    V, Nrm = surface.vertices, surface.normals
    peaks = hough_centres(V[region], Nrm[region], HEAD_RADII, inward=False, tol=0.0015)
    if not peaks:
        return None, None
    _, c0, r0 = peaks[0]
    fit, sel = refine_sphere(V, Nrm, c0, r0, band=max(0.0015, 0.08 * r0), min_cos=0.8, mask=region)
    return _articular_head(V, Nrm, surface.areas, fit, sel, region)


def head_coverage(surface: Surface, fit, sel) -> float:
    """Fraction of the fitted sphere's area covered by the surface points used (0-1)."""
    if fit is None or sel is None:
        return 0.0
    return float(min(1.0, surface.areas[sel].sum() / (4.0 * np.pi * float(fit.radius) ** 2)))


def _articular_head(V, Nrm, A, fit, sel, region):
    """Refit the head sphere on its articular part only.

    The neck joins the head about 130-140 degrees from the head's pole (the
    point opposite the neck); the junction is blended and pulls a sphere fit
    towards the neck.  The neck direction is the mean direction of the bone
    in the shell just outside the head; points more than 110 degrees from the
    pole, or farther than a band of 3 rms (at least 1 mm) from the sphere,
    are left out of the final fit.
    """
    c, r = np.asarray(fit.centre, float), float(fit.radius)
    dist = np.linalg.norm(V - c, axis=1)
    shell = region & (dist > 1.15 * r) & (dist < 1.6 * r)
    if shell.sum() < 10:
        return fit, sel
    pole = -unit((A[shell] @ V[shell]) / A[shell].sum() - c)
    for _ in range(2):
        d = V - c
        dist = np.linalg.norm(d, axis=1)
        cos_pole = (d @ pole) / np.maximum(dist, 1e-12)
        band = max(0.001, 3.0 * float(fit.rms))
        keep = region & (np.abs(dist - r) < band) & (cos_pole > np.cos(np.radians(HEAD_CAP_DEG)))
        keep &= np.einsum("ij,ij->i", d, Nrm) > 0.8 * dist
        if keep.sum() < 30:
            break
        from personalize.fitting import fit_sphere
        fit = fit_sphere(V[keep], normals=Nrm[keep])
        sel = keep
        c, r = np.asarray(fit.centre, float), float(fit.radius)
    return fit, sel


def _iso(noise: float, extra: float) -> np.ndarray:
    s2 = noise ** 2 + extra ** 2
    return s2 * np.eye(3)


def _bow(surface: Surface, hp, bot, top) -> np.ndarray:
    V, A = surface.vertices, surface.areas
    L = top - bot

    def cen(f0, f1):
        m = (hp > bot + f0 * L) & (hp < bot + f1 * L)
        return (A[m] @ V[m]) / A[m].sum()
    return cen(0.45, 0.55) - 0.5 * (cen(0.2, 0.3) + cen(0.7, 0.8))


def _sphere_json(fit, n: int) -> dict:
    return {"type": "sphere", "centre": np.asarray(fit.centre).tolist(), "radius": float(fit.radius),
            "rms": float(fit.rms), "n_points": n, "converged": bool(fit.converged)}


def _condyles(surface, res, cond_region, dist_region, med, ant, sd, P, noise):
    """Medial and lateral condyle centres, the knee axis, epicondyles.

    The posterior and distal condylar surfaces (normals not facing anteriorly,
    i.e. not the trochlea) of the distal block are split at the notch into a
    medial and a lateral half.  Each half gets a robust sphere; the line
    through the two sphere centres is a first flexion axis.  Each condyle
    centre is then the centre of an ellipsoid with one semi-axis along that
    axis (`fit_ellipsoid_about_axis`, 7 parameters), fitted to the
    posterior-distal arc extended to 45 degrees anterior of the distal
    direction and refitted on the points within 3 rms; if either ellipsoid is
    implausible both condyles fall back to their spheres (noted).  The two
    semi-axes across the flexion axis are the condyle's sagittal ellipse
    (``*_condyle_a >= *_condyle_b``).

    The knee (flexion) axis reported is the cylinder through the posterior
    condyles (`posterior_condyle_cylinder`), the convention of hand-built
    models (NMSBuilder) and of STAPLE; the knee centre
    (``intercondylar_midpoint``) is the point of that axis between the
    condyles: the condyle centres' midpoint projected on it.  Without a
    cylinder the line through the condyle centres is kept (noted).
    """
    from personalize.fitting import fit_sphere

    V, Nrm = surface.vertices, surface.normals
    # not the trochlea (anterior-facing) nor the epicondylar side walls
    facing = cond_region & ((Nrm @ ant) < 0.3) & (np.abs(Nrm @ med) < 0.5)
    if facing.sum() < 60:
        res.flag(FLAG_LOW_CONFIDENCE, "femoral condyles not found")
        return
    m = V @ med
    # notch: the emptiest medio-lateral bin between the two condylar masses
    # two condylar masses along the medio-lateral line: 1-D two-means (area-weighted)
    mm, aa = m[facing], surface.areas[facing]
    c1, c2 = np.percentile(mm, [25, 75])
    for _ in range(20):
        split = 0.5 * (c1 + c2)
        lo_, hi_ = mm <= split, mm > split
        n1 = (aa[lo_] @ mm[lo_]) / aa[lo_].sum()
        n2 = (aa[hi_] @ mm[hi_]) / aa[hi_].sum()
        if abs(n1 - c1) + abs(n2 - c2) < 1e-7:
            break
        c1, c2 = n1, n2
    split = 0.5 * (c1 + c2)
    sep = c2 - c1
    # each condyle's window is centred on its lowest (most distal) point: the
    # 2-means centres are pulled towards the notch roof
    low = {}
    hgt = V @ sd
    for label, side_mask in (("medial", facing & (m > split)), ("lateral", facing & (m <= split))):
        idx = np.flatnonzero(side_mask)
        low[label] = float(m[idx[np.argmin(hgt[idx])]]) if len(idx) else (c2 if label == "medial" else c1)
    sph, sels = {}, {}
    for label, centre_ml in (("medial", low["medial"]), ("lateral", low["lateral"])):
        # a window of +-30 % of the condyle separation around each condyle's
        # lowest point keeps its own posterior-distal surface, not the notch
        # roof nor the epicondyles
        half = np.abs(m - centre_ml) < 0.3 * sep
        sel = np.flatnonzero(facing & half)
        sel = sel[:: max(1, len(sel) // 3000)]
        try:
            sph[label] = fit_sphere(V[sel], normals=Nrm[sel])
        except FitError:
            res.flag(FLAG_LOW_CONFIDENCE, f"{label} condyle could not be fitted")
            return
        wide = np.flatnonzero(cond_region & half & ((Nrm @ ant) < ANT_MAX) & (np.abs(Nrm @ med) < 0.5))
        sels[label] = wide[:: max(1, len(wide) // 3000)]
    # flexion axis direction: line through the condyle SPHERE centres.  Both
    # condyles bias their sphere centres alike, so the direction is robust
    # where free ellipsoid centres (over partial, noisy arcs) are not.
    ms = Landmark(np.asarray(sph["medial"].centre, float), sphere_centre_cov(sph["medial"]))
    ls_ = Landmark(np.asarray(sph["lateral"].centre, float), sphere_centre_cov(sph["lateral"]))
    ax = line_through(ms, ls_) if res.side == "r" else line_through(ls_, ms)
    # condyle centres: ellipsoids with one semi-axis along the flexion axis
    # (7 parameters instead of 9: the free ellipsoid drifts along near-flat
    # directions on a noisy partial arc, the sphere is biased on an oval one)
    fits = {}
    for label in ("medial", "lateral"):
        fits[label] = _condyle_about_axis(V, surface.areas, sels[label], sph[label], ax.direction, ant)
    use_ell = all(f is not None for f in fits.values())
    if not use_ell:
        fits = sph
    for label, f in fits.items():
        cov = np.asarray(f.covariance)[:3, :3] + 1e-12 * np.eye(3)
        res.landmarks[f"{label}_condyle_centre"] = Landmark(np.asarray(f.centre, float), cov)
        if use_ell:
            # sagittal semi-axes: the two perpendicular to the flexion axis
            Rf, rr = np.asarray(f.rotation), np.asarray(f.radii, float)
            k_ax = int(np.argmax(np.abs(Rf.T @ ax.direction)))
            radii = np.sort(np.delete(rr, k_ax))[::-1]
            res.scalars[f"{label}_condyle_a"] = float(radii[0])
            res.scalars[f"{label}_condyle_b"] = float(radii[1])
            res.fits[f"{label}_condyle"] = {"type": "ellipsoid", "centre": np.asarray(f.centre).tolist(),
                                            "radii": rr.tolist(), "rotation": Rf.tolist(), "rms": float(f.rms),
                                            "converged": bool(f.converged), "axis_constrained": True}
        else:
            res.scalars[f"{label}_condyle_a"] = float(f.radius)
            res.scalars[f"{label}_condyle_b"] = float(f.radius)
            res.fits[f"{label}_condyle"] = _sphere_json(f, len(sels[label]))
    res.notes.append(f"condyles modelled as {'axis-constrained ellipsoids' if use_ell else 'spheres'}")
    m_lm, l_lm = res.landmarks["medial_condyle_centre"], res.landmarks["lateral_condyle_centre"]
    mid = 0.5 * (m_lm.position + l_lm.position)
    mid_cov = 0.25 * (m_lm.cov + l_lm.cov)
    # flexion axis: the cylinder through the posterior condyles (the convention of
    # hand-built models and of STAPLE); the line through the condyle centres is the
    # fallback when no cylinder can be fitted
    # "distal" is taken from the shaft axis, not the mechanical axis, so that the
    # result does not depend on whether the femoral head is in the field of view
    cyl = posterior_condyle_cylinder(surface, cond_region, mid, ax.direction, sd, ant,
                                     m_lm.position, l_lm.position)
    if cyl is None:
        res.notes.append("knee axis: no cylinder on the posterior condyles; line through the condyle centres")
        ax = Axis(point=mid, direction=ax.direction, sd_deg=ax.sd_deg)
        cyl_fit = None
    else:
        fit, sel, u = cyl
        u = orient(u, ax.direction)
        p = np.asarray(fit.point, float)
        # knee centre: the point of the cylinder axis between the condyles (the
        # condyle centres' midpoint projected on it)
        mid = p + float((mid - p) @ u) * u
        Pp = np.eye(3) - np.outer(u, u)
        mid_cov = Pp @ (np.asarray(fit.covariance)[:3, :3]) @ Pp + float(u @ mid_cov @ u) * np.outer(u, u)
        mid_cov = mid_cov + 1e-12 * np.eye(3)
        ax = Axis(point=mid, direction=u, sd_deg=axis_sd_deg(fit))
        res.scalars["posterior_condyle_radius"] = float(fit.radius)
        res.scalar_sd["posterior_condyle_radius"] = float(np.sqrt(max(np.asarray(fit.covariance)[-1, -1], 0.0)))
        res.fits["posterior_condyles"] = {"type": "cylinder", "point": mid.tolist(), "axis": u.tolist(),
                                          "radius": float(fit.radius), "rms": float(fit.rms),
                                          "n_points": int(sel.sum()), "converged": bool(fit.converged)}
        cyl_fit = fit
    sep = float(np.linalg.norm(m_lm.position - l_lm.position))
    if not 0.02 < sep < 0.09:
        res.flag(FLAG_LOW_CONFIDENCE, f"condyle centres {sep * 1e3:.0f} mm apart")

    def epicondyles(direction):
        u_ = direction if res.side == "r" else -direction    # medial -> lateral
        return (extreme_vertex(surface, u_, dist_region, smooth=0.001),
                extreme_vertex(surface, -u_, dist_region, smooth=0.001))

    k_lat, k_med = epicondyles(ax.direction)
    r_cond = 0.5 * (float(sph["medial"].radius) + float(sph["lateral"].radius))
    ax, mid, mid_cov = _knee_cross_check(surface, res, cond_region, ax, mid, mid_cov, cyl_fit, sd, ant,
                                         m_lm.position, l_lm.position, V[k_med], V[k_lat], r_cond, noise)
    res.axes["knee_axis"] = ax
    res.landmarks["intercondylar_midpoint"] = Landmark(mid, mid_cov)
    # Epicondyles: extreme points along the knee axis in the distal block.
    k_lat, k_med = epicondyles(ax.direction)
    res.landmarks[f"{P}KNE"] = Landmark(V[k_lat].copy(), _iso(noise, 0.002))
    res.landmarks[f"{P}MFC"] = Landmark(V[k_med].copy(), _iso(noise, 0.002))


#: model standard deviation of each knee estimate, as a fraction of the mean condyle
#: sphere radius (centres; ~1 mm and ~7.5 mm on an adult knee), and in degrees (axes):
#: how far that construction can lie from the flexion axis on a real femur.  The
#: cylinders and spheres describe the articular arc; the epicondyles are the bone's
#: widest points, a coarse axis 3-8 mm from the articular one on real femurs
KNEE_MODEL_SD = {"posterior_condyle_cylinder": (0.04, 1.0), "posterior_arc_cylinder": (0.04, 1.0),
                 "posterior_arc_spheres": (0.04, 3.0), "epicondyles": (0.3, 5.0)}


def _knee_cross_check(surface, res, cond_region, ax, mid, mid_cov, cyl_fit, sd, ant, medial, lateral,
                      epi_med, epi_lat, r_cond, noise):
    """Knee centre and axis from independent estimates, tested against each other (`crosscheck`).

    Estimates (first = primary): the posterior-condyle cylinder (normals in
    the posterior arc), the posterior-arc cylinder (points lying in it too),
    the line through spheres fitted to each condyle's posterior arc, and the
    epicondylar line (a check only: it votes on agreement, not in the mean).  The centre is compared across the primary axis; its
    model sd is `KNEE_MODEL_SD` x the condyle sphere radius.  Returns the
    combined axis, centre and covariance (fit + spread of left-out estimates).
    """
    from personalize.fitting import fit_sphere

    from .crosscheck import Estimate, cross_check, cross_check_directions

    u0 = ax.direction
    V, Nrm = surface.vertices, surface.normals
    est_c, est_u = [], []

    def add(name, point, cov, direction, sd_deg, check=False):
        kc, ka = KNEE_MODEL_SD[name]
        est_c.append(Estimate(name, np.asarray(point, float), np.asarray(cov, float), kc * r_cond, check))
        d = orient(unit(np.asarray(direction, float)), u0)
        est_u.append(Estimate(name, d, np.radians(sd_deg) ** 2 * np.eye(3), np.radians(ka), check))

    def on_line(p, u):                            # the line's point across from the primary centre
        p = np.asarray(p, float)
        return p + float((mid - p) @ u) * u

    if cyl_fit is not None:
        add("posterior_condyle_cylinder", mid, mid_cov, u0, ax.sd_deg)
    arc = posterior_condyle_cylinder(surface, cond_region, mid, u0, sd, ant, medial, lateral, by_position=True)
    u_arc = u0
    if arc is not None:
        fit2, sel2, u2 = arc
        u_arc = orient(u2, u0)
        Pp = np.eye(3) - np.outer(u_arc, u_arc)
        add("posterior_arc_cylinder", on_line(fit2.point, u_arc), Pp @ np.asarray(fit2.covariance)[:3, :3] @ Pp,
            u_arc, axis_sd_deg(fit2))
        res.fits["posterior_arc_cylinder"] = {"type": "cylinder", "point": np.asarray(fit2.point).tolist(),
                                              "axis": u_arc.tolist(), "radius": float(fit2.radius),
                                              "rms": float(fit2.rms), "n_points": int(sel2.sum())}
    # spheres on each condyle's posterior arc (lying and facing 0-90 deg from distal about the arc axis)
    p_arc = est_c[-1].value if est_c else mid
    dist_dir = unit(perpendicular(-sd, u_arc))
    post_dir = orient(np.cross(u_arc, dist_dir), -ant)
    d = V - p_arc
    thp, thn = np.arctan2(d @ post_dir, d @ dist_dir), np.arctan2(Nrm @ post_dir, Nrm @ dist_dir)
    lo, hi = np.radians(POSTERIOR_ARC_DEG)
    t = d @ u_arc
    sep = float(np.linalg.norm(np.asarray(medial) - lateral))
    base = cond_region & (thp >= lo) & (thp <= hi) & (thn >= lo) & (thn <= hi) & (np.abs(Nrm @ u_arc) < CYL_AXIAL_MAX)
    cs = []
    for c in (medial, lateral):
        k = base & (np.abs(t - float((np.asarray(c) - p_arc) @ u_arc)) < CONDYLE_BAND * sep)
        if k.sum() < 30:
            break
        try:
            cs.append(fit_sphere(V[k], normals=Nrm[k]))
        except FitError:
            break
    if len(cs) == 2:
        a_, b_ = np.asarray(cs[0].centre, float), np.asarray(cs[1].centre, float)
        line = orient(unit(b_ - a_), u0)
        cov = 0.25 * (sphere_centre_cov(cs[0]) + sphere_centre_cov(cs[1]))
        sdd = float(np.degrees(np.sqrt(np.trace(sphere_centre_cov(cs[0]) + sphere_centre_cov(cs[1])) / 3)
                               / max(np.linalg.norm(b_ - a_), 1e-3)))
        add("posterior_arc_spheres", on_line(0.5 * (a_ + b_), line), cov, line, sdd)
    add("epicondyles", on_line(0.5 * (epi_med + epi_lat), unit(epi_lat - epi_med)), _iso(noise, 0.002),
        epi_lat - epi_med, 2.0, check=True)
    rc = cross_check(est_c, plane_normal=u0)
    ru = cross_check_directions(est_u)
    u = ru.value
    centre = rc.value
    cov = rc.cov_fit + rc.cov_spread + 1e-12 * np.eye(3)
    sd_deg = float(np.degrees(np.sqrt(np.trace(ru.cov_fit + ru.cov_spread) / 2)))
    res.fits["knee_cross_check"] = {"centre": rc.to_json("m"), "axis": ru.to_json("rad"),
                                    "model_sd": {k: {"centre_mm": round(v[0] * r_cond * 1e3, 3), "axis_deg": v[1]}
                                                 for k, v in KNEE_MODEL_SD.items()}}
    for r_, what, k in ((rc, "centre", 1e3), (ru, "axis", np.degrees(1.0))):
        if not r_.agree:
            res.flag(FLAG_LOW_CONFIDENCE, f"knee {what}: estimates disagree ({', '.join(r_.disagreeing)} left out; "
                                          f"spread {r_.spread * k:.1f} {'mm' if what == 'centre' else 'deg'})")
    return Axis(point=centre, direction=u, sd_deg=sd_deg), centre, cov


#: posterior condyle arc used for the flexion-axis cylinder: surface normals from
#: the distal (0 deg) to the posterior (90 deg) direction about the axis -- the
#: tibiofemoral contact arc from full extension to 90 degrees of flexion
POSTERIOR_ARC_DEG = (0.0, 90.0)
#: largest |normal . axis| of a point used for the cylinder (24 deg off radial):
#: leaves out the condyles' side walls and the rims rounded by smoothing
CYL_AXIAL_MAX = 0.4
#: half-width of each condyle's central band along the axis, as a fraction of
#: the distance between the condyle centres (+-6 mm on an adult knee): the part
#: of a condyle closest to a cylinder (its articular surface is also curved
#: coronally, so a wider band pulls the radius in and the axis towards it)
CONDYLE_BAND = 0.15


def posterior_condyle_cylinder(surface: Surface, region: np.ndarray, centre, axis, up, ant, medial, lateral,
                               iterations: int = 4, by_position: bool = False):
    r"""Cylinder through the posterior condyles (the knee flexion axis).

    Model: one circular cylinder (axis line, radius) through the articular
    arcs of both femoral condyles from the distal to the posterior point,
    minimising the sum of squared orthogonal distances
    :math:`\sum_i w_i (\lVert (I - a a^T)(x_i - p) \rVert - R)^2`
    (`personalize.fitting.fit_cylinder`, weights w = vertex areas; robust
    EM while the points are selected, then plain least squares on its
    inliers).  The points are re-selected about the current axis on every
    iteration: surface normal at an angle of ``POSTERIOR_ARC_DEG`` about the
    axis from the distal direction (distal = away from ``up``, e.g. the
    shaft axis, orthogonal to the axis) towards the posterior, within
    ``CYL_AXIAL_MAX`` of radial, and in the central band of either condyle
    (``CONDYLE_BAND`` of the condyle separation about its centre along the
    axis).  Every
    criterion is relative to the bone's own axes: the selection does not
    depend on the bone's pose in the scanner.

    With ``by_position`` the points must also *lie* in that arc about the
    current axis (angle of ``x - p`` about it), not only face it: on an oval
    condyle whose distal part is flatter than its posterior part the normal
    rule alone lets the distal surface dominate; both rules together keep the
    arc the posterior condyle occupies.  Used as a second, cross-checking
    estimate (`_knee_cross_check`).

    Returns
    -------
    (fit, selected mask, unit axis) or None when fewer than 60 points qualify,
    the fit fails or its radius leaves 10-45 mm.
    """
    from personalize.fitting import fit_cylinder

    V, Nrm, A = surface.vertices, surface.normals, surface.areas
    u = unit(np.asarray(axis, float))
    p = np.asarray(centre, float)
    sep = float(np.linalg.norm(np.asarray(medial) - np.asarray(lateral)))
    lo, hi = np.radians(POSTERIOR_ARC_DEG)
    fit = sel = None
    for _ in range(iterations):
        dist_dir = unit(perpendicular(-np.asarray(up, float), u))
        post_dir = orient(np.cross(u, dist_dir), -np.asarray(ant, float))
        th = np.arctan2(Nrm @ post_dir, Nrm @ dist_dir)
        t = (V - p) @ u
        tm, tl = (np.asarray(medial) - p) @ u, (np.asarray(lateral) - p) @ u
        win = (np.abs(t - tm) < CONDYLE_BAND * sep) | (np.abs(t - tl) < CONDYLE_BAND * sep)
        new = region & win & (th >= lo) & (th <= hi) & (np.abs(Nrm @ u) < CYL_AXIAL_MAX)
        if by_position:
            thp = np.arctan2((V - p) @ post_dir, (V - p) @ dist_dir)
            new &= (thp >= lo) & (thp <= hi)
        if new.sum() < 60:
            if fit is None:
                return None
            break
        if sel is not None and np.array_equal(new, sel):
            break
        sel = new
        try:
            fit = fit_cylinder(V[sel], normals=Nrm[sel], weights=A[sel], axis_hint=u)
        except FitError:
            return None
        u = orient(unit(np.asarray(fit.axis, float)), u)
        q = np.asarray(fit.point, float)
        p = q + float((p - q) @ u) * u
    if fit is None:
        return None
    # final plain least-squares fit on the robust fit's inliers: it converges to
    # the solver's tight step tolerance, where the EM stops on its weights, so
    # the result moves with the bone to well under 0.01 mm / 0.01 degree
    keep = sel.copy()
    keep[sel] = np.asarray(fit.inlier_weights) > 0.5
    if keep.sum() >= 60:
        try:
            fit = fit_cylinder(V[keep], normals=Nrm[keep], weights=A[keep], axis_hint=u, robust=False)
            sel = keep
            u = orient(unit(np.asarray(fit.axis, float)), u)
        except FitError:
            pass
    if not 0.010 < float(fit.radius) < 0.045:
        return None
    return fit, sel, u


def _condyle_about_axis(V, A, sel, sphere, axis, ant):
    """Condyle ellipsoid with one semi-axis along the flexion axis, or None if implausible.

    Starts from the condyle's sphere (sagittal semi-axes = its radius, the
    medio-lateral one 0.6 of it); refitted once on the points within 3 rms of
    the first fit.  Rejected when not converged, when a semi-axis leaves
    4-40 mm or when the centre moves more than half the sphere radius from
    the sphere centre.
    """
    from personalize.fitting import FittingError
    from personalize.fitting.ellipsoid import fit_ellipsoid_about_axis

    r = float(sphere.radius)
    c0 = np.asarray(sphere.centre, float)
    R0 = np.column_stack([ant, np.cross(axis, ant), axis])
    idx = sel
    f = None
    for _ in range(2):
        try:
            Rs, a0 = (R0, [r, r, 0.6 * r]) if f is None else _axis_last(f, axis)
            g = fit_ellipsoid_about_axis(V[idx], axis, centre0=c0 if f is None else f.centre,
                                         radii0=a0, rotation0=Rs, weights=A[idx])
        except FittingError:
            break
        f = g
        res_ = np.abs(f.residuals(V[sel]))
        nxt = sel[res_ < max(3.0 * float(f.rms), 5e-4)]
        if len(nxt) < 40:
            break
        idx = nxt
    if f is None:
        return None
    rr = np.asarray(f.radii)
    if not (np.all(np.isfinite(rr)) and rr.min() > 0.004 and rr.max() < 0.04):
        return None
    if np.linalg.norm(np.asarray(f.centre) - c0) > 0.5 * r:
        return None
    return f


def _axis_last(f, axis):
    """Rotation and semi-axes of fit ``f`` with the semi-axis along ``axis`` last."""
    k = int(np.argmax(np.abs(np.asarray(f.rotation).T @ axis)))
    order = [j for j in range(3) if j != k] + [k]
    return np.asarray(f.rotation)[:, order], np.asarray(f.radii)[order]


def _neck(surface, res, head, sp, sd, prox_region):
    """Neck axis and narrowest neck diameter from cross-sections.

    Planes perpendicular to the current axis guess cut the neck between one
    and 2.2 head radii from the head centre; the closed section loop around
    the axis gives a centroid and an area.  The axis is re-estimated as the
    line from the head centre through the section centroids (twice); the
    narrowest section's equivalent-circle diameter is the minimal neck diameter.
    """
    import trimesh

    c = np.asarray(head.centre, float)
    r = float(head.radius)
    # first guess: the neck is the only bone in the shell just outside the head
    dist = np.linalg.norm(surface.vertices - c, axis=1)
    shell = (dist > 1.15 * r) & (dist < 1.6 * r)
    if shell.sum() >= 10:
        d = unit((surface.areas[shell] @ surface.vertices[shell]) / surface.areas[shell].sum() - c)
    else:
        foot = sp + ((c - sp) @ sd) * sd
        d = unit(foot - c)
    mesh = trimesh.Trimesh(surface.vertices, surface.faces, process=False)
    best = None
    for it in range(3):
        cents, diams = [], []
        for t in np.linspace(0.9 * r, 2.2 * r, 14):
            area, cen3 = _section(mesh, c + t * d, d, c, 1.5 * r)
            if area is None:
                continue
            cents.append(cen3)
            diams.append((2.0 * np.sqrt(area / np.pi), t, cen3))
        if len(cents) < 3:
            break
        # keep the sections up to the narrowest one: beyond it the trochanters join
        k = int(np.argmin([q[0] for q in diams]))
        best = diams[k]
        use = np.array(cents[: max(k + 1, 3)])
        d_new = unit(np.mean([unit(q - c) for q in use], axis=0))
        if np.allclose(d_new, d, atol=1e-9):
            break
        d = d_new
    if best is None:
        res.flag(FLAG_LOW_CONFIDENCE, "femoral neck section not found")
        return
    diam, cen3, _ = best[0], best[2], best[1]
    var_c = np.trace(np.asarray(head.covariance)[:3, :3]) / 3.0
    sd_deg = float(np.degrees(np.sqrt(var_c + (0.05 * diam) ** 2) / max(np.linalg.norm(c - cen3), 1e-3)))
    res.axes["neck_axis"] = Axis(point=c.copy(), direction=-d, sd_deg=sd_deg)   # neck -> head
    res.scalars["neck_diameter_min"] = float(diam)


def _section(mesh, origin, normal, centre, max_radius):
    """Area and centroid of the closed section loop of ``mesh`` nearest to the line (centre, normal).

    The plane section (`trimesh.intersections.mesh_plane`) is split into
    loops by segment connectivity; the loop whose centroid lies closest to
    the line is fanned from its centroid (the neck section is star-shaped).
    """
    import trimesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    seg = trimesh.intersections.mesh_plane(mesh, plane_normal=normal, plane_origin=origin)
    if seg is None or len(seg) < 8:
        return None, None
    pts = seg.reshape(-1, 3)
    key = np.round(pts / 1e-7).astype(np.int64)   # 0.1 micrometre: shared edge points coincide
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1, 2)
    n = int(inv.max()) + 1
    g = coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    seg_lab = lab[inv[:, 0]]
    best = None
    for l in np.unique(seg_lab):
        sl = seg[seg_lab == l]
        if len(sl) < 6:
            continue
        lens = np.linalg.norm(sl[:, 1] - sl[:, 0], axis=1)
        cen = (lens @ sl.mean(axis=1)) / lens.sum()
        off = cen - centre
        dist = np.linalg.norm(off - (off @ normal) * normal)
        if dist < max_radius and (best is None or dist < best[0]):
            area = 0.5 * np.abs(np.cross(sl[:, 0] - cen, sl[:, 1] - cen) @ normal).sum()
            best = (dist, float(area), cen)
    if best is None:
        return None, None
    return best[1], best[2]
