"""Tibia and fibula landmarks: shaft, plateau, tuberosity, malleoli, fibular head, plafond cylinder.

A ``tibia`` surface often carries the fibula as a second connected component
(the STAPLE data sets do); the two are split by connectivity and the fibula
landmarks are reported under ``fibula_<side>`` when no separate fibula
surface is given.

Orientation from the bone alone:

* long axis = largest principal axis of the tibia component; the proximal end
  is the one with more surface (plateau block versus pilon);
* medial-lateral line = widest direction of the proximal (plateau) surface;
* with a fibula (component or separate bone): the fibula lies lateral *and*
  posterior of the tibial plateau centre, which fixes both signs;
  without it: the medial malleolus is the most distal point and is medial,
  the tibial tuberosity is the most anterior bump below the plateau;
* side = chirality of (anterior, proximal, lateral).
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError
from lowerlimb.geometry import orient, unit
from lowerlimb.bones import side_of
from personalize.fitting import fit_cylinder

from .common import FLAG_LOW_CONFIDENCE, FLAG_NAME_MISMATCH, FLAG_TRUNCATED, Axis, BoneLandmarks, Landmark
from .long_bones import long_bone_axes, shaft_line
from .shape_fits import axis_sd_deg, isotropic_cov, perpendicular, principal_axes, refine_cylinder
from .surface import Surface, edge_curvature, extreme_vertex, largest_patch, vertex_components

__all__ = ["detect_tibia", "detect_fibula", "split_components", "merge_surfaces", "tibia_surface"]

PLAFOND_RADII = np.arange(0.012, 0.0401, 0.002)


def split_components(surface: Surface) -> list[Surface]:
    """Connected components of a surface, largest (by area) first."""
    F = surface.faces
    n = len(surface.vertices)
    k, lab = vertex_components(F, n)
    if k == 1:
        return [surface]
    out = []
    for c in range(k):
        vm = lab == c
        fm = vm[F[:, 0]]
        if fm.sum() < 50:
            continue
        idx = np.full(n, -1)
        idx[vm] = np.arange(vm.sum())
        out.append(Surface(vertices=surface.vertices[vm], faces=idx[F[fm]], normals=surface.normals[vm],
                           areas=surface.areas[vm], closed=surface.closed))
    out.sort(key=lambda s: -s.areas.sum())
    return out


def merge_surfaces(parts: list[Surface]) -> Surface:
    """One surface holding all `parts` (vertex and face arrays concatenated)."""
    off = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return Surface(vertices=np.concatenate([p.vertices for p in parts]),
                   faces=np.concatenate([p.faces + o for p, o in zip(parts, off)]),
                   normals=np.concatenate([p.normals for p in parts]),
                   areas=np.concatenate([p.areas for p in parts]), closed=all(p.closed for p in parts))


def tibia_surface(surface: Surface) -> Surface:
    """The tibia without a fibula component (used as the talus' neighbour)."""
    comps = split_components(surface)
    keep = [comps[0]]
    found = False
    for c in comps[1:]:
        _, _, sdc = principal_axes(c.vertices, c.areas)
        if not found and sdc[0] > 0.05 and c.areas.sum() > 0.05 * comps[0].areas.sum():
            found = True
        else:
            keep.append(c)
    return keep[0] if len(keep) == 1 else merge_surfaces(keep)


#: a second shaft in the tibia's middle third counts as a fused fibula when it holds at least this share of the
#: band's surface and spans this share of the band's length (ICL-MRI and LHDL-CT fibulae: 25-35 % and the whole
#: band; a bump of the tibia itself, such as the interosseous crest, is not a component of the band)
FUSED_FIBULA_AREA = 0.1
FUSED_FIBULA_SPAN = 0.8


def fused_fibular_shaft(tib: Surface, h: np.ndarray, lo: float, hi: float) -> np.ndarray | None:
    """Centroid (3,) of a fibular shaft joined to the tibia surface at its ends, or None.

    Tibia and fibula touch only at the tibiofibular joints; where a segmentation or a point-cloud
    reconstruction joins them there, the surface is one component, but its part between heights `lo` and
    `hi` (m, `h` the vertices' heights along the shaft) still splits into two shafts.  The smaller one is
    the fibula when it is large and long enough (`FUSED_FIBULA_AREA`, `FUSED_FIBULA_SPAN`).
    """
    band = (h > lo) & (h < hi)
    F = tib.faces[band[tib.faces].all(axis=1)]
    if len(F) < 100:
        return None
    _, lab = vertex_components(F, len(tib.vertices))
    used = np.unique(F)
    parts = sorted((np.flatnonzero(lab == c) for c in np.unique(lab[used])), key=lambda v: -tib.areas[v].sum())
    if len(parts) < 2:
        return None
    v = parts[1]
    total = sum(tib.areas[p].sum() for p in parts)
    if tib.areas[v].sum() < FUSED_FIBULA_AREA * total or np.ptp(h[v]) < FUSED_FIBULA_SPAN * (hi - lo):
        return None
    return (tib.areas[v] @ tib.vertices[v]) / tib.areas[v].sum()


def detect_tibia(surface: Surface, name: str = "tibia_r", fibula: Surface | None = None, *,
                 femur: Surface | None = None, talus: Surface | None = None):
    """Detect tibial landmarks, axes and the plafond cylinder.

    Parameters
    ----------
    surface : Surface
        The tibia (may include the fibula as a separate component).
    name : str
        ``tibia_r`` or ``tibia_l``.
    fibula : Surface, optional
        A separately segmented fibula (used as the lateral-posterior cue).
    femur, talus : Surface, optional
        Neighbours from the same scan: the end that articulates with the
        femur is proximal, the one on the talus distal, and an end lying on
        its neighbour is not a field-of-view cut (a flat plateau can look
        like one).

    Returns
    -------
    tibia : BoneLandmarks
    fibula_component : Surface or None
        The fibula found inside `surface`, if any.
    """
    res = BoneLandmarks(bone=name, side=side_of(name))
    comps = split_components(surface)
    tib = comps[0]
    fib_comp = None
    rest = []
    for c in comps[1:]:
        _, _, sdc = principal_axes(c.vertices, c.areas)
        if fib_comp is None and sdc[0] > 0.05 and c.areas.sum() > 0.05 * tib.areas.sum():   # long and big enough
            fib_comp = c
        else:
            rest.append(c)
    if rest:
        # pieces that are not the fibula belong to the tibia (e.g. a pilon split
        # from the shaft by a segmentation gap)
        tib = merge_surfaces([tib] + rest)
        res.notes.append(f"{name}: {len(rest) + 1} disconnected tibial pieces merged")
    fib = fibula if fibula is not None else fib_comp
    V, Nrm, A = tib.vertices, tib.normals, tib.areas
    lb = long_bone_axes(tib)
    e, L = lb.axis, lb.length
    cut = dict(lb.cut)
    on = {(k, e): _end_on(V, lb, e, other) for k, other in (("femur", femur), ("talus", talus)) for e in (1, -1)}
    near = _neighbour_ends(on)
    if near is not None:
        # bones from one scan sit in their joints: trust the neighbours over the end shapes
        ps = near
        for sgn, k in ((ps, "femur"), (-ps, "talus")):
            if cut[sgn] and on[(k, sgn)]:
                cut[sgn] = False
        if cut[1] and cut[-1]:
            res.flag(FLAG_TRUNCATED, "both tibial ends are planar cuts")
            res.flag(FLAG_LOW_CONFIDENCE)
        elif cut[1] or cut[-1]:
            res.flag(FLAG_TRUNCATED, "tibia truncated")
    elif cut[1] and not cut[-1]:
        ps = -1 if lb.flatness[-1] > 0.65 else 1
        res.flag(FLAG_TRUNCATED, "tibia truncated")
    elif cut[-1] and not cut[1]:
        ps = 1 if lb.flatness[1] > 0.65 else -1
        res.flag(FLAG_TRUNCATED, "tibia truncated")
    else:
        ps = 1 if lb.area[1] > lb.area[-1] else -1
        if cut[1]:
            res.flag(FLAG_TRUNCATED, "both tibial ends are planar cuts")
            res.flag(FLAG_LOW_CONFIDENCE)
    prox = ps * e
    hp = ps * lb.h
    _femur_check(tib, res, lb, name)
    top, bot = float(hp.max()), float(hp.min())
    has_prox, has_dist = not cut[ps], not cut[-ps]
    lo = bot + (0.3 * L if has_dist else 0.05 * L)
    hi = top - (0.3 * L if has_prox else 0.05 * L)
    sp, sd = shaft_line(tib, e, lb.h, *sorted((ps * lo, ps * hi)))
    sd = orient(sd, prox)
    res.axes["shaft_axis"] = Axis(point=sp, direction=sd, sd_deg=1.0)

    # ---- plateau ------------------------------------------------------------------
    plat = None
    if has_prox:
        plat = (hp > top - 0.02) & (Nrm @ sd > 0.6)
        if plat.sum() < 20:
            plat = None
    if plat is not None:
        cp, axp, _ = principal_axes(V[plat], A[plat])
        ml = unit(perpendicular(axp[:, 0], sd))
    else:
        dist_blk = hp < bot + 0.04
        cp = None
        _, axd, _ = principal_axes(V[dist_blk], A[dist_blk])
        ml = unit(perpendicular(axd[:, 0], sd))
    w = np.cross(sd, ml)

    # ---- signs: lateral and anterior -------------------------------------------------
    lat = ant = None
    fc = None if fib is None else (fib.areas @ fib.vertices) / fib.areas.sum()
    if fc is None and has_prox and has_dist:
        fc = fused_fibular_shaft(tib, hp, bot + 0.3 * L, top - 0.3 * L)
        if fc is not None:
            res.notes.append(f"{name}: fibula joined to the tibia; its shaft gives the lateral and posterior sides")
    if fc is not None:
        ref = cp if cp is not None else sp
        off = perpendicular(fc - ref, sd)
        lat = ml if off @ ml > 0 else -ml
        ant = -w if off @ w > 0 else w
        if abs(off @ w) < 0.003:
            ant = None
    if lat is None and has_dist:
        k = int(np.argmin(hp))                     # tip of the medial malleolus
        off = perpendicular(V[k] - sp, sd)
        lat = -ml if off @ ml > 0 else ml
    if ant is None and lat is not None and res.side is not None:
        # no fibula: honour the side in the name (chirality then fixes anterior)
        ant = w if (np.cross(w, sd) @ lat > 0) == (res.side == "r") else -w
        res.notes.append(f"{name}: no fibula; anterior direction from the side in the name")
    if ant is None and has_prox:
        slab = (hp < top - 0.02) & (hp > top - 0.06)
        q = (V[slab] - sp) @ w
        ant = w if q.max() > -q.min() else -w
        res.flag(FLAG_LOW_CONFIDENCE, "tibial anterior direction from the tuberosity only")
    if lat is None or ant is None:
        res.flag(FLAG_LOW_CONFIDENCE, "tibial orientation undetermined")
        lat = ml if lat is None else lat
        ant = w if ant is None else ant
    right = np.cross(ant, sd)
    side = "r" if right @ lat > 0 else "l"
    res.side = side
    P = "R" if side == "r" else "L"
    med = -lat

    if plat is not None:
        # centre of the plateau: centroid of the superior-facing articular region,
        # taken on the plateau surface (nearest vertex height)
        res.landmarks["plateau_centre"] = Landmark(cp.copy(), isotropic_cov(0.002))
        dirn = ml if ml @ right > 0 else -ml
        res.axes["knee_axis"] = Axis(point=cp.copy(), direction=dirn, sd_deg=3.0)
        # tuberosity: most anterior point 1-5 cm below the plateau
        slab = (hp < top - 0.015) & (hp > top - 0.06)
        if slab.any():
            k = extreme_vertex(tib, ant, slab, smooth=0.002)
            res.landmarks[f"{P}TTB"] = Landmark(V[k].copy(), isotropic_cov(0.002))
    if has_dist:
        # medial malleolus: its distal tip (ISB's MM, for the frames and axes) and its most medial point, where a
        # medial malleolus marker is palpated (the IOR / Plug-in-Gait site, STAPLE's RMMA); re-found along the
        # talocrural axis once the talus is known (`malleolar_markers`)
        med_blk = (hp < bot + 0.05) & (((V - sp) @ med) > 0)
        k = extreme_vertex(tib, -sd, med_blk, smooth=0.001)
        res.landmarks["medial_malleolus_tip"] = Landmark(V[k].copy(), isotropic_cov(0.002))
        k = extreme_vertex(tib, med, med_blk, smooth=0.001)
        res.landmarks[f"{P}MMA"] = Landmark(V[k].copy(), isotropic_cov(0.002))
        _plafond(tib, res, hp, bot, sd, right, ant)
    # ISB-like frame: Y from the malleolar midpoint (or plafond) to the plateau centre
    if "plateau_centre" in res.landmarks and "medial_malleolus_tip" in res.landmarks:
        lo_pt = res.landmarks.get("plafond_centre", res.landmarks["medial_malleolus_tip"]).position
        Y = unit(res.landmarks["plateau_centre"].position - lo_pt)
        Z = unit(perpendicular(right, Y))
        X = np.cross(Y, Z)
        res.frames["isb"] = {"origin": lo_pt.copy(), "rotation": np.column_stack([X, Y, Z])}
    res.frames["anatomical"] = {"origin": sp.copy(), "rotation": np.column_stack([ant, sd, right])}
    return res, fib_comp


#: an end of the tibia whose tip lies within this distance of the femur (talus) articulates with it, m
NEIGHBOUR_GAP = 0.01


def _end_on(V: np.ndarray, lb, sgn: int, other: Surface | None) -> bool:
    """Whether the tip (last 5 mm) of the tibia's ``sgn`` end lies within `NEIGHBOUR_GAP` of `other`."""
    if other is None:
        return False
    hh = sgn * lb.h
    tip = hh > hh.max() - 0.005
    d, _ = other.tree().query(V[tip], distance_upper_bound=NEIGHBOUR_GAP)
    return bool(np.isfinite(d).mean() > 0.2)


def _neighbour_ends(on: dict) -> int | None:
    """Sign (+1 / -1 along the tibia's long axis) of the proximal end, or None if the neighbours do not tell.

    `on[("femur" | "talus", end)]`: whether that end of the tibia lies on that neighbour (`_end_on`).
    """
    votes = []
    for other, toward in (("femur", 1), ("talus", -1)):
        ends = [e for e in (1, -1) if on[(other, e)]]
        if len(ends) == 1:
            votes.append(toward * ends[0])
    if not votes or len(set(votes)) > 1:
        return None
    return votes[0]


def _femur_check(tib: Surface, res: BoneLandmarks, lb, name: str) -> None:
    """Flag a femur given as a tibia: a femoral head (sphere covering >= 50 %, off the long axis) at either end."""
    from .femur import find_head, head_coverage

    for sgn in (1, -1):
        hh = sgn * lb.h
        region = hh > hh.max() - min(0.25 * lb.length, 0.11)
        try:
            fit, sel = find_head(tib, region)
        except FitError:
            continue
        if fit is None:
            continue
        off = np.asarray(fit.centre) - lb.centre
        off = float(np.linalg.norm(off - (off @ lb.axis) * lb.axis))
        # a femoral head: large spherical coverage, set off the long axis by the neck
        if 0.012 < fit.radius < 0.035 and head_coverage(tib, fit, sel) >= 0.5 and off > 0.8 * fit.radius:
            res.flag(FLAG_NAME_MISMATCH, f"{name}: one end carries a femoral head; is this mesh a femur?")
            res.flag(FLAG_LOW_CONFIDENCE)
            return


def _plafond(tib: Surface, res: BoneLandmarks, hp, bot, sd, right, ant):
    """Cylinder fitted to the concave distal articular surface (plafond).

    Candidates are the largest connected patches of distal-facing surface in
    the distal 6 cm, and the largest patches of its concave part (negative
    mean curvature, `common.edge_curvature`): on a shallow plafond the convex
    anterior and posterior lips and the malleolus joined to it make the whole
    patch fit a convex cylinder.  Each candidate gets a cylinder fit (axis
    hint: medio-lateral) and a band refinement; the largest patch whose
    cylinder is concave (normals towards the axis) with a plausible radius
    (2-sd interval meeting 1-4.5 cm) wins.  The malleolar tips, also
    distal-facing, are convex and rejected.
    """
    V, Nrm = tib.vertices, tib.normals
    region = (hp < bot + 0.06) & (Nrm @ (-sd) > 0.5)
    best = None
    candidates = largest_patch(tib, region, 3) + largest_patch(tib, region & (edge_curvature(tib) < 0), 2)
    for patch in candidates:
        if patch.sum() < 20:
            continue
        try:
            f0 = fit_cylinder(V[patch], normals=Nrm[patch], axis_hint=right)
            d = V[patch] - f0.point
            radial = d - np.outer(d @ f0.axis, f0.axis)
            # plausible radius: its 2-sd interval meets 1-4.5 cm (a shallow plafond's
            # radius is uncertain by several millimetres)
            r_sd = 2.0 * float(np.sqrt(max(np.asarray(f0.covariance)[-1, -1], 0.0)))
            if np.mean(np.einsum("ij,ij->i", radial, Nrm[patch])) >= 0 or not (
                    f0.radius - r_sd < 0.045 and f0.radius + r_sd > 0.01):
                continue                            # convex or implausible: not the plafond
            fit, sel, p, u = refine_cylinder(V, Nrm, f0.point, f0.axis, f0.radius,
                                             band=max(0.0015, 0.08 * f0.radius), convex=False, min_cos=0.6,
                                             mask=(hp < bot + 0.07) & (Nrm @ (-sd) > 0.0))
        except FitError:
            continue
        area = float(tib.areas[sel].sum())
        if best is None or area > best[0]:
            best = (area, fit, sel, p, u)
    if best is None:
        res.flag(FLAG_LOW_CONFIDENCE, "tibial plafond not found")
        return
    _, fit, sel, p, u = best
    u = orient(u, right)
    cov = np.asarray(fit.covariance)[:3, :3] + 1e-12 * np.eye(3)
    # centre of the articular arc: the cylinder's apex above its axis
    up_ax = unit(perpendicular(sd, u))
    res.landmarks["plafond_centre"] = Landmark(p + float(fit.radius) * up_ax, cov)
    res.scalars["plafond_radius"] = float(fit.radius)
    res.scalar_sd["plafond_radius"] = float(np.sqrt(max(np.asarray(fit.covariance)[-1, -1], 0.0)))
    res.axes["ankle_axis"] = Axis(point=p.copy(), direction=u, sd_deg=axis_sd_deg(fit))
    res.fits["plafond"] = {"type": "cylinder", "point": p.tolist(), "axis": u.tolist(),
                           "radius": float(fit.radius), "rms": float(fit.rms), "n_points": int(sel.sum()),
                           "converged": bool(fit.converged)}


def malleolar_markers(tibia_surface: Surface, fibula_surface: Surface, tibia: BoneLandmarks, fibula: BoneLandmarks,
                      ankle_axis: np.ndarray) -> None:
    """The malleolar marker sites (``RMMA``, ``RANK``) re-found along the talocrural axis (in place).

    Plug-in-Gait and IOR palpate the malleoli along the ankle's axis.  Alone,
    the tibia and fibula have only the knee's medial-lateral direction (MMA)
    and the line through the malleolar tips (ANK), 17-24 deg from the talar
    dome's axis on ICL-MRI and LHDL-CT; on the flat faces of the malleoli that
    moves the extreme points 3-9 mm.  With the talus detected, both markers are
    the extreme points of the distal 5 cm (tibia) and 4 cm (fibula) along its
    ankle axis (``ankle_axis``: unit, any sign).
    """
    P = "R" if tibia.side == "r" else "L"
    if "shaft_axis" not in tibia.axes or f"{P}MMA" not in tibia.landmarks or f"{P}ANK" not in fibula.landmarks:
        return
    prox = tibia.axes["shaft_axis"].direction
    ctr = tibia.axes["shaft_axis"].point
    med = unit(np.asarray(ankle_axis, float))
    if (fibula.landmarks[f"{P}ANK"].position - ctr) @ med > 0:
        med = -med
    for surf, res, key, band, d in ((tibia_surface, tibia, f"{P}MMA", 0.05, med),
                                    (fibula_surface, fibula, f"{P}ANK", 0.04, -med)):
        V = surf.vertices
        hp = V @ prox
        blk = (hp < hp.min() + band) & ((V - ctr) @ d > 0)
        if blk.sum() >= 3:
            k = extreme_vertex(surf, d, blk, smooth=0.001)
            res.landmarks[key] = Landmark(V[k].copy(), isotropic_cov(0.002))


def detect_fibula(surface: Surface, name: str = "fibula_r", tibia: BoneLandmarks | None = None) -> BoneLandmarks:
    """Fibular head (``RHFB``) and lateral malleolus (``RANK``).

    The proximal end and the lateral direction come from the tibia's
    anatomical frame when available; alone, the fibula's ends are told apart
    by the malleolus' larger flare and the result is flagged low-confidence.
    """
    res = BoneLandmarks(bone=name, side=side_of(name))
    fib = surface                                  # every piece of a fibula surface is fibula
    V = fib.vertices
    c, ax, _ = principal_axes(V, fib.areas)
    e = ax[:, 0]
    if tibia is not None and "anatomical" in tibia.frames:
        R = tibia.frames["anatomical"]["rotation"]
        prox = orient(e, R[:, 1])
        right = R[:, 2]
        side = tibia.side or res.side
    else:
        lb = long_bone_axes(fib)
        prox = e if lb.area[1] > lb.area[-1] else -e   # the head is bulkier than the malleolus
        right = None
        side = res.side
        res.flag(FLAG_LOW_CONFIDENCE, "fibula without tibia: orientation uncertain")
    res.side = side
    P = "R" if side == "r" else "L"
    h = (V - c) @ prox
    if right is not None:
        # fibular head: most lateral point of the proximal 3 cm
        lat = right if side == "r" else -right
        k = extreme_vertex(fib, lat, h > h.max() - 0.03, smooth=0.001)
    else:
        k = extreme_vertex(fib, prox, smooth=0.002)
    res.landmarks[f"{P}HFB"] = Landmark(V[k].copy(), isotropic_cov(0.002))
    # lateral malleolus: its distal tip (ISB's LM, for the frames and axes) and its most lateral point along the
    # transmalleolar direction over the distal 4 cm, where the ankle marker is palpated (Plug-in-Gait ANK, IOR LM;
    # STAPLE's RANK, 20 mm above its tip RLM on ICL_MRI)
    k = extreme_vertex(fib, -prox, smooth=0.001)
    tip = V[k].copy()
    res.landmarks["lateral_malleolus_tip"] = Landmark(tip, isotropic_cov(0.002))
    a = None
    if tibia is not None and "medial_malleolus_tip" in tibia.landmarks:
        a = tip - tibia.landmarks["medial_malleolus_tip"].position
        a = a - (a @ prox) * prox
    elif right is not None:
        a = right if side == "r" else -right
    if a is not None and np.linalg.norm(a) > 1e-6:
        k = extreme_vertex(fib, a / np.linalg.norm(a), h < h.min() + 0.04, smooth=0.001)
        res.landmarks[f"{P}ANK"] = Landmark(V[k].copy(), isotropic_cov(0.002))
    else:
        res.landmarks[f"{P}ANK"] = Landmark(tip, isotropic_cov(0.002))
    res.axes["shaft_axis"] = Axis(point=c, direction=prox, sd_deg=2.0)
    return res
