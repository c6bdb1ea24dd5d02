"""The femur's knee end: condyle centres, the knee flexion axis and the epicondyles.

The posterior and distal condylar surfaces are split at the intercondylar
notch into a medial and a lateral condyle; each gives a sphere centre
(Hough vote, then `shape_fits.refine_sphere`) and an ellipsoid about the
flexion axis; a cylinder through the posterior condyles
(`posterior_condyle_cylinder`) is the knee axis, cross-checked against the
sphere centres and the epicondyles (`personalize.landmarks.crosscheck`).
Called by `femur.detect_femur` once the femur's orientation is known.
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError
from lowerlimb.geometry import orient, unit

from .common import FLAG_LOW_CONFIDENCE, Axis, Landmark
from .shape_fits import axis_sd_deg, isotropic_cov, line_through, perpendicular, sphere_centre_cov, sphere_fit_json
from .surface import Surface, extreme_vertex

__all__ = ["condyle_landmarks", "posterior_condyle_cylinder", "CONDYLE_RADII", "KNEE_MODEL_SD"]


#: radii (m) of the condyle spheres voted for
CONDYLE_RADII = np.arange(0.012, 0.0361, 0.0015)
#: condyle-centre fits use the posterior-distal arc up to 45 degrees anterior
#: of the distal direction (normal . anterior < cos 45): the centre of an oval
#: arc is ill-posed when the arc stops at the distal point, and the trochlea
#: begins farther forward (its stray points are down-weighted by the robust fit)
ANT_MAX = float(np.cos(np.radians(45.0)))


def condyle_landmarks(surface, res, cond_region, dist_region, med, ant, sd, P, noise):
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
            res.fits[f"{label}_condyle"] = sphere_fit_json(f, len(sels[label]))
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
    res.landmarks[f"{P}KNE"] = Landmark(V[k_lat].copy(), isotropic_cov(noise, 0.002))
    res.landmarks[f"{P}MFC"] = Landmark(V[k_med].copy(), isotropic_cov(noise, 0.002))


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
    add("epicondyles", on_line(0.5 * (epi_med + epi_lat), unit(epi_lat - epi_med)), isotropic_cov(noise, 0.002),
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
