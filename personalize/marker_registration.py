"""MRI landmarks registered segment by segment to the markers of a static trial.

Each registration segment (pelvis; per side femur, shank = tibia + fibula,
foot = calcaneus + talus + toes) pairs the landmarks named like a marker
(`SEGMENT_MARKERS`) with the marker centres of the static trial
(`marker_correspondences`: the landmark moved out along the bone's outward
normal by the soft tissue and the marker radius) and registers them
(`personalize.registration.register_landmarks`).  `register_segments` checks
units and sides first (left and right labels mixed between the MRI and the
markers are refused).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Mapping

import numpy as np

from lowerlimb.bones import mirror_name
from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS

from .registration import (MARKER_PLACEMENT_SD, SURFACE_NORMAL_SD_DEG, Registration, palpation_sd, register_landmarks,
                           skin_prior, static_marker_positions)

if TYPE_CHECKING:
    from personalize.landmarks.common import BoneLandmarks, LandmarkSet

__all__ = ["SEGMENT_MARKERS", "SEGMENT_BONES", "GUESSED_NORMAL_SD_DEG", "AXIS_LANDMARK_DISTANCE", "Correspondences",
           "marker_correspondences",
           "surface_normal", "SegmentRegistrations", "register_segments"]

#: angular sd (deg) of an outward normal guessed from internal landmarks (no surface given)
GUESSED_NORMAL_SD_DEG = 30.0
#: m, largest distance of a landmark from a joint axis for it to count as lying on that axis (and be projected on
#: it): the epicondyles and malleoli of the five real bone sets of ../shared/data/bones lie 1-29 mm from their
#: knee / ankle axis (MC22's left ankle, whose plafond is not found, the 29), of the analytic phantom 9-31 mm; the
#: nearest landmark off the axis (the tibial tuberosity, fibular head, greater trochanter) 300-424 mm
AXIS_LANDMARK_DISTANCE = 0.050
#: marker names (without side letter) per registration segment
SEGMENT_MARKERS: dict[str, tuple[str, ...]] = {
    "pelvis": ("RASI", "LASI", "RPSI", "LPSI", "SYMP"),
    "femur": ("TRO", "KNE", "MFC"),
    "tibia": ("TTB", "HFB", "ANK", "MMA"),
    "calcn": ("HEE", "D1M", "D5M"),
}
#: bones whose landmarks form one rigid registration segment (tibia+fibula = shank; foot)
SEGMENT_BONES: dict[str, tuple[str, ...]] = {
    "pelvis": ("pelvis",),
    "femur": ("femur",),
    "tibia": ("tibia", "fibula"),
    "calcn": ("calcn", "talus", "toes"),
}


def _segment_marker_names(seg: str, side: str | None) -> tuple[str, ...]:
    if seg == "pelvis":
        return SEGMENT_MARKERS["pelvis"]
    return tuple(side.upper() + m for m in SEGMENT_MARKERS[seg])


def _internal_reference(bones: Mapping[str, BoneLandmarks], bone_names, p: np.ndarray):
    """Nearest non-marker (internal: centres) landmark of the segment, or None."""
    best, bd = None, np.inf
    for b in bone_names:
        for name, lm in (bones[b].landmarks.items() if b in bones else ()):
            if name in _ALL_MARKER_NAMES:
                continue
            dist = np.linalg.norm(lm.position - p)
            if 1e-4 < dist < bd:
                best, bd = lm.position, dist
    return best


_ALL_MARKER_NAMES = {m for v in SEGMENT_MARKERS.values() for m in v} | {
    s + m for s in "RL" for k, v in SEGMENT_MARKERS.items() if k != "pelvis" for m in v}


#: m, radius over which a landmark's outward normal is averaged: the soft tissue and the marker lie along the
#: surface's local orientation, not one facet's (a label-volume surface's vertex normals scatter by 20-40 deg,
#: and 50 mm of tissue turns 20 deg into 17 mm)
NORMAL_RADIUS = 0.008


def surface_normal(surface, p: np.ndarray, radius: float = NORMAL_RADIUS) -> np.ndarray:
    """Outward unit normal of `surface` (``vertices`` and ``vertex_normals`` or ``normals``) at `p`: the mean of
    the vertex normals within `radius` of the vertex nearest `p` (that vertex's own when none other is)."""
    V = np.asarray(getattr(surface, "vertices"), float)
    N = getattr(surface, "vertex_normals", None)
    if N is None:
        N = getattr(surface, "normals")
    N = np.asarray(N, float)
    d2 = np.sum((V - p) ** 2, axis=1)
    k = int(np.argmin(d2))
    near = np.sum((V - V[k]) ** 2, axis=1) <= radius ** 2
    n = N[near].sum(axis=0)
    if not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
        n = N[k]
    return n / np.linalg.norm(n)


@dataclass
class Correspondences:
    """Scanner points paired with lab marker centres, with each pair's offset model: `register_landmarks`' input.

    Per pair: the scanner point and its covariance, the marker centre and its
    covariance, the outward normal, the offset along it (soft tissue + marker
    radius; 0 for a point known in both frames) with its sd, the normal's sd and
    the palpation sd across the normal (0 for a point known in both frames).
    """

    names: list = field(default_factory=list)
    mri: list = field(default_factory=list)
    mri_cov: list = field(default_factory=list)
    lab: list = field(default_factory=list)
    lab_cov: list = field(default_factory=list)
    normals: list = field(default_factory=list)
    offset: list = field(default_factory=list)
    offset_sd: list = field(default_factory=list)
    normal_sd_deg: list = field(default_factory=list)
    tissue: list = field(default_factory=list)
    palpation_sd: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.names)

    def add(self, name: str, mri: Gaussian, lab: Gaussian, normal=(0.0, 0.0, 1.0), offset: float = 0.0,
            offset_sd: float = 0.0, normal_sd_deg: float = SURFACE_NORMAL_SD_DEG) -> None:
        """One pair; the defaults describe a point known in both frames (a joint centre: no offset)."""
        self.names.append(name)
        self.mri.append(mri.mean)
        self.mri_cov.append(mri.cov)
        self.lab.append(lab.mean)
        self.lab_cov.append(lab.cov)
        self.normals.append(np.asarray(normal, float))
        self.offset.append(float(offset))
        self.offset_sd.append(float(offset_sd))
        self.normal_sd_deg.append(float(normal_sd_deg))
        self.tissue.append(0.0)
        self.palpation_sd.append(0.0)

    def add_marker(self, name: str, mri: Gaussian, lab: Gaussian, normal, *, skin_thickness=None, skin_sd=None,
                   marker_radius: float = DEFAULT_MARKER_RADIUS, normal_sd_deg: float = SURFACE_NORMAL_SD_DEG,
                   palpated: bool | None = None) -> None:
        """A skin marker over a scanner point: offset = soft tissue (`skin_thickness`, else the site prior) + radius.

        A prior tissue is recorded in ``tissue`` (0 for a given one): `register` can estimate its scale.  A
        palpated marker carries its site's palpation sd across the normal (`registration.palpation_sd`);
        ``palpated=None``: palpated unless its tissue is given (measured in the MRI: the measured path's scales
        were calibrated on phantoms whose markers sit exactly)."""
        self.add(name, mri, lab, normal, _per_marker(skin_thickness, name, 0) + marker_radius,
                 _per_marker(skin_sd, name, 1), normal_sd_deg)
        given = skin_thickness.get(name) if isinstance(skin_thickness, dict) else skin_thickness
        self.tissue[-1] = _per_marker(None, name, 0) if given is None else 0.0
        self.palpation_sd[-1] = palpation_sd(name) if (given is None if palpated is None else palpated) else 0.0

    def register(self, segment: str | None = None, *, k_outlier: float = 3.0, tissue_prior=None,
                 fixed=()) -> Registration:
        """`register_landmarks` of these pairs; with `tissue_prior` (`kinematics.gait.soft_tissue.TissueScalePrior`)
        the scale of the prior tissues is estimated with the pose; `fixed`: names never rejected as outliers."""
        return register_landmarks(np.array(self.mri), np.array(self.lab), np.array(self.mri_cov), np.array(self.lab_cov),
                                  np.array(self.normals), np.array(self.offset), offset_sd=np.array(self.offset_sd),
                                  normal_sd_deg=np.array(self.normal_sd_deg), names=self.names, k_outlier=k_outlier,
                                  segment=segment, tissue=np.array(self.tissue) if tissue_prior is not None else None,
                                  tissue_prior=tissue_prior, palpation_sd=np.array(self.palpation_sd), fixed=fixed)


def marker_correspondences(bones: Mapping[str, BoneLandmarks], bone_names, marker_names, static: Mapping[str, Gaussian],
                           *, surfaces: dict | None = None, normals: dict | None = None, skin_thickness=None,
                           skin_sd=None, marker_radius: float = DEFAULT_MARKER_RADIUS, axis=None,
                           sites: Mapping[str, str] | None = None, palpated: bool | None = None,
                           tissue_scale: float = 1.0) -> Correspondences:
    """The landmarks of `bone_names` named like a marker of `marker_names` that `static` shows (in that order).

    Each landmark p is paired with its marker, offset along the outward normal
    n by the soft tissue + marker radius (`Correspondences.add_marker`).  n is
    ``normals[marker]`` (scanner frame), else the landmark's bone surface in
    `surfaces` (nearest vertex; a bone of the segment when its own is absent),
    else guessed from the nearest internal landmark of the segment (e.g.
    condyle centre -> epicondyle) with `GUESSED_NORMAL_SD_DEG`.  With ``axis =
    (point c, direction u)`` a landmark that lies on that joint axis (within
    `AXIS_LANDMARK_DISTANCE` of it: the epicondyles, the malleoli) is first
    projected on it and n = ±u away from c: Plug-in-Gait places the knee and
    ankle markers on the flexion / transmalleolar axis at the epicondyle /
    malleolus, not on the prominence itself.  Landmarks away from the axis (the
    greater trochanter, tibial tuberosity, fibular head) are used as they are.
    Without `axis` every landmark is the palpated site itself (IOR, CAST:
    markers on the prominences).  ``sites``: marker -> the landmark to pair it
    with when not the one named like it (the malleolus tips for markers put on
    the transmalleolar axis).  The normal of a marker over prior (not measured)
    tissue is averaged over the expected tissue thickness (`tissue_scale` x its
    prior, at least `NORMAL_RADIUS`): fat smooths a prominence at the scale of
    its own thickness.

    Parameters
    ----------
    bones : bone -> `personalize.landmarks.BoneLandmarks` (scanner frame, m)
    static : marker -> lab centre (`static_marker_positions`)
    """
    found = {}
    site = {(sites or {}).get(n, n): n for n in marker_names}
    for b in bone_names:
        for n, lm in (bones[b].landmarks.items() if b in bones else ()):
            if n in site:
                found[site[n]] = (b, lm)
    pair = [n for n in marker_names if n in found and n in static]
    P = np.array([found[n][1].position for n in pair], float).reshape(-1, 3)
    out = Correspondences()
    for i, n in enumerate(pair):
        b, lm = found[n]
        p = P[i]
        surf = None
        if surfaces is not None:
            surf = surfaces.get(b, next((surfaces[x] for x in bone_names if x in surfaces), None))
        if normals is not None and n in normals:
            nrm, nsd = np.asarray(normals[n], float), SURFACE_NORMAL_SD_DEG
        elif surf is not None:
            nrm, nsd = surface_normal(surf, p, _normal_radius(n, skin_thickness, palpated, tissue_scale)), \
                SURFACE_NORMAL_SD_DEG
        else:
            ref = _internal_reference(bones, bone_names, p)
            if ref is None:
                ref = np.delete(P, i, axis=0).mean(axis=0)
            nrm, nsd = p - ref, GUESSED_NORMAL_SD_DEG
        if axis is not None:
            c0 = np.asarray(axis[0], float)
            u = np.asarray(axis[1], float) / np.linalg.norm(axis[1])
            along = c0 + np.dot(p - c0, u) * u
            if np.linalg.norm(p - along) <= AXIS_LANDMARK_DISTANCE:
                p = along
                nrm = u if np.dot(p - c0, u) > 0 else -u
        out.add_marker(n, Gaussian(p, lm.cov), static[n], nrm, skin_thickness=skin_thickness, skin_sd=skin_sd,
                       marker_radius=marker_radius, normal_sd_deg=nsd, palpated=palpated)
    return out


def _lr_axis(points: dict) -> np.ndarray | None:
    """Subject's rightward direction in one world: RASI - LASI, else mean(R*) - mean(L*)."""
    if "RASI" in points and "LASI" in points:
        return points["RASI"] - points["LASI"]
    r = [v for k, v in points.items() if k[:1] == "R" and mirror_name(k) in points]
    l_ = [points[mirror_name(k)] for k, v in points.items() if k[:1] == "R" and mirror_name(k) in points]
    if r:
        return np.mean(r, axis=0) - np.mean(l_, axis=0)
    return None


def _up_axis(points: dict) -> np.ndarray | None:
    """Subject's upward direction in one world: pelvis centroid minus distal (knee/ankle/foot) centroid, or mid-ASIS - SYMP."""
    pel = [points[n] for n in SEGMENT_MARKERS["pelvis"] if n in points]
    dist = [v for k, v in points.items() if k[1:] in SEGMENT_MARKERS["tibia"] + SEGMENT_MARKERS["calcn"] + ("KNE", "MFC")]
    if pel and dist:
        return np.mean(pel, axis=0) - np.mean(dist, axis=0)
    if "RASI" in points and "LASI" in points and "SYMP" in points:
        return 0.5 * (points["RASI"] + points["LASI"]) - points["SYMP"]
    return None


def _check_sides(mri: dict, lab: dict, lm_source: str, trial_source: str) -> None:
    """Refuse labels of one side matched to markers of the other (mirrored geometry)."""
    right_m, right_l = _lr_axis(mri), _lr_axis(lab)
    # Pelvis chirality: sign of ((LASI - RASI) × (mid-ASIS - mid-PSIS)) · up must agree.
    need = ("RASI", "LASI", "RPSI", "LPSI")
    if all(n in mri for n in need) and all(n in lab for n in need):
        up_m, up_l = _up_axis(mri), _up_axis(lab)
        if up_m is not None and up_l is not None:
            def chir(w, up):
                n = np.cross(w["LASI"] - w["RASI"], 0.5 * (w["RASI"] + w["LASI"]) - 0.5 * (w["RPSI"] + w["LPSI"]))
                return np.sign(n @ up)
            if chir(mri, up_m) != chir(lab, up_l):
                raise InputError(trial_source, f"pelvis markers are mirrored with respect to the MRI landmarks of {lm_source}: "
                                 "left and right labels are swapped on one side")
    if right_m is None or right_l is None:
        return
    # Each lateral-minus-medial pair must point away from the midline in both worlds.
    for lat, med in (("KNE", "MFC"), ("ANK", "MMA"), ("D5M", "D1M")):
        for s, sign in (("R", 1.0), ("L", -1.0)):
            a, b = s + lat, s + med
            if a in mri and b in mri and a in lab and b in lab:
                sm = np.sign((mri[a] - mri[b]) @ right_m)
                sl = np.sign((lab[a] - lab[b]) @ right_l)
                if sm != sl:
                    raise InputError(trial_source, f"{a}/{b} are mirrored with respect to the MRI landmarks of {lm_source}: "
                                     f"the markers labelled {s} look like the other side's (sides mixed)")


class SegmentRegistrations(dict):
    """dict segment -> Registration, plus ``skipped``: {segment: reason} for segments left out."""

    def __init__(self, *args, skipped: dict | None = None, **kw):
        super().__init__(*args, **kw)
        self.skipped = dict(skipped or {})


def _normal_radius(name: str, skin_thickness, palpated: bool | None, tissue_scale: float) -> float:
    """Radius (m) of `surface_normal` for marker `name`: `NORMAL_RADIUS` where its tissue is measured (sampled
    along the vertex's own normal), else at least the expected tissue, `tissue_scale` x its thickness."""
    given = skin_thickness.get(name) if isinstance(skin_thickness, dict) else skin_thickness
    if palpated is False or (palpated is None and given is not None):
        return NORMAL_RADIUS
    return max(NORMAL_RADIUS, float(tissue_scale) * _per_marker(skin_thickness, name, 0))


def _per_marker(value, name: str, k: int) -> float:
    """`value` for marker `name`: a number, a {name: number} dict, or None; else the site prior's mean (k=0) / sd (k=1)."""
    if isinstance(value, dict):
        value = value.get(name)
    return float(skin_prior(name)[k] if value is None else value)


def _segment_correspondences(bones, bone_names, wanted, static, surfaces, normals, skin_thickness, skin_sd,
                             marker_radius, virtual: dict, tissue_scale: float = 1.0) -> Correspondences:
    """`marker_correspondences` of one segment plus its virtual markers ({marker: (scanner point, normal)})."""
    corr = marker_correspondences(bones, bone_names, wanted, static, surfaces=surfaces, normals=normals,
                                  skin_thickness=skin_thickness, skin_sd=skin_sd, marker_radius=marker_radius,
                                  tissue_scale=tissue_scale)
    for n, (p, nrm) in virtual.items():
        if n in static:
            corr.add_marker(n, Gaussian(np.asarray(p, float), np.zeros((3, 3))), static[n], nrm,
                            skin_thickness=skin_thickness, skin_sd=skin_sd, marker_radius=marker_radius)
    return corr


def register_segments(landmarks: LandmarkSet, static_trial, *, sides=("r", "l"), segments=None,
                      on_missing: str = "raise", normals: dict | None = None,
                      surfaces: dict | None = None, skin_thickness: float | dict | None = None,
                      skin_sd: float | dict | None = None, marker_radius: float = DEFAULT_MARKER_RADIUS,
                      placement_sd: float = MARKER_PLACEMENT_SD, k_outlier: float = 3.0,
                      landmarks_source: str = "landmarks.json", tissue_prior=None,
                      virtual: dict | None = None) -> SegmentRegistrations:
    """Register every segment's MRI landmarks to the static-trial markers.

    Segments: ``pelvis`` (RASI, LASI, RPSI, LPSI, SYMP), ``femur_s`` (TRO, KNE,
    MFC), ``tibia_s`` (tibia + fibula: TTB, HFB, ANK, MMA), ``calcn_s`` (calcn,
    talus, toes: HEE, D1M, D5M), each side letter prefixed (R/L).  Segments
    with no landmark and no marker at all are skipped; a segment with some
    but fewer than 3 usable correspondences raises.

    Correspondences and outward normals: `marker_correspondences` (`normals`
    {marker name: (3,)}, else the bone surfaces `surfaces` {bone: mesh}, else
    guessed from the nearest internal landmark with a 30° sd).

    Parameters
    ----------
    landmarks : `personalize.landmarks.LandmarkSet` (scanner frame, m; `LandmarkSet.from_json` reads a landmarks.json)
    static_trial : kinematics.io.markers.MarkerTrial
    segments : names to register (e.g. ``("pelvis", "femur_r")``); default all
    on_missing : ``"raise"`` (default) or ``"skip"``: what to do with a
        segment that has fewer than 3 correspondences (skipped ones are
        listed with the reason in ``result.skipped``)
    skin_thickness, skin_sd : m, one value or {marker name: m}; default (and names missing from a dict):
        the per-site population prior `skin_prior` (soft tissue along the bone's outward normal).
        The pipeline passes the tissue MEASURED in the MRI's body/skin label where it has one
        (`personalize.skin.measure_pelvis_skin`) and lets the prior fill the rest
    placement_sd : m, marker placement sd added to the static scatter
    tissue_prior : `kinematics.gait.soft_tissue.TissueScalePrior` or None: the scale of the prior
        tissues is then estimated per segment with its pose (`register_landmarks`)
    virtual : {segment: {marker: (scanner point (3,), outward normal (3,))}} for markers over a point that is
        not itself a landmark (a sacral marker over the mid-point of the PSIS)

    Returns
    -------
    SegmentRegistrations (dict segment -> Registration, and ``.skipped``)

    Raises
    ------
    InputError : wrong units, fewer than 3 correspondences in a segment (named),
        or left/right labels mixed between the MRI and the markers
    """
    tsrc = static_trial.source or "static trial"
    bones = landmarks.bones
    static = static_marker_positions(static_trial, placement_sd=placement_sd)
    mri_all = {n: lm.position for b in bones.values() for n, lm in b.landmarks.items() if n in _ALL_MARKER_NAMES}
    lab_all = {n: v.mean for n, v in static.items() if n in _ALL_MARKER_NAMES}
    common = sorted(set(mri_all) & set(lab_all))
    if len(common) >= 3:
        # Unit check: inter-landmark distances must match the marker distances to within skin offsets.
        dm = [np.linalg.norm(mri_all[a] - mri_all[b]) for i, a in enumerate(common) for b in common[i + 1:]]
        dl = [np.linalg.norm(lab_all[a] - lab_all[b]) for i, a in enumerate(common) for b in common[i + 1:]]
        ratio = float(np.median(np.asarray(dl) / np.maximum(dm, 1e-9)))
        if not 0.7 < ratio < 1.4:
            raise InputError(tsrc, f"marker distances are {ratio:.3g} x the MRI landmark distances: check units (both must be metres)")
    _check_sides(mri_all, lab_all, landmarks_source, tsrc)

    if on_missing not in ("raise", "skip"):
        raise InputError("on_missing", f"must be 'raise' or 'skip', got {on_missing!r}")
    segs = [("pelvis", None)] + [(s, side) for side in sides for s in ("femur", "tibia", "calcn")]
    known = {s if d is None else f"{s}_{d}" for s, d in segs}
    if segments is not None:
        unknown = sorted(set(segments) - known)
        if unknown:
            raise InputError("segments", f"unknown segment(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    out = SegmentRegistrations()
    for seg, side in segs:
        seg_name = seg if side is None else f"{seg}_{side}"
        if segments is not None and seg_name not in segments:
            continue
        bone_names = [b if b == "pelvis" else f"{b}_{side}" for b in SEGMENT_BONES[seg]]
        wanted = _segment_marker_names(seg, side)
        mri = {n for b in bone_names if b in bones for n in bones[b].landmarks if n in wanted}
        lab_names = [n for n in wanted if n in static]
        if not mri and not lab_names:
            continue
        corr = _segment_correspondences(bones, bone_names, wanted, static, surfaces, normals, skin_thickness, skin_sd,
                                        marker_radius, (virtual or {}).get(seg_name, {}))
        if len(corr) < 3:
            missing_mri = [n for n in wanted if n not in mri]
            missing_lab = [n for n in wanted if n not in static]
            problem = (f"segment {seg_name} has {len(corr)} usable landmark/marker pairs ({', '.join(corr.names) or 'none'}), "
                       f"needs 3; missing in MRI: {', '.join(missing_mri) or 'none'}, missing in static trial: "
                       f"{', '.join(missing_lab) or 'none'}")
            if on_missing == "skip":
                out.skipped[seg_name] = problem
                continue
            raise InputError(tsrc if len(mri) >= 3 else landmarks_source, problem)
        reg = corr.register(seg_name, k_outlier=k_outlier, tissue_prior=tissue_prior)
        if reg.tissue_scale is not None and surfaces is not None and normals is None:
            # the normals' averaging radius follows the tissue: once its scale is estimated, fit again with it
            corr = _segment_correspondences(bones, bone_names, wanted, static, surfaces, normals, skin_thickness,
                                            skin_sd, marker_radius, (virtual or {}).get(seg_name, {}),
                                            tissue_scale=reg.tissue_scale)
            reg = corr.register(seg_name, k_outlier=k_outlier, tissue_prior=tissue_prior)
        out[seg_name] = reg
    return out
