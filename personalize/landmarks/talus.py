"""Talus: trochlear dome cylinder (talocrural axis) and the subtalar axis.

Articular surfaces are found from the bone's own shape, helped by its
neighbours when they are present (bones segmented from one scan sit in their
anatomical positions, so the talar dome is the part of the talus facing the
tibia and the posterior facet the part facing the calcaneus):

* dome: talus vertices whose normal points at the tibia within a gap of a few
  millimetres, taken with the talus turned about the ankle axis to its
  neutral pose (its own superior, away from the calcaneus, under the tibia's)
  so that the ankle angle of the foot in the scanner does not choose the part
  of the trochlea that is fitted; alone, the largest convex cylindrical patch
  found by Hough voting along the normals;
* talar head (talonavicular surface): the convex sphere-like end of the bone
  farthest in front of the dome along the long axis;
* posterior talocalcaneal facet: the concave inferior facet of the body
  (facing the calcaneus) behind the sinus tarsi.

The subtalar axis is the line through the centres of the spheres fitted to
the posterior facet (concave, its centre lies in the calcaneus) and to the
talar head, pointing anteriorly (after Parr et al. 2012, also used by STAPLE).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.errors import FitError
from lowerlimb.geometry import orient, unit

from .common import FLAG_LOW_CONFIDENCE, Axis, BoneLandmarks, Landmark
from .shape_fits import (axis_sd_deg, hough_centres, line_through, perpendicular, principal_axes, refine_cylinder,
                         refine_sphere, size_unit, sphere_centre_cov)
from .surface import Surface, facing, largest_patch

__all__ = ["detect_talus"]

DOME_RADII = np.arange(0.012, 0.0351, 0.0015)
HEAD_RADII = np.arange(0.008, 0.0301, 0.0015)
FACET_RADII = np.arange(0.012, 0.0501, 0.002)
#: distance of a posterior-facet inlier from the fitted sphere, m
FACET_INLIER = 0.0008
#: largest plausible posterior-facet radius, m (adults 14-25 mm); a flattened, noisy
#: facet drives the refit towards a plane, which must be rejected, not used
FACET_MAX_RADIUS = 0.04
#: m, the talar length (largest principal extent) below which the talus is taken as smaller than an adult's and
#: the subtalar search's lengths (head and facet radii, zones, Hough tolerances) shrink with it: a bit below the
#: shortest adult talus of the real sets (ICL-MRI 60, LHDL-CT 61, TLEM2-MRI 60 and 63, VAKHUM-CT 58, the tali
#: split from MC22's whole-foot meshes 54 mm)
ADULT_TALUS_LENGTH = 0.052
#: talar dome seed: talus points whose normal meets the tibia within this gap, m
DOME_CONTACT_GAP = 0.006
#: ... and whose normal is within acos(DOME_MIN_UP_COS) of superior (the trochlea,
#: not the malleolar facets)
DOME_MIN_UP_COS = 0.3
#: talar dome convention: "contact" (default: the talus facing the tibia, refined
#: on its own cylinder) or "staple" (talus-intrinsic trochlea selection as in STAPLE,
#: `personalize.landmarks.trochlea`, with DOME_STAPLE_OPTIONS).  The STAPLE
#: convention was measured (benchmarks/landmarks.py) and not adopted: on ICL-MRI its
#: axis is 0.74 deg from the hand-built model (STAPLE's own 0.42), +-20 % on its
#: settings moves it up to 0.9 mm / 0.9 deg, on TLEM2-MRI its radii are 14.5 /
#: 16.8 mm (right / left), and on the 0.5 x 0.5 x 2 mm phantoms its ankle errs by up
#: to 7 mm / 16 deg (1 mm phantoms: 0.3 mm / 0.6 deg).  STAPLE's superior direction
#: (an outline quadrilateral) fails on the phantom tali, so the tibia's superior axis
#: picks the quadrilateral's superior edge when known.
DOME_METHOD = "contact"
DOME_STAPLE_OPTIONS: dict = {}
#: dome contact taken with the talus turned about the ankle axis to its neutral pose
#: (its own superior, opposite the talocalcaneal contact, under the tibia's): the
#: selection then no longer depends on the ankle angle the foot had in the scanner
#: (on ICL-MRI, +-15 deg of scan ankle angle moved the scan-pose dome 2.7 mm / 2.6 deg)
DOME_NEUTRAL_POSE = True
#: neutral-pose re-selections (each refits the axis the next turn is made about)
DOME_NEUTRAL_ITERATIONS = 2
#: neutral-pose contact: talus points facing the tibia within the joint space (5th
#: percentile of those distances: cartilage, or none in a bone-and-cartilage segmentation)
#: plus this margin, m (None: the fixed DOME_CONTACT_GAP).  On TLEM2-MRI (joint space
#: 1.4 mm against ICL's 3.1) +-20 % on the fixed gap moved the ankle up to 4.9 mm, on
#: this margin 0.8 mm (benchmarks/landmarks.py)
DOME_CONTACT_MARGIN: float | None = 0.003
#: the contact-patch cylinder's axis turned by these angles (deg) about the superior direction seeds the dome
#: refinement, and the refit of least rms (among those keeping at least DOME_SEED_MIN_SHARE of the largest
#: selection) wins: the talar dome, a near-spherical cap on a small patch, has a second cylinder about
#: 80 deg from the flexion axis.  On LHDL-CT tali voxelised at 1.3 mm the patch fit landed there (rms 1.0 mm,
#: the true axis 0.2-0.3 mm, with more points), an ankle axis 23 deg off after the cross-check.
DOME_SEED_ANGLES = (0.0, -30.0, 30.0, -60.0, 60.0)
#: deg, the most the neutral-pose re-selection may turn the dome axis: it changes which points are the dome,
#: not the dome (0-4 deg on ICL-MRI, LHDL-CT, TLEM2-MRI's tali and MC22's right one); on MC22's left talus it
#: turned a 0.38 mm rms cylinder 84 deg onto a 1.05 mm one
DOME_NEUTRAL_MAX_TURN_DEG = 20.0
DOME_SEED_MIN_SHARE = 0.7


def _near(surface: Surface, other: Surface | None, gap: float) -> np.ndarray | None:
    """Vertices of `surface` whose outward normal ray meets `other` within `gap` (approx.)."""
    if other is None:
        return None
    d, _, ahead = facing(surface, other, gap)
    # nearly touching points count even when the vector is tiny
    return ahead | (d < 0.0005)


def detect_talus(surface: Surface, name: str = "talus_r", *, tibia: Surface | None = None,
                 calcaneus: Surface | None = None, right_hint: np.ndarray | None = None,
                 up_hint: np.ndarray | None = None) -> BoneLandmarks:
    """Detect the talar dome cylinder and the subtalar axis.

    Parameters
    ----------
    surface : Surface
    name : str
    tibia, calcaneus : Surface, optional
        Neighbouring bones in the same frame (articular cues).
    right_hint, up_hint : (3,) arrays, optional
        The subject's right and superior directions from the tibia's frame.
    """
    res = BoneLandmarks(bone=name, side=name[-1] if name[-2:] in ("_r", "_l") else None)
    V, Nrm, A = surface.vertices, surface.normals, surface.areas
    c, ax, sdv = principal_axes(V, A)

    # ---- dome ----------------------------------------------------------------------
    dome_mask = None
    near_tib = _near(surface, tibia, DOME_CONTACT_GAP)
    tibia_up = up_hint
    talus_up = None
    if calcaneus is not None:
        # the talus sits on the calcaneus: its own superior is away from the calcaneal contact
        nc = _near(surface, calcaneus, 0.006)
        if nc is not None and nc.sum() >= 20:
            talus_up = unit(-(A[nc] @ Nrm[nc]))
    if up_hint is None:
        up_hint = talus_up
    if near_tib is not None and up_hint is not None:
        near_tib &= Nrm @ up_hint > DOME_MIN_UP_COS
    if near_tib is not None and near_tib.sum() >= 30:
        patches = largest_patch(surface, near_tib, 1)
        dome_mask = patches[0] if patches else None
    if up_hint is None and dome_mask is not None:
        up_hint = unit((A[dome_mask] @ Nrm[dome_mask]))
    fit = None
    if DOME_METHOD == "staple":
        from .trochlea import staple_trochlea_cylinder
        try:
            tc = staple_trochlea_cylinder(surface, up_hint=up_hint, **DOME_STAPLE_OPTIONS)
            fit, p, u = tc, tc.point.copy(), tc.axis.copy()
            sel = np.zeros(len(V), bool)
            sel[surface.faces[tc.faces].ravel()] = True
            dome_mask = None
        except FitError as exc:
            res.flag(FLAG_LOW_CONFIDENCE, f"talar trochlea (STAPLE convention): {exc}")
    if dome_mask is not None and fit is None:
        try:
            from personalize.fitting import fit_cylinder
            hint = right_hint if right_hint is not None else ax[:, 1]
            try:
                f0 = fit_cylinder(V[dome_mask], normals=Nrm[dome_mask], axis_hint=hint)
            except FitError:
                # a slow robust fit on a noisy contact patch is still a usable start:
                # the refinement below re-selects the dome points and refits
                f0 = fit_cylinder(V[dome_mask], normals=Nrm[dome_mask], axis_hint=hint, require_convergence=False)
            try:
                fit, sel, p, u = _refine_dome(V, Nrm, f0, up_hint, _dome_zone(V, Nrm, f0, up_hint) & dome_mask)
            except FitError as exc:
                if not (0.5 * DOME_RADII[0] < f0.radius < 2 * DOME_RADII[-1]):
                    raise
                # keep the contact-patch fit (flagged) rather than lose the dome to a slow refit
                res.flag(FLAG_LOW_CONFIDENCE, f"talar dome refinement: {exc}; contact-patch cylinder kept")
                fit, sel, u = f0, dome_mask, unit(np.asarray(f0.axis, float))
                tt = (V[sel] - np.asarray(f0.point, float)) @ u
                p = np.asarray(f0.point, float) + 0.5 * (tt.min() + tt.max()) * u
        except FitError as exc:
            res.flag(FLAG_LOW_CONFIDENCE, f"talar dome cylinder (tibia contact): {exc}")
            fit = None
        if fit is not None and DOME_NEUTRAL_POSE:
            if talus_up is None or tibia_up is None:
                res.notes.append(f"{name}: talar dome taken at the scan's ankle angle (no "
                                 f"{'calcaneus' if talus_up is None else 'tibial frame'} for the neutral pose)")
            else:
                try:
                    fit, sel, p, u = _neutral_dome(surface, tibia, fit, p, u, talus_up, tibia_up)
                except FitError as exc:
                    res.notes.append(f"{name}: talar dome at the scan's ankle angle kept ({exc})")
    if fit is None:
        res.flag(FLAG_LOW_CONFIDENCE, "talar dome found without the tibia" if tibia is None else "talar dome from shape only")
        peaks = hough_centres(V, Nrm, DOME_RADII, inward=False, tol=0.0015, n_peaks=3, min_separation=0.01)
        for _, c0, r0 in peaks:
            mask = None if up_hint is None else (Nrm @ up_hint > 0.0)
            try:
                fit, sel, p, u = refine_cylinder(V, Nrm, c0, ax[:, 1] if right_hint is None else right_hint, r0,
                                                 band=max(0.0015, 0.08 * r0), min_cos=0.6, mask=mask)
                break
            except FitError:
                fit = None
    if fit is None:
        res.flag(FLAG_LOW_CONFIDENCE, "talar dome not found")
        return res
    if up_hint is None:
        up_hint = unit(A[sel] @ Nrm[sel])
    if right_hint is not None:
        u = orient(u, right_hint)
    cov = np.asarray(fit.covariance)[:3, :3] + 1e-12 * np.eye(3)
    # mid-dome along the axis: centre of the selected points' extent
    res.landmarks["talar_dome_centre"] = Landmark(p.copy(), cov)
    res.scalars["talar_dome_radius"] = float(fit.radius)
    res.scalar_sd["talar_dome_radius"] = float(np.sqrt(max(np.asarray(fit.covariance)[-1, -1], 0.0)))
    res.axes["ankle_axis"] = Axis(point=p.copy(), direction=u, sd_deg=axis_sd_deg(fit))
    res.fits["talar_dome"] = {"type": "cylinder", "point": p.tolist(), "axis": u.tolist(), "radius": float(fit.radius),
                              "rms": float(fit.rms), "n_points": int(sel.sum()), "converged": bool(fit.converged)}

    # ---- anterior: the talar head projects farther in front of the dome than the
    # posterior process behind it, along the long axis orthogonal to the dome axis
    up = unit(perpendicular(up_hint, u))
    fwd = np.cross(up, u)                        # anterior if u points right
    q = (V - p) @ fwd
    if -q.min() > q.max():
        fwd = -fwd
        if right_hint is None:
            u = -u                               # keep (fwd, up, u) right-handed: u to the right
            res.axes["ankle_axis"] = Axis(point=p.copy(), direction=u, sd_deg=res.axes["ankle_axis"].sd_deg)
    # With the foot plantarflexed in the scanner the head, which points
    # antero-inferiorly, projects little farther along `fwd` than the
    # posterior process: the extents alone are then ambiguous, and the
    # direction is confirmed by a talar head sphere found at the anterior end.
    ambiguous = right_hint is not None and -q.min() <= q.max() < 1.2 * -q.min()
    ant = fwd
    res.frames["anatomical"] = {"origin": p.copy(), "rotation": np.column_stack([ant, up, np.cross(ant, up)])}

    # ---- subtalar axis --------------------------------------------------------------------
    size = size_unit(V, ax[:, 0], ADULT_TALUS_LENGTH, res, "long (subtalar joint)")
    _subtalar(surface, res, p, float(fit.radius), ant, up, calcaneus, size)
    if ambiguous and "talar_head_centre" not in res.landmarks:
        res.flag(FLAG_LOW_CONFIDENCE, "talar head not clearly anterior")
    return res


@dataclass(frozen=True)
class NormalLineSphere:
    """Sphere from the common point of surface normals (centre (3,), m; radius, rms m; cov (3, 3) m^2)."""

    centre: np.ndarray
    radius: float
    rms: float
    cov: np.ndarray
    n_points: int


def _normal_line_sphere(P: np.ndarray, N: np.ndarray, w: np.ndarray) -> NormalLineSphere:
    r"""Centre of a sphere as the weighted least-squares meeting point of its normal lines.

    Model: every surface point :math:`p_i` with unit normal :math:`n_i` lies on a
    sphere, so the line :math:`p_i + t n_i` passes through the centre :math:`c`.
    Minimised: :math:`\sum_i w_i \lVert (I - n_i n_i^T)(p_i - c) \rVert^2`
    (squared distances from c to the normal lines; w_i = vertex areas), solved
    in closed form :math:`Q c = \sum_i w_i (I - n_i n_i^T) p_i`,
    :math:`Q = \sum_i w_i (I - n_i n_i^T)`.  Radius: weighted mean of
    :math:`\lVert p_i - c \rVert`; rms: of the radial residuals.  Covariance:
    sandwich estimate :math:`Q^{-1} (\sigma^2 \sum_i w_i^2 (I - n_i n_i^T)) Q^{-1}`
    with :math:`\sigma^2` the mean squared line distance per constrained direction.

    P, N : (n, 3) points (m) and unit normals; w : (n,) weights.
    """
    Pr = np.eye(3)[None] - np.einsum("ij,ik->ijk", N, N)          # projectors orthogonal to each normal
    Q = np.einsum("i,ijk->jk", w, Pr)
    b = np.einsum("i,ijk,ik->j", w, Pr, P)
    c = np.linalg.solve(Q, b)
    e = np.einsum("ijk,ik->ij", Pr, P - c)
    s2 = float(np.sum(w * np.einsum("ij,ij->i", e, e)) / (2.0 * w.sum()))
    Qi = np.linalg.inv(Q)
    cov = Qi @ (s2 * np.einsum("i,ijk->jk", w * w, Pr)) @ Qi
    d = np.linalg.norm(P - c, axis=1)
    r = float(np.average(d, weights=w))
    rms = float(np.sqrt(np.average((d - r) ** 2, weights=w)))
    return NormalLineSphere(c, r, rms, 0.5 * (cov + cov.T) + 1e-14 * np.eye(3), len(P))


def _neutral_dome(surface: Surface, tibia: Surface, fit, p, u, talus_up, tibia_up):
    """Talar dome re-selected with the talus in its neutral pose against the tibia.

    The talus is turned about the current dome axis :math:`(p, u)` by the
    angle that brings its own superior direction (``talus_up``, projected on
    the plane normal to :math:`u`) onto the tibia's (``tibia_up``); the dome
    is the part of the turned talus facing the tibia within the joint space
    plus ``DOME_CONTACT_MARGIN``, fitted on the talus as it lies in the scan.  The
    selection is then a property of the two bones' shapes, not of the
    ankle angle at which the foot lay in the scanner.

    Returns
    -------
    fit, sel, p, u : as ``refine_cylinder`` (scan frame)

    Raises
    ------
    FitError
        If the turned talus does not meet the tibia or the dome does not refit.
    """
    from scipy.spatial.transform import Rotation

    from personalize.fitting import fit_cylinder

    V, Nrm = surface.vertices, surface.normals
    for _ in range(DOME_NEUTRAL_ITERATIONS):
        a, b = perpendicular(talus_up, u), perpendicular(tibia_up, u)
        if np.linalg.norm(a) < 0.3 or np.linalg.norm(b) < 0.3:
            raise FitError("the talus' or the tibia's superior direction lies along the ankle axis")
        a, b = unit(a), unit(b)
        rot = Rotation.from_rotvec(np.arctan2(np.cross(a, b) @ u, a @ b) * u)
        turned = Surface(rot.apply(V - p) + p, surface.faces, rot.apply(Nrm), surface.areas, surface.closed)
        d, _, ahead = facing(turned, tibia, max(0.015, DOME_CONTACT_GAP))
        up_facing = turned.normals @ tibia_up > DOME_MIN_UP_COS
        gap = DOME_CONTACT_GAP
        if DOME_CONTACT_MARGIN is not None and (up_facing & ahead).sum() >= 30:
            gap = float(np.percentile(d[up_facing & ahead], 5)) + DOME_CONTACT_MARGIN
        # as `_near` with this gap
        near = ((ahead & (d < gap)) | (d < 0.0005)) & up_facing
        patches = largest_patch(surface, near, 1) if near.sum() >= 30 else []
        if not patches or patches[0].sum() < 30:
            raise FitError("the talus turned to its neutral pose does not meet the tibia")
        mask = patches[0]
        f0 = fit_cylinder(V[mask], normals=Nrm[mask], axis_hint=u, require_convergence=False)
        u_in = u
        fit, sel, p, u = refine_cylinder(V, Nrm, f0.point, orient(unit(np.asarray(f0.axis, float)), u), f0.radius,
                                         band=max(0.0015, 0.08 * f0.radius), min_cos=0.6,
                                         mask=_dome_zone(V, Nrm, f0, talus_up) & mask)
        turn = float(np.degrees(np.arccos(np.clip(abs(u @ u_in), -1.0, 1.0))))
        if turn > DOME_NEUTRAL_MAX_TURN_DEG:
            raise FitError(f"the neutral-pose dome turned the axis {turn:.0f} deg")
    return fit, sel, p, u


def _refine_dome(V, Nrm, f0, up_hint, mask):
    """Dome cylinder refined from the contact-patch fit `f0` turned by each of `DOME_SEED_ANGLES` about
    `up_hint`: (fit, selection, point, axis) of least rms among the refits keeping at least
    `DOME_SEED_MIN_SHARE` of the largest selection.  Raises FitError when no seed refits."""
    from scipy.spatial.transform import Rotation

    u0 = unit(np.asarray(f0.axis, float))
    up = None if up_hint is None else unit(perpendicular(np.asarray(up_hint, float), u0))
    out, last = [], None
    for ang in (DOME_SEED_ANGLES if up is not None else (0.0,)):
        seed = u0 if ang == 0.0 else Rotation.from_rotvec(np.radians(ang) * up).apply(u0)
        try:
            out.append(refine_cylinder(V, Nrm, f0.point, seed, f0.radius, band=max(0.0015, 0.08 * f0.radius),
                                       min_cos=0.6, mask=mask))
        except FitError as exc:
            last = exc
    if not out:
        raise last
    n_max = max(int(o[1].sum()) for o in out)
    return min((o for o in out if o[1].sum() >= DOME_SEED_MIN_SHARE * n_max), key=lambda o: float(o[0].rms))


def _dome_zone(V, Nrm, f0, up_hint):
    d = V - f0.point
    radial = d - np.outer(d @ f0.axis, f0.axis)
    m = np.linalg.norm(radial, axis=1) < 2.0 * f0.radius
    if up_hint is not None:
        m &= Nrm @ up_hint > -0.2
    return m


def _subtalar(surface, res, dome_p, dome_r, ant, up, calcaneus, u: float = 1.0):
    """Talar head and posterior facet spheres, the subtalar axis through them; lengths in units of `u` x adult."""
    V, Nrm = surface.vertices, surface.normals
    q = (V - dome_p) @ ant
    # talar head: anterior block, normals pointing forward
    head_zone = (q > q.max() - 0.025 * u) & (Nrm @ ant > 0.2)
    head = None
    if head_zone.sum() >= 20:
        peaks = hough_centres(V[head_zone], Nrm[head_zone], u * HEAD_RADII, inward=False, tol=0.0015 * u)
        if peaks:
            _, c0, r0 = peaks[0]
            try:
                # narrow band, near-radial normals: the neck's blend must not flatten the head
                head, hsel = refine_sphere(V, Nrm, c0, r0, band=max(0.001, 0.05 * r0), min_cos=0.8,
                                           mask=q > q.max() - 0.035 * u, iterations=6)
            except FitError as exc:
                res.flag(FLAG_LOW_CONFIDENCE, f"talar head sphere: {exc}")
    # posterior calcaneal facet: inferior, behind the dome centre
    facet_zone = (Nrm @ (-up) > 0.3) & (q < 0.01 * u)
    near_cal = _near(surface, calcaneus, 0.006)
    if near_cal is not None and (near_cal & facet_zone).sum() >= 20:
        facet_zone &= near_cal
    facet = _facet_sphere(surface, facet_zone, up, concave=True, u=u) if facet_zone.sum() >= 20 else None
    if facet is None:
        res.flag(FLAG_LOW_CONFIDENCE, "posterior talocalcaneal facet not found")
    if head is None or facet is None:
        res.flag(FLAG_LOW_CONFIDENCE, "subtalar axis not found")
        return
    if (facet.centre - dome_p) @ ant > 0:
        # the posterior facet's centre lies 12-24 mm behind the dome centre on ICL-MRI, LHDL-CT and MC22; on both
        # TLEM2-MRI tali a small concave patch in front of it (8-10 mm radius, between the middle facet and the
        # sinus tarsi) wins and the axis comes out nearly vertical
        res.notes.append(f"{res.bone}: posterior talocalcaneal facet found in front of the talar dome centre; "
                         "check the subtalar axis")
    hl = Landmark(np.asarray(head.centre, float), sphere_centre_cov(head))
    fl = Landmark(facet.centre.copy(), facet.cov)
    res.landmarks["talar_head_centre"] = hl
    res.landmarks["posterior_facet_centre"] = fl
    ax = line_through(fl, hl)
    d = orient(ax.direction, ant)
    # the subtalar axis point closest to the dome centre (joint origin)
    o = fl.position + ((dome_p - fl.position) @ d) * d
    res.axes["subtalar_axis"] = Axis(point=o, direction=d, sd_deg=ax.sd_deg)
    # the same joint seen from the calcaneus: its convex posterior talar facet (a check of the talar one)
    if calcaneus is not None:
        cq = (calcaneus.vertices - dome_p) @ ant
        czone = (calcaneus.normals @ up > 0.3) & (cq < 0.01 * u)
        near_tal = _near(calcaneus, surface, 0.006)
        if near_tal is not None:
            czone &= near_tal
        cf = _facet_sphere(calcaneus, czone, up, concave=False, u=u) if czone.sum() >= 20 else None
        if cf is not None:
            res.landmarks["calcaneal_facet_centre"] = Landmark(cf.centre.copy(), cf.cov)
            res.fits["calcaneal_posterior_facet"] = {"type": "sphere", "centre": cf.centre.tolist(),
                                                     "radius": float(cf.radius), "rms": float(cf.rms),
                                                     "n_points": int(cf.n_points), "method": "normal lines",
                                                     "surface": "calcaneus"}
    res.fits["talar_head"] = {"type": "sphere", "centre": hl.position.tolist(), "radius": float(head.radius),
                              "rms": float(head.rms), "converged": bool(head.converged)}
    res.fits["posterior_calcaneal_facet"] = {"type": "sphere", "centre": fl.position.tolist(),
                                             "radius": float(facet.radius), "rms": float(facet.rms),
                                             "n_points": int(facet.n_points), "method": "normal lines"}


def _facet_sphere(surface, zone, up, concave: bool, u: float = 1.0):
    """Sphere of a posterior talocalcaneal facet (concave on the talus, convex on the calcaneus), or None.

    Hough votes along the normals in `zone`, every peak refined with a narrow
    band and normals close to radial (a wide band lets the facet's rim and the
    surrounding underside drag the sphere to a larger radius), then its centre
    taken as the normals' common point (`_normal_line_sphere`: on a shallow,
    noisy cap the distance fit trades radius for centre height).  Kept: centre
    on the bone's side of the facet (below the talar facet, inside the
    calcaneus under the calcaneal one), radius 8 mm to `FACET_MAX_RADIUS`, rms
    under 1.2 mm; the one with the largest inlier area (points within
    `FACET_INLIER`) wins, so a fixed tolerance does not favour large radii.
    """
    V, Nrm, A = surface.vertices, surface.normals, surface.areas
    peaks = hough_centres(V[zone], Nrm[zone], u * FACET_RADII, inward=concave, tol=0.002 * u, n_peaks=4,
                          min_separation=0.008 * u)
    best = None
    for _, c0, r0 in peaks:
        try:
            _, fsel = refine_sphere(V, Nrm, c0, r0, band=max(0.001, 0.03 * r0), convex=not concave,
                                    min_cos=0.85, mask=zone, iterations=6)
        except FitError:
            continue
        f = _normal_line_sphere(V[fsel], Nrm[fsel], A[fsel])
        below = (f.centre - (A[fsel] @ V[fsel]) / A[fsel].sum()) @ up < 0
        if not (below and 0.008 * u < f.radius < FACET_MAX_RADIUS * u):
            continue
        inl = zone & (np.abs(np.linalg.norm(V - f.centre, axis=1) - f.radius) < FACET_INLIER)
        score = (float(A[inl].sum()) if f.rms < 0.0012 else 0.0, -f.rms)
        if best is None or score > best[0]:
            best = (score, f)
    if best is None:
        return None
    # refitted once on the chosen sphere's own inliers: the refinement band's selection is not the scored one
    f = best[1]
    inl = zone & (np.abs(np.linalg.norm(V - f.centre, axis=1) - f.radius) < FACET_INLIER)
    if inl.sum() >= 20:
        g = _normal_line_sphere(V[inl], Nrm[inl], A[inl])
        f = g if 0.008 * u < g.radius < FACET_MAX_RADIUS * u else f
    return f
