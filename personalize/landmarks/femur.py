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
(`shape_fits.hough_centres`), then refined by robust fits on the points within a
band of the primitive (`shape_fits.refine_sphere`).  The knee end (condyles,
knee axis, epicondyles) is `femoral_condyles`.
"""
from __future__ import annotations

import numpy as np

from lowerlimb.errors import FitError
from lowerlimb.geometry import orient, unit
from lowerlimb.bones import side_of

from .common import FLAG_LOW_CONFIDENCE, FLAG_NAME_MISMATCH, FLAG_TRUNCATED, Axis, BoneLandmarks, Landmark
from .femoral_condyles import CONDYLE_RADII, condyle_landmarks
from .long_bones import long_bone_axes, shaft_line
from .shape_fits import hough_centres, isotropic_cov, perpendicular, refine_sphere, sphere_centre_cov, sphere_fit_json
from .surface import Surface, extreme_vertex

__all__ = ["detect_femur", "head_coverage", "find_head"]

HEAD_RADII = np.arange(0.012, 0.0331, 0.0015)      # adult 20-28 mm, juvenile from ~12 mm
#: the femoral head's articular cap: points within this angle of the head's pole (opposite the neck), deg; the
#: head-neck junction lies at about 130-140 deg
HEAD_CAP_DEG = 110.0


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
    res = BoneLandmarks(bone=name, side=side_of(name))
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
            res.fits["femoral_head"] = sphere_fit_json(head, int(sel.sum()))
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
    named = side_of(name)
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
        condyle_landmarks(surface, res, cond_region, dist_region, med, ant, sd, P, noise)

    # ---- neck axis and diameter --------------------------------------------------------
    if head is not None:
        _neck(surface, res, head, sp, sd, prox_region)

    # ---- greater trochanter: the lateral prominence the TRO marker is palpated on -----
    # (CAST, Cappozzo et al. 1995; IOR, Leardini et al. 2007: "most lateral
    # prominence of the greater trochanter"), not its proximal tip, which lies
    # 30-40 mm higher and more posterior on real femurs.  "Lateral" is the
    # epicondylar direction made perpendicular to the mechanical axis (the
    # femur's vertical and frontal-plane lateral in standing).
    if has_prox:
        lat_mask = prox_region & (((V - sp) @ lat) > 0.5 * lb.shaft_radius)
        up = sd
        if head is not None and "intercondylar_midpoint" in res.landmarks:
            up = unit(np.asarray(head.centre) - res.landmarks["intercondylar_midpoint"].position)
        lateral = lat
        if f"{P}KNE" in res.landmarks and f"{P}MFC" in res.landmarks:
            lateral = unit(res.landmarks[f"{P}KNE"].position - res.landmarks[f"{P}MFC"].position)
        lateral = unit(perpendicular(lateral, up))
        if head is not None:
            r = float(head.radius)
            d = (V - np.asarray(head.centre)) @ up
            lat_mask &= (np.linalg.norm(V - head.centre, axis=1) > 1.3 * r) & (d > -4.5 * r) & (d < 2.0 * r)
        if lat_mask.any():
            k = extreme_vertex(surface, lateral, lat_mask, smooth=0.002)
            res.landmarks[f"{P}TRO"] = Landmark(V[k].copy(), isotropic_cov(noise, 0.002))

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


def _bow(surface: Surface, hp, bot, top) -> np.ndarray:
    V, A = surface.vertices, surface.areas
    L = top - bot

    def cen(f0, f1):
        m = (hp > bot + f0 * L) & (hp < bot + f1 * L)
        return (A[m] @ V[m]) / A[m].sum()
    return cen(0.45, 0.55) - 0.5 * (cen(0.2, 0.3) + cen(0.7, 0.8))


#: head radii from the head centre beyond which no face can belong to a neck section `_neck` takes (its planes lie
#: 0.9-2.2 radii from the centre and keep loops centred within 1.5 radii of the neck line; an oblique cut of the
#: shaft spans under 3 radii)
NECK_SECTION_BALL = 8.0


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
    # the sections are cut from the proximal femur only (faces within NECK_SECTION_BALL head radii of the head
    # centre, which holds every loop that can be chosen): the same loops, sliced from a third of the faces
    near = np.linalg.norm(surface.vertices - c, axis=1) < NECK_SECTION_BALL * r
    mesh = trimesh.Trimesh(surface.vertices, surface.faces[near[surface.faces].any(axis=1)], process=False)
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
