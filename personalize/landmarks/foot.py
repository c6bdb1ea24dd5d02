"""Calcaneus + forefoot (``calcn``) and toes: plantar support plane, ground contacts, foot axes.

The plantar support plane is the plane tangent from below to the heel tuber
and the first and fifth metatarsal heads: a face of the bone's convex hull.
It is found by alternating "lowest point of the heel / first / fifth
metatarsal region along the current down direction" and "plane through the
three", which converges to that hull face in a few steps.  Each contact point
is then refined on a sphere fitted to the surface around it (heel tuber,
metatarsal head): the contact is the sphere's pole along the plane normal, so
it does not depend on where the mesh vertices happen to lie.

Superior comes from the talus / tibia when present (the talus sits on top of
the calcaneus); alone, from the side of the convex hull opposite the largest
hull face (the plantar triangle is the largest flat face of a foot).
Anterior = from the heel to the metatarsal heads (long principal axis,
oriented away from the calcaneal end, which is bulkier and higher).
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError
from lowerlimb.geometry import unit
from lowerlimb.bones import side_of

from .common import FLAG_LOW_CONFIDENCE, Axis, BoneLandmarks, Landmark
from .shape_fits import (isotropic_cov, perpendicular, principal_axes, refine_sphere, size_unit, sphere_centre_cov,
                         sphere_fit_json)
from .surface import Surface, extreme_vertex, facing, largest_patch, vertex_components

__all__ = ["detect_calcn", "detect_toes"]


def _largest_hull_face_normal(V: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    hull = ConvexHull(V)
    T = V[hull.simplices]
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    a = np.linalg.norm(n, axis=1)
    k = int(np.argmax(a))
    nk = n[k] / a[k]
    # outward: away from the centroid
    return nk if (T[k, 0] - V.mean(axis=0)) @ nk > 0 else -nk


#: position of the second ray across the forefoot, as a fraction of the D1M-D5M width from the medial border
#: (first metatarsal head about 25 mm of a 90 mm forefoot; an anatomical assumption, not fitted)
TOE_RAY_FRACTION = 0.3
#: m, half-width of the band about the second ray, and the length behind its tip taken as the head
TOE_BAND_HALF_WIDTH = 0.006
TOE_HEAD_LENGTH = 0.015
#: m, how far ahead of D1M (the first head's medial side) the second head's tip may lie; beyond it lie the toes
#: (tip 12-16 mm ahead on ICL-MRI, LHDL-CT and both TLEM2-MRI feet; the band's front 29-41 mm ahead on MC22's
#: feet, which keep their toes)
TOE_MAX_AHEAD_OF_D1M = 0.02
#: m, the length (largest principal extent) of a calcaneus with its mid- and forefoot below which the foot is
#: taken as smaller than an adult's and the lengths above and of the contact spheres shrink with it: a bit below
#: the shortest adult one of the real sets (ICL-MRI 199, LHDL-CT 178, TLEM2-MRI 175 and 176 mm, the calcanei split
#: from MC22's whole-foot meshes 168 mm and more)
ADULT_FOOT_LENGTH = 0.165


#: m, largest distance between a toes component and the forefoot for it to be a proximal phalanx (the
#: metatarsophalangeal joint spaces: 0.3-5.2 mm on LHDL-CT, both TLEM2-MRI and both MC22 feet; the middle
#: phalanges lie 10 mm and more from the forefoot)
PHALANX_MAX_GAP = 0.008
#: m, how much further than the phalanges' (median) closest approach a forefoot vertex may lie from the toes to be
#: on a metatarsal head's articular surface
MT_HEAD_BAND = 0.003
#: largest fraction of the calcaneus-with-forefoot surface within `PHALANX_MAX_GAP` / 2 of the toes: beyond it
#: the two meshes overlap and no articular surface can be told (ICL-MRI's toes mesh holds its metatarsals too:
#: 71 % of its forefoot lies within 4 mm of it; LHDL-CT 2.6 %, TLEM2-MRI 2.0-2.3 %)
MTP_MAX_INTERFACE_FRACTION = 0.15
#: m, radii admitted for a metatarsal head's articular sphere (times the foot's size unit; 4.8-13.1 mm on LHDL-CT
#: and both TLEM2-MRI feet, the first head the largest), and the largest rms over the radius
MT_HEAD_RADIUS = (0.004, 0.018)
MT_HEAD_MAX_RMS = 0.25
#: least cosine between a forefoot vertex's normal and the direction to its nearest toes point on a head's
#: articular surface
MT_HEAD_MIN_FACING = 0.5
#: added sd of an mtp found from the plantar contact spheres of the first and fifth heads rather than their
#: articular surfaces: centre as a fraction of those spheres' radius, axis in degrees (see `_articular_mtp`)
PLANTAR_MTP_SD = (1.0, 6.0)
#: the calcaneus' note, and the toes' low-confidence flag, when the mtp comes from the plantar spheres
PLANTAR_MTP_NOTE = "mtp from the plantar metatarsal head spheres"


def metatarsal_heads(surface: Surface, toes: Surface, med: np.ndarray, u: float = 1.0) -> tuple[list, str | None]:
    """Spheres of the metatarsal heads' articular surfaces, medial to lateral, or ``([], why)``.

    A head's articular surface is the part of the forefoot facing its proximal phalanx: the forefoot vertices
    within a gap of the toes whose normal points to the nearest toes point (cosine above
    `MT_HEAD_MIN_FACING`), split into edge-connected patches, the five largest kept.  The gap is the joint
    space plus `MT_HEAD_BAND`: the median closest approach of the proximal phalanges (the toes mesh's
    connected components within `PHALANX_MAX_GAP` of the forefoot; 1.0 mm on LHDL-CT, 3.3 mm on MC22's right
    foot), or ``PHALANX_MAX_GAP / 2`` when the toes mesh has fewer than three (phalanges fused by the
    segmentation).  Each patch gets a sphere (`personalize.fitting.fit_sphere`, points and normals), kept when
    its radius lies in `MT_HEAD_RADIUS` (times `u`) and its rms below `MT_HEAD_MAX_RMS` of it.  Returns
    ``[(fit, n_points), ...]`` sorted along `med` (medial first) and None, or fewer than three heads and why.
    """
    from personalize.fitting import fit_sphere

    d, k, ahead = facing(surface, toes, PHALANX_MAX_GAP + MT_HEAD_BAND, MT_HEAD_MIN_FACING)
    near = np.isfinite(d)
    frac = float(surface.areas[near & (d < 0.5 * PHALANX_MAX_GAP)].sum() / surface.areas.sum())
    if frac > MTP_MAX_INTERFACE_FRACTION:
        return [], (f"the toes mesh overlaps the forefoot ({100 * frac:.0f} % of it within "
                    f"{0.5e3 * PHALANX_MAX_GAP:.0f} mm): no metatarsal head articular surface told apart")
    # an articular surface faces its partner
    near &= ahead
    _, lab = vertex_components(toes.faces, len(toes.vertices))
    comp = np.full(len(d), -1)
    comp[near] = lab[k[near]]
    closest = sorted(float(d[comp == c].min()) for c in np.unique(comp[near]))
    closest = [x for x in closest if x < PHALANX_MAX_GAP][:5]
    gap = MT_HEAD_BAND + (float(np.median(closest)) if len(closest) >= 3 else 0.5 * PHALANX_MAX_GAP - MT_HEAD_BAND)
    surfaces = largest_patch(surface, near & (d < gap), n=5)
    heads = []
    for sel in surfaces:
        n = int(sel.sum())
        if n < 10:
            continue
        try:
            f = fit_sphere(surface.vertices[sel], normals=surface.normals[sel])
        except FitError:
            continue
        if MT_HEAD_RADIUS[0] * u < f.radius < MT_HEAD_RADIUS[1] * u and f.rms < MT_HEAD_MAX_RMS * f.radius:
            heads.append((f, n))
    heads.sort(key=lambda h: -float(np.asarray(h[0].centre) @ med))
    return heads, (None if len(heads) >= 3 else f"{len(heads)} metatarsal head articular surface(s) found against "
                   "the toes (3 needed)")


def _mtp_from_heads(heads, side: str) -> tuple[Axis, Landmark, np.ndarray]:
    r"""The mtp axis and centre from the metatarsal heads' sphere centres :math:`c_i`.

    The axis is the least-squares line through the centres (the first principal direction :math:`a` of the
    :math:`c_i - \bar c`, pointing right), the centre their mean :math:`\bar c`.  The heads lie on an arc
    (the second head furthest forward), so no single hinge passes through all and where the joint centre lies
    is a convention: the centre's spread returned is isotropic, :math:`(\sum_i |r_i|^2 / 2n) I`, with
    :math:`r_i` the centres' offsets perpendicular to the line (on LHDL-CT the expert's mtp lies 6.5 mm from
    the centroid, 4.7 mm off the line).
    The axis sd propagates the centres' fit covariances: :math:`\sqrt{\bar\sigma^2 / \sum_i t_i^2}` rad,
    :math:`t_i` the centres' positions along the line and :math:`\bar\sigma^2` their mean per-component variance.
    """
    C = np.array([np.asarray(f.centre, float) for f, _ in heads])
    covs = [sphere_centre_cov(f) for f, _ in heads]
    c = C.mean(axis=0)
    D = C - c
    a = np.linalg.svd(D, full_matrices=False)[2][0]
    # the medial-most head first: right is medial -> lateral on a right foot, lateral -> medial on a left one
    a = a if (D[-1] - D[0]) @ a > 0 else -a
    a = a if side == "r" else -a
    t = D @ a
    R = D - np.outer(t, a)
    var = float(np.mean([np.trace(k) for k in covs]) / 3.0)
    sd = float(np.degrees(np.sqrt(var / max(float(t @ t), 1e-12))))
    centre = Landmark(c, sum(covs) / len(covs) ** 2)
    return Axis(point=c.copy(), direction=a, sd_deg=sd), centre, float(np.sum(R * R) / (2 * len(C))) * np.eye(3)


def _articular_mtp(res: BoneLandmarks, surface: Surface, toes: Surface | None, med, u: float, side: str,
                   width: float) -> None:
    """The mtp axis and centre from the metatarsal heads' articular spheres (`_mtp_from_heads`) when at least
    three heads spanning half the forefoot's width (`width`, D1M to D5M) are found; else the plantar contact
    spheres' line stays, its uncertainty widened by `PLANTAR_MTP_SD` and flagged."""
    heads, why = metatarsal_heads(surface, toes, med, u) if toes is not None else ([], "no toes surface")
    if heads and why is None:
        span = float((np.asarray(heads[0][0].centre) - np.asarray(heads[-1][0].centre)) @ med)
        if span < 0.5 * width:
            why = (f"the metatarsal head articular surfaces found span {1e3 * span:.0f} mm of the forefoot's "
                   f"{1e3 * width:.0f} mm")
    if why is None:
        axis, centre, spread = _mtp_from_heads(heads, side)
        res.axes["mtp_axis"] = axis
        res.landmarks["mtp_centre"] = Landmark(centre.position, centre.cov + spread)
        for i, (f, n) in enumerate(heads):
            res.fits[f"metatarsal_head_{i + 1}_sphere"] = sphere_fit_json(f, n)
        return
    if "mtp_axis" not in res.axes:
        return
    k_c, k_a = PLANTAR_MTP_SD
    r = np.mean([res.fits[f"{m}_sphere"]["radius"] for m in ("met1", "met5")])
    c = res.landmarks["mtp_centre"]
    res.landmarks["mtp_centre"] = Landmark(c.position, c.cov + isotropic_cov(k_c * r))
    ax = res.axes["mtp_axis"]
    res.axes["mtp_axis"] = Axis(ax.point, ax.direction, float(np.hypot(ax.sd_deg, k_a)))
    if toes is not None:
        # a note here, the flag on the toes: the calcaneus' other joint (subtalar) is not in doubt
        res.notes.append(f"{PLANTAR_MTP_NOTE} ({why})")


def plantar_mtp_reason(calcn: BoneLandmarks) -> str | None:
    """The calcaneus' note saying its mtp comes from the plantar head spheres (and why), or None."""
    return next((n for n in calcn.notes if n.startswith(PLANTAR_MTP_NOTE)), None)


def _second_ray_dorsum(V, X, up, med, d1m, d5m, fore, u: float = 1.0) -> np.ndarray | None:
    """Plug-in-Gait's TOE site: the most dorsal point over the second metatarsal head (scanner, m), or None.

    The second ray is the band at `TOE_RAY_FRACTION` of the way from D1M to D5M across the foot; its most
    anterior vertex, at most `TOE_MAX_AHEAD_OF_D1M` ahead of D1M, is the head's tip, and the head the
    `TOE_HEAD_LENGTH` behind it (lengths times `u`, the foot's size relative to an adult's).
    """
    w = V @ med
    w2 = float(d1m @ med + TOE_RAY_FRACTION * ((d5m - d1m) @ med))
    band = fore & (np.abs(w - w2) < TOE_BAND_HALF_WIDTH * u)
    if np.count_nonzero(band) < 10:
        return None
    x = V @ X
    # a foot label with its toes: the band's front is the second toe, not the metatarsal head
    band &= x < float(d1m @ X) + TOE_MAX_AHEAD_OF_D1M * u
    if np.count_nonzero(band) < 10:
        return None
    tip = float(x[band].max())
    head = band & (x > tip - TOE_HEAD_LENGTH * u)
    k = np.flatnonzero(head)[np.argmax(V[head] @ up)]
    return V[k].copy()


def detect_calcn(surface: Surface, name: str = "calcn_r", *, up_hint=None, right_hint=None,
                 talus: Surface | None = None, toes: Surface | None = None) -> BoneLandmarks:
    """Detect heel / metatarsal landmarks, ground contacts, foot axes and the foot frame.

    Parameters
    ----------
    surface : Surface
        Calcaneus with the mid- and fore-foot bones (STAPLE's ``calcn``).
    up_hint, right_hint : (3,) arrays, optional
        Superior and rightward directions from the leg (tibia / talus frames).
    talus : Surface, optional
        Used for the superior direction when `up_hint` is not given.
    toes : Surface, optional
        The phalanges: the metatarsal heads' articular surfaces face them (`metatarsal_heads`).
    """
    res = BoneLandmarks(bone=name, side=side_of(name))
    V, Nrm, A = surface.vertices, surface.normals, surface.areas
    c, ax, sdv = principal_axes(V, A)
    long_ax = ax[:, 0]
    if up_hint is None and talus is not None:
        up_hint = unit(perpendicular((talus.areas @ talus.vertices) / talus.areas.sum() - c, long_ax))
    if up_hint is None:
        down = _largest_hull_face_normal(V)
        up = -down
        res.flag(FLAG_LOW_CONFIDENCE, "superior direction of the foot from its own hull only")
    else:
        up = unit(np.asarray(up_hint, float))
    # anterior: towards the metatarsal heads; the calcaneal end carries more bone higher up
    fwd = unit(perpendicular(long_ax, up))
    q = (V - c) @ fwd
    L = float(q.max() - q.min())
    u = size_unit(V, long_ax, ADULT_FOOT_LENGTH, res, "long")
    back = q < q.min() + 0.25 * L
    front = q > q.max() - 0.25 * L
    if talus is not None:
        # the talus sits over the hind foot (its centroid at 25-30 % of the foot's length from the heel on
        # ICL-MRI, LHDL-CT and both TLEM2-MRI feet); the height rule below took ICL-MRI's toes for its heel
        qt = float(((talus.areas @ talus.vertices) / talus.areas.sum() - c) @ fwd)
        flip = qt > 0.5 * (q.min() + q.max())
    else:
        hb = float((A[back] @ ((V[back] - c) @ up)) / A[back].sum())
        hf = float((A[front] @ ((V[front] - c) @ up)) / A[front].sum())
        flip = hf > hb
    if flip:
        fwd = -fwd
        q = -q
        back, front = front, back
    if right_hint is not None:
        right = unit(perpendicular(np.asarray(right_hint, float), up))
        fwd = unit(perpendicular(fwd, right))
        # keep the frame consistent: X = Y x Z must be forward
        if np.cross(up, right) @ fwd < 0:
            res.flag(FLAG_LOW_CONFIDENCE, "foot forward direction disagrees with the leg")
    right = unit(np.cross(fwd, up))
    side = res.side or "r"
    med = -right if side == "r" else right
    P = "R" if side == "r" else "L"
    # ---- support plane iteration ----------------------------------------------------------
    w = (V - c) @ med
    L = float(q.max() - q.min())
    heel_zone = q < q.min() + 0.3 * L
    fore = q > q.max() - 0.3 * L
    m1_zone = fore & (w > np.median(w[fore]))
    m5_zone = fore & (w <= np.median(w[fore]))
    n = -up
    for _ in range(8):
        h = V @ n
        kh = np.flatnonzero(heel_zone)[np.argmax(h[heel_zone])]
        k1 = np.flatnonzero(m1_zone)[np.argmax(h[m1_zone])]
        k5 = np.flatnonzero(m5_zone)[np.argmax(h[m5_zone])]
        nn = unit(np.cross(V[k1] - V[kh], V[k5] - V[kh]))
        nn = nn if nn @ n > 0 else -nn
        if np.allclose(nn, n, atol=1e-12):
            break
        n = nn
    down = n
    up = -down
    # ---- contacts refined on local spheres ---------------------------------------------------
    contacts = {}
    for lab, k, rad in (("heel", kh, 0.012 * u), ("met1", k1, 0.008 * u), ("met5", k5, 0.008 * u)):
        near = np.linalg.norm(V - V[k], axis=1) < rad
        pt, cov = V[k].copy(), isotropic_cov(0.001)
        try:
            from personalize.fitting import fit_sphere
            f0 = fit_sphere(V[near], normals=Nrm[near])
            f, sel = refine_sphere(V, Nrm, f0.centre, f0.radius, band=max(0.0008 * u, 0.08 * f0.radius),
                                   min_cos=0.5, mask=np.linalg.norm(V - V[k], axis=1) < 1.6 * rad)
            if 0.003 * u < f.radius < 0.04 * u:
                pt = np.asarray(f.centre) + f.radius * down
                cov = sphere_centre_cov(f) + float(np.asarray(f.covariance)[3, 3]) * np.outer(down, down)
                res.fits[f"{lab}_sphere"] = {"type": "sphere", "centre": np.asarray(f.centre).tolist(),
                                             "radius": float(f.radius), "rms": float(f.rms)}
                contacts[lab] = (pt, f)
        except FitError:
            pass
        if lab not in contacts:
            contacts[lab] = (pt, None)
        res.landmarks[f"{lab}_contact"] = Landmark(pt, cov)
    # the contacts' own plane (after refinement) is the support plane
    hc, m1c, m5c = (res.landmarks[f"{k}_contact"].position for k in ("heel", "met1", "met5"))
    nrm = unit(np.cross(m1c - hc, m5c - hc))
    up = nrm if nrm @ up > 0 else -nrm
    # ---- marker-named landmarks ---------------------------------------------------------------
    mc = 0.5 * (m1c + m5c)
    Z = unit(np.cross(mc - hc, up))
    X = np.cross(up, Z)
    # heel marker: most posterior point of the heel (along the foot's long axis)
    k = extreme_vertex(surface, -X, heel_zone, smooth=0.001)
    res.landmarks[f"{P}HEE"] = Landmark(V[k].copy(), isotropic_cov(0.002))
    dd = unit(X + up)
    for lab in ("met1", "met5"):
        f = contacts[lab][1]
        if f is not None:
            res.landmarks[f"{lab}_dorsal"] = Landmark(np.asarray(f.centre) + f.radius * dd, sphere_centre_cov(f))
            res.landmarks[f"{lab}_head_centre"] = Landmark(np.asarray(f.centre, float), sphere_centre_cov(f))
    # first / fifth metatarsal head markers: the most medial / lateral point of the forefoot (anterior 30 %), where
    # they are palpated (IOR foot protocol, Leardini et al. 2007) and where STAPLE puts RD1M / RD5M (ICL_MRI: 90 mm
    # apart; the lowest points of the medial and lateral halves above were 52 mm apart, the 2nd-4th heads)
    for mk, direction in ((f"{P}D1M", med), (f"{P}D5M", -med)):
        k = extreme_vertex(surface, direction, fore, smooth=0.001)
        res.landmarks[mk] = Landmark(V[k].copy(), isotropic_cov(0.002))
    toe = _second_ray_dorsum(V, X, up, med, res.landmarks[f"{P}D1M"].position, res.landmarks[f"{P}D5M"].position, fore,
                             u)
    if toe is not None:
        res.landmarks[f"{P}TOE"] = Landmark(toe, isotropic_cov(0.003))
    # ---- axes and frame ---------------------------------------------------------------------------
    res.frames["foot"] = {"origin": hc.copy(), "rotation": np.column_stack([X, up, Z])}
    # hindfoot: principal axis of the calcaneus block (posterior 45 % of the foot)
    hind = q < q.min() + 0.45 * (q.max() - q.min())
    ch, axh, _ = principal_axes(V[hind], A[hind])
    res.axes["hindfoot_axis"] = Axis(point=ch, direction=unit(axh[:, 0] if axh[:, 0] @ X > 0 else -axh[:, 0]), sd_deg=3.0)
    if "met1_head_centre" in res.landmarks and "met5_head_centre" in res.landmarks:
        a = res.landmarks["met1_head_centre"].position
        b = res.landmarks["met5_head_centre"].position
        mid_head = 0.5 * (a + b)
        res.axes["forefoot_axis"] = Axis(point=mid_head, direction=X.copy(), sd_deg=3.0)
        d = b - a if side == "r" else a - b
        ax5 = Axis(point=mid_head, direction=unit(d), sd_deg=float(np.degrees(
            np.sqrt(np.trace(res.landmarks["met1_head_centre"].cov + res.landmarks["met5_head_centre"].cov) / 2)
            / np.linalg.norm(d))))
        res.axes["mtp_axis"] = ax5
        res.landmarks["mtp_centre"] = Landmark(mid_head, 0.25 * (res.landmarks["met1_head_centre"].cov
                                                                + res.landmarks["met5_head_centre"].cov))
    _articular_mtp(res, surface, toes, med, u, side, float((res.landmarks[f"{P}D1M"].position
                                                            - res.landmarks[f"{P}D5M"].position) @ med))
    res.frames["anatomical"] = {"origin": c, "rotation": np.column_stack([X, up, Z])}
    return res


def detect_toes(surface: Surface, name: str = "toes_r", calcn: BoneLandmarks | None = None) -> BoneLandmarks:
    """MTP axis of the toes segment.

    With the calcaneus' result the axis is its mtp axis (`detect_calcn`), flagged low-confidence when it comes
    from the plantar metatarsal head spheres; alone, the toes' principal axis is used.
    """
    res = BoneLandmarks(bone=name, side=side_of(name))
    if calcn is not None and "mtp_axis" in calcn.axes:
        res.axes["mtp_axis"] = calcn.axes["mtp_axis"]
        why = plantar_mtp_reason(calcn)
        if why is not None:
            res.flag(FLAG_LOW_CONFIDENCE, why)
        return res
    V, A = surface.vertices, surface.areas
    c, ax, _ = principal_axes(V, A)
    res.axes["mtp_axis"] = Axis(point=c, direction=ax[:, 0], sd_deg=10.0)
    res.flag(FLAG_LOW_CONFIDENCE, "MTP axis from the toes' principal axis only")
    return res
