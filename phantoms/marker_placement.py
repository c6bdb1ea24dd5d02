"""Markers placed on a real-anatomy phantom: bony landmarks, skin thickness by body build, palpation error.

Bony landmarks (`find_landmarks`) are extremal points of the meshes in the
standing pose, the way they are palpated (model ground: X forward, Y up,
Z right; "lateral" is +Z on the right, -Z on the left):

* ASI / PSI: most anterior / posterior pelvis vertex of each side above the
  hip centres (+30 mm) in the expert pelvis frame (PSI at least 15 mm from the
  midline);
* TRO: most lateral femur vertex from 100 mm below to 50 mm above the hip centre;
* KNE / MFC: femur vertices within 50 mm above the knee centre, extreme along the
  expert's knee axis (lateral / medial epicondyle);
* TTB (tibial tuberosity): most anterior tibia vertex 20-90 mm below the knee centre;
* HFB: most lateral fibula vertex within 70 mm below the knee centre;
* ANK / MMA: fibula / tibia vertices within 40-50 mm above the ankle centre,
  extreme along the expert's ankle axis (lateral / medial malleolus);
* HEE: most posterior calcaneus vertex; LCA: most lateral in its posterior quarter;
  D1M / D5M: most medial / lateral in the anterior 20 % of the foot (metatarsal
  heads); P1M / P5M: most medial / lateral in 50-70 % of the foot length
  (metatarsal bases); TOE: most dorsal vertex over the second metatarsal head (anterior 8 %, 20-45 %
  of the way across the forefoot).

Marker centre = surface point + (skin thickness + marker radius) x outward normal
(normal: mean vertex normal within max(6 mm, skin thickness) of the surface point:
fat over a prominence smooths it at the scale of its own thickness, so 40 mm of
tissue over the ASIS lies along the iliac crest's broad normal, not along one
6 mm facet of the spine's tip, which palpation's few millimetres swing by 30-50 deg).  The anatomical (bony) markers are
first displaced tangentially by a palpation error and re-projected onto the
bone (nearest vertex).  Skin markers without a landmark (thigh and shank
wands, SHN, clusters, gait2392's thigh/shank markers) sit at a fraction of
the segment, at the bone's radius in their direction plus the segment's soft
tissue; CAST clusters are rigid four-marker plates 15 mm off the skin.

Soft-tissue prior by body build (`TISSUE_CLASSES`; mean, sd in mm, log-normal draws)
----------------------------------------------------------------------------------
adult ASIS 9.7 +- 7.0, PSIS 19.6 +- 10.9: Mantovani, Ng & Lamontagne 2016
(Gait Posture 44:48, pelvic CT, n = 67), tissue correlated with BMI; obese
ASIS 30 +- 8, PSIS 40 +- 10 (the upper part of that distribution and beyond:
subcutaneous fat over the iliac crest exceeds 3-4 cm at BMI > 30);
child ASIS 6 +- 3, PSIS 12 +- 5.  Greater trochanter, thigh and shank soft
tissue and the thin sites (epicondyles, malleoli, foot) are ASSUMED values,
scaled by build.

Palpation error (`PALPATION_SD_MM`)
-----------------------------------
Per-site sd of the tangential misplacement, 5-15 mm, within the inter-examiner
dispersion measured by Della Croce, Cappozzo & Kerrigan 1999 (Med Biol Eng
Comput 37:155, pelvis and lower-limb landmarks, rms 6-21 mm, largest at the
greater trochanter and the epicondyles) and reviewed by Della Croce et al. 2005
(Gait Posture 21:226): 5 mm on sharp, subcutaneous points (malleoli, metatarsal
heads), 15 mm at the greater trochanter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS
from kinematics.io.marker_sets import MarkerSet

__all__ = ["TISSUE_CLASSES", "PALPATION_SD_MM", "PlacedMarker", "find_landmarks",
           "place_markers", "draw_tissue", "skin_normal", "NORMAL_RADIUS_MIN"]

_MANTOVANI = "Mantovani, Ng & Lamontagne 2016, Gait Posture 44:48"
#: body build -> site -> (mean mm, sd mm); "thigh"/"shank": soft tissue of the skin (non-bony) markers
TISSUE_CLASSES = {
    "child": {"ASI": (6.0, 3.0), "PSI": (12.0, 5.0), "TRO": (12.0, 5.0), "thigh": (20.0, 6.0), "shank": (8.0, 3.0),
              "KNE": (3.0, 1.5), "MFC": (3.0, 1.5), "TTB": (2.0, 1.0), "HFB": (3.0, 1.5), "ANK": (2.0, 1.0),
              "MMA": (2.0, 1.0), "HEE": (5.0, 2.0), "foot": (2.0, 1.0)},
    "adult": {"ASI": (9.7, 7.0), "PSI": (19.6, 10.9), "TRO": (25.0, 10.0), "thigh": (35.0, 10.0), "shank": (12.0, 4.0),
              "KNE": (5.0, 3.0), "MFC": (5.0, 3.0), "TTB": (3.0, 1.5), "HFB": (5.0, 2.0), "ANK": (3.0, 2.0),
              "MMA": (3.0, 2.0), "HEE": (6.0, 3.0), "foot": (3.0, 2.0)},
    "obese": {"ASI": (30.0, 8.0), "PSI": (40.0, 10.0), "TRO": (50.0, 12.0), "thigh": (65.0, 15.0), "shank": (22.0, 6.0),
              "KNE": (10.0, 4.0), "MFC": (12.0, 5.0), "TTB": (5.0, 2.0), "HFB": (8.0, 3.0), "ANK": (5.0, 2.0),
              "MMA": (5.0, 2.0), "HEE": (9.0, 3.0), "foot": (5.0, 2.0)},
}
TISSUE_SOURCES = {"ASI": _MANTOVANI, "PSI": _MANTOVANI}
#: palpation sd (mm) of the tangential misplacement per landmark (Della Croce et al. 1999, 2005)
PALPATION_SD_MM = {"ASI": 8.0, "PSI": 10.0, "TRO": 15.0, "KNE": 10.0, "MFC": 10.0, "TTB": 7.0, "HFB": 9.0,
                   "ANK": 5.0, "MMA": 5.0, "HEE": 8.0, "LCA": 8.0, "D1M": 5.0, "D5M": 5.0, "P1M": 7.0, "P5M": 7.0,
                   "TOE": 6.0}
#: marker base name -> landmark it sits on (placement; see the module docstring)
_ON_LANDMARK = {"ASI": "ASI", "PSI": "PSI", "TRO": "TRO", "KNE": "KNE", "MFC": "MFC", "TUB": "TTB", "HFB": "HFB",
                "ANK": "ANK", "MMA": "MMA", "HEE": "HEE", "LCA": "LCA", "P1M": "P1M", "P5M": "P5M", "D1M": "D1M",
                "D5M": "D5M", "TOE": "TOE", "ASIS": "ASI", "Knee.Lat": "KNE", "Knee.Med": "MFC", "Ankle.Lat": "ANK",
                "Ankle.Med": "MMA", "Heel": "HEE", "Toe.Lat": "D5M", "Toe.Med": "D1M", "Midfoot.Lat": "P5M",
                "Midfoot.Sup": "MFS", "Toe.Tip": "TIP"}
#: skin markers: base name -> (segment, fraction from the distal joint, direction: angle from lateral
#: towards anterior in deg)
_SKIN = {"SHN": ("tibia", 0.5, 30.0),
         "Thigh.Upper": ("femur", 0.6, 0.0), "Thigh.Front": ("femur", 0.45, 90.0), "Thigh.Rear": ("femur", 0.3, -45.0),
         "Shank.Upper": ("tibia", 0.8, 0.0), "Shank.Front": ("tibia", 0.65, 90.0), "Shank.Rear": ("tibia", 0.55, -45.0)}
#: Plug-in-Gait's wand markers, placed as its protocol asks (`_pig_wand`), not as plain skin markers
_PIG_WANDS = {"THI": "femur", "TIB": "tibia"}
#: shortest distance (m) of a wand marker's skin point from the line its plane is spanned from (a wand, or the
#: shank's lateral bulk, keeps Plug-in-Gait's chord off a degenerate plane)
PIG_WAND_MIN_OFFSET = 0.03
#: rigid clusters: prefix -> (segment, fraction, direction deg); corners (long, tangential) m
_CLUSTERS = {"TH": ("femur", 0.5, 30.0), "SH": ("tibia", 0.5, 30.0)}
_CORNERS = ((0.045, 0.03), (0.045, -0.03), (-0.035, -0.03), (-0.045, 0.035))


def draw_tissue(rng: np.random.Generator, build: str, site: str) -> float:
    """One subject's skin-to-bone thickness (m) at `site` for body build `build` (log-normal, table mean/sd)."""
    if build not in TISSUE_CLASSES:
        raise InputError("--tissue", f"{build!r} is not one of {', '.join(TISSUE_CLASSES)}")
    table = TISSUE_CLASSES[build]
    key = site if site in table else ("foot" if site in ("LCA", "D1M", "D5M", "P1M", "P5M", "TOE", "MFS", "TIP")
                                      else "KNE")
    mean, sd = (x * 1e-3 for x in table[key])
    s2 = np.log1p((sd / mean) ** 2)
    return float(np.exp(np.log(mean) - 0.5 * s2 + np.sqrt(s2) * rng.standard_normal()))


@dataclass(frozen=True)
class PlacedMarker:
    """A marker fixed on a body (local frame, m) and how it got there (for truth.json)."""

    label: str
    body: str
    offset: np.ndarray
    kind: str                     # "landmark", "skin", "cluster", "virtual"
    landmark: str | None = None
    landmark_local: np.ndarray | None = None
    surface_local: np.ndarray | None = None
    normal_local: np.ndarray | None = None
    thickness: float = 0.0
    palpation_offset: np.ndarray | None = None

    def to_json(self) -> dict:
        f = lambda v: None if v is None else [float(x) for x in v]  # noqa: E731
        return {"body": self.body, "offset_m": f(self.offset), "kind": self.kind, "landmark": self.landmark,
                "landmark_body_m": f(self.landmark_local), "surface_point_body_m": f(self.surface_local),
                "normal_body": f(self.normal_local), "thickness_m": float(self.thickness),
                "palpation_offset_m": f(self.palpation_offset),
                "palpation_error_m": None if self.palpation_offset is None else float(np.linalg.norm(self.palpation_offset))}


class _Standing:
    """Body poses and joint frames of the standing pose in the model ground frame."""

    def __init__(self, anat, q):
        from kinematics.algorithms.fk import forward_kinematics

        self.anat, self.model = anat, anat.model
        st = forward_kinematics(self.model, q)
        self.R = {b: st.rotations[0, i] for i, b in enumerate(self.model.body_names)}
        self.p = {b: st.positions[0, i] for i, b in enumerate(self.model.body_names)}
        self.joint = {}
        for j in self.model.joints:
            T = j.parent_offset
            self.joint[j.name] = (self.R[j.parent] @ T.translation + self.p[j.parent], self.R[j.parent] @ T.rotation)

    def verts(self, bone):
        b = self.anat.bone_body[bone]
        return np.asarray(self.anat.local_meshes[bone].vertices) @ self.R[b].T + self.p[b]

    def to_local(self, body, x):
        return self.R[body].T @ (np.asarray(x, float) - self.p[body])

    def to_ground(self, body, x):
        return self.R[body] @ np.asarray(x, float) + self.p[body]

    def dir_local(self, body, v):
        return self.R[body].T @ np.asarray(v, float)


#: m, smallest radius over which a bony marker's offset direction is averaged (the marker's own footprint)
NORMAL_RADIUS_MIN = 0.006


def skin_normal(mesh, p_local: np.ndarray, radius: float = NORMAL_RADIUS_MIN) -> np.ndarray:
    """Outward unit normal of `mesh` at `p_local`: its vertex normals averaged within `radius` (m; the 8 nearest
    vertices when fewer than 3 lie there), the direction a marker over that point is offset along."""
    V = np.asarray(mesh.vertices)
    N = np.asarray(mesh.vertex_normals)
    near = np.linalg.norm(V - p_local, axis=1) < radius
    if near.sum() < 3:
        near = np.argsort(np.linalg.norm(V - p_local, axis=1))[:8]
    n = N[near].sum(axis=0)
    n /= np.linalg.norm(n)
    # vertex normals follow the face winding: an inward-wound mesh has a negative signed volume.  (Testing
    # against the direction from the bone's centroid flips correct normals near the ends of long bones: the
    # lateral malleolus's marker went 15 mm into the ankle.)
    return -n if mesh.volume < 0 else n


def find_landmarks(anat, q_standing) -> dict:
    """Bony landmarks (see the module docstring): ``"RASI" -> (bone, point (3,) in its body's local frame)``."""
    S = _Standing(anat, q_standing)
    A, U = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    out = {}

    def put(name, bone, pts, i):
        out[name] = (bone, S.to_local(anat.bone_body[bone], pts[i]))

    gp = next(j for j in anat.model.joints if j.parent == "ground")
    Rp, op = S.R["pelvis"] @ gp.child_offset.rotation, S.to_ground("pelvis", gp.child_offset.translation)
    Vg = S.verts("pelvis")
    Vp = (Vg - op) @ Rp                                    # pelvis frame: x anterior, y up, z right
    for s in anat.sides:
        P, sg = s.upper(), (1.0 if s == "r" else -1.0)
        lat = sg * np.array([0, 0, 1.0])
        h = (S.joint[f"hip_{s}"][0] - op) @ Rp
        side = (Vp[:, 2] * sg > 0.02) & (Vp[:, 1] > h[1] + 0.03)
        i = np.flatnonzero(side)
        put(f"{P}ASI", "pelvis", Vg, i[np.argmax(Vp[i, 0])])
        i = np.flatnonzero(side & (Vp[:, 2] * sg > 0.015))
        put(f"{P}PSI", "pelvis", Vg, i[np.argmin(Vp[i, 0])])
        H, K = S.joint[f"hip_{s}"][0], S.joint[f"knee_{s}"][0]
        Ak = S.joint[f"ankle_{s}"][0]
        F = S.verts(f"femur_{s}")
        i = np.flatnonzero((F[:, 1] > H[1] - 0.10) & (F[:, 1] < H[1] + 0.05))
        put(f"{P}TRO", f"femur_{s}", F, i[np.argmax(F[i] @ lat)])
        k = S.joint[f"knee_{s}"][1][:, 2]
        k = k if k @ lat > 0 else -k
        i = np.flatnonzero(F[:, 1] < K[1] + 0.05)
        put(f"{P}KNE", f"femur_{s}", F, i[np.argmax(F[i] @ k)])
        put(f"{P}MFC", f"femur_{s}", F, i[np.argmin(F[i] @ k)])
        T = S.verts(f"tibia_{s}")
        i = np.flatnonzero((T[:, 1] < K[1] - 0.02) & (T[:, 1] > K[1] - 0.09))
        put(f"{P}TTB", f"tibia_{s}", T, i[np.argmax(T[i] @ A)])
        Fi = S.verts(f"fibula_{s}")
        i = np.flatnonzero(Fi[:, 1] > K[1] - 0.07)
        put(f"{P}HFB", f"fibula_{s}", Fi, i[np.argmax(Fi[i] @ lat)])
        a = S.joint[f"ankle_{s}"][1][:, 2]
        a = a if a @ lat > 0 else -a
        i = np.flatnonzero(Fi[:, 1] < Ak[1] + 0.04)
        put(f"{P}ANK", f"fibula_{s}", Fi, i[np.argmax(Fi[i] @ a)])
        i = np.flatnonzero(T[:, 1] < Ak[1] + 0.05)
        put(f"{P}MMA", f"tibia_{s}", T, i[np.argmin(T[i] @ a)])
        C = S.verts(f"calcn_{s}")
        ctr = C - C.mean(axis=0)
        _, _, Vt = np.linalg.svd(ctr[:, [0, 2]], full_matrices=False)
        f = np.array([Vt[0, 0], 0.0, Vt[0, 1]])
        f = f if f @ A > 0 else -f
        fl = np.cross(f, U) * sg                            # foot lateral
        af, lf = C @ f, C @ fl
        amin, amax = af.min(), af.max()
        L = amax - amin
        put(f"{P}HEE", f"calcn_{s}", C, int(np.argmin(af)))
        i = np.flatnonzero(af < amin + 0.25 * L)
        put(f"{P}LCA", f"calcn_{s}", C, i[np.argmax(lf[i])])
        i = np.flatnonzero(af > amax - 0.2 * L)
        put(f"{P}D1M", f"calcn_{s}", C, i[np.argmin(lf[i])])
        put(f"{P}D5M", f"calcn_{s}", C, i[np.argmax(lf[i])])
        lo_l, hi_l = lf[i].min(), lf[i].max()
        # over the second metatarsal head: the front 8 % (the heads; the most dorsal vertex of the front 20 %
        # was 25 mm behind them, on the shafts), a fifth to under half of the way across the forefoot
        k = np.flatnonzero(af > amax - 0.08 * L)
        j = k[(lf[k] > lo_l + 0.2 * (hi_l - lo_l)) & (lf[k] < lo_l + 0.45 * (hi_l - lo_l))]
        j = j if j.size else i
        put(f"{P}TOE", f"calcn_{s}", C, j[np.argmax(C[j, 1])])
        i = np.flatnonzero((af > amin + 0.5 * L) & (af < amin + 0.7 * L))
        put(f"{P}P1M", f"calcn_{s}", C, i[np.argmin(lf[i])])
        put(f"{P}P5M", f"calcn_{s}", C, i[np.argmax(lf[i])])
        i = np.flatnonzero((af > amin + 0.55 * L) & (af < amin + 0.7 * L))
        put(f"{P}MFS", f"calcn_{s}", C, i[np.argmax(C[i, 1])])
        tb = f"toes_{s}" if f"toes_{s}" in anat.meshes else f"calcn_{s}"
        Tt = S.verts(tb)
        put(f"{P}TIP", tb, Tt, int(np.argmax(Tt @ f)))
    return out


def _segment_axis(S, seg, s):
    if seg == "femur":
        prox, dist = S.joint[f"hip_{s}"][0], S.joint[f"knee_{s}"][0]
    else:
        prox, dist = S.joint[f"knee_{s}"][0], S.joint[f"ankle_{s}"][0]
    return prox, dist


def _skin_point(S, anat, seg, s, frac, angle_deg, soft):
    """Skin point, outward direction (model ground) at `frac` from the distal joint, `angle_deg` from lateral."""
    prox, dist = _segment_axis(S, seg, s)
    z = (prox - dist) / np.linalg.norm(prox - dist)
    sg = 1.0 if s == "r" else -1.0
    lat = np.array([0, 0, sg])
    lat = lat - (lat @ z) * z
    lat /= np.linalg.norm(lat)
    ant = np.cross(lat, z) * sg
    ant = ant if ant[0] > 0 else -ant
    th = np.radians(angle_deg)
    d = np.cos(th) * lat + np.sin(th) * ant
    c = dist + frac * (prox - dist)
    bone = f"{seg}_{s}"
    V = S.verts(bone)
    rel = V - c
    along = rel @ z
    perp = rel - np.outer(along, z)
    r = np.linalg.norm(perp, axis=1)
    ok = (np.abs(along) < 0.01) & (perp @ d > 0.9 * r)
    radius = float((perp[ok] @ d).max()) if ok.any() else 0.02
    return c + (radius + soft) * d, d, z


def _pig_wand(S, anat, s, seg, soft, marker):
    """Skin point and outward direction (model ground) of Plug-in-Gait's THI or TIB wand marker, aimed at the
    KNE or ANK marker centre `marker` (ground, m).

    Plug-in-Gait's chord (`kinematics.gait.pig.chord_joint_centre`) puts the knee (ankle) centre in the plane
    of the wand, the proximal centre and the KNE (ANK) marker: the wand is aimed, as its protocol asks (Davis et
    al. 1991), so that this plane holds the joint centres' line and the lateral marker as placed (palpation
    error and all).  THI sits at the lower third of the thigh, TIB at the lower third of the shank, each on the
    joint centres' line turned towards its KNE (ANK) marker, at the skin over the bone (femur; tibia and
    fibula), at least `PIG_WAND_MIN_OFFSET` from the line; tibial torsion 0 in subject.json, as most labs
    leave it.  Set straight lateral in the ground instead, TIB sat anterior of the knee-ANK line (the
    malleolus lies postero-lateral) and the chord put the ankle centre 75-80 mm off; aimed along the flexion
    axes instead of the markers (the epicondyle is not on the knee axis), the knee centre 13-30 mm.
    """
    prox, dist = (f"hip_{s}", f"knee_{s}") if seg == "femur" else (f"knee_{s}", f"ankle_{s}")
    Pj, Dj = S.joint[prox][0], S.joint[dist][0]
    z = (Pj - Dj) / np.linalg.norm(Pj - Dj)
    d = (marker - Dj) - ((marker - Dj) @ z) * z
    d /= np.linalg.norm(d)
    base = Dj + 0.33 * (Pj - Dj)
    V = np.vstack([S.verts(f"{b_}_{s}") for b_ in ((seg,) if seg == "femur" else ("tibia", "fibula"))
                   if f"{b_}_{s}" in anat.local_meshes])
    rel = V - base
    near = np.abs(rel @ z) < 0.01
    reach = float((rel[near] @ d).max()) if near.any() else 0.0
    return base + max(reach + soft, PIG_WAND_MIN_OFFSET) * d, d


def place_markers(anat, q_standing, marker_set: MarkerSet, build: str, seed: int, *, palpation: bool = True):
    """Place every marker of `marker_set` on `anat` (standing pose `q_standing`).

    Markers whose segment is ``torso``/``ignore`` or not a body of the model are skipped.

    Returns
    -------
    dict label -> `PlacedMarker`; dict site -> thickness (m) drawn for this subject
    """
    if build not in TISSUE_CLASSES:
        raise InputError("--tissue", f"{build!r} is not one of {', '.join(TISSUE_CLASSES)}")
    S = _Standing(anat, q_standing)
    lms = find_landmarks(anat, q_standing)
    rng = np.random.default_rng([int(seed), 41])
    tissue: dict[str, float] = {}

    def t_of(site, s=""):
        key = f"{site}" if site in ("ASI", "PSI") else f"{s}{site}"   # pelvis sites shared by both sides
        if key not in tissue:
            tissue[key] = draw_tissue(rng, build, site)
        return tissue[key]

    placed: dict[str, PlacedMarker] = {}
    bodies = set(anat.model.body_names)
    r = DEFAULT_MARKER_RADIUS
    clusters: dict[tuple, dict] = {}
    deferred, wands = [], []
    for label, md in marker_set.markers.items():
        if md.segment not in bodies:
            continue
        side = md.segment[-1] if md.segment[-2:] in ("_r", "_l") else None
        if label.startswith(("R.", "L.")):
            base, S_ = label[2:], label[0]
        elif label[0] in "RL" and len(label) > 1:
            base, S_ = label[1:], label[0]
        else:
            base, S_ = label, None
        s = (S_ or "R").lower() if side is None else side
        P = s.upper()
        if base in _ON_LANDMARK:
            site = _ON_LANDMARK[base]
            bone, p_loc = lms[f"{P}{site}"]
            body = anat.bone_body[bone]
            mesh = anat.local_meshes[bone]
            n = skin_normal(mesh, p_loc)
            off = np.zeros(3)
            surf = p_loc
            sd = PALPATION_SD_MM.get(site, 0.0) * 1e-3 if palpation else 0.0
            if sd > 0:
                tang = rng.normal(scale=sd / np.sqrt(2.0), size=3)   # rms of the 2-D misplacement = sd
                tang -= (tang @ n) * n
                V = np.asarray(mesh.vertices)
                k = int(np.argmin(np.linalg.norm(V - (p_loc + tang), axis=1)))
                surf = V[k].copy()
                off = surf - p_loc
            t = t_of(site, P)
            # the skin over a prominence follows the bone at the scale of the tissue between them, not a facet's
            n = skin_normal(mesh, surf, radius=max(NORMAL_RADIUS_MIN, t))
            placed[label] = PlacedMarker(label, body, surf + (t + r) * n, "landmark", md.landmark or f"{P}{site}",
                                         p_loc, surf, n, t, off)
        elif base in _PIG_WANDS:
            wands.append((label, base, s))       # aimed at the KNE / ANK marker: placed after it
        elif base in _SKIN:
            seg, frac, ang = _SKIN[base]
            t = t_of("thigh" if seg == "femur" else "shank", P)
            x, d, _ = _skin_point(S, anat, seg, s, frac, ang, t)
            body = f"{seg}_{s}"
            placed[label] = PlacedMarker(label, body, S.to_local(body, x + r * d), "skin", None, None,
                                         S.to_local(body, x), S.dir_local(body, d), t, None)
        elif base[:2] in _CLUSTERS and base[2:].isdigit():
            clusters.setdefault((base[:2], s), {})[int(base[2:])] = label
        elif base.endswith("Sacral"):
            deferred.append(label)
    for (pre, s), members in clusters.items():
        seg, frac, ang = _CLUSTERS[pre]
        t = t_of("thigh" if seg == "femur" else "shank", s.upper())
        x, d, z = _skin_point(S, anat, seg, s, frac, ang, t)
        tang = np.cross(z, d)
        body = f"{seg}_{s}"
        for k, label in members.items():
            lo, ta = _CORNERS[(k - 1) % 4]
            pos = x + (0.015 + r) * d + lo * z + ta * tang
            placed[label] = PlacedMarker(label, body, S.to_local(body, pos), "cluster", None, None,
                                         S.to_local(body, x), S.dir_local(body, d), t, None)
    for label, base, s in wands:
        seg = _PIG_WANDS[base]
        P = s.upper()
        t = t_of("thigh" if seg == "femur" else "shank", P)
        aim = f"{P}{'KNE' if seg == 'femur' else 'ANK'}"
        if aim in placed:
            m = placed[aim]
            aim_at = S.to_ground(m.body, m.offset)
        else:                                    # no such marker in the set: its landmark
            bone, p_loc = lms[aim]
            b = anat.bone_body[bone]
            aim_at = S.to_ground(b, p_loc + (t_of(aim[1:], P) + r) * skin_normal(anat.local_meshes[bone], p_loc))
        x, d = _pig_wand(S, anat, s, seg, t, aim_at)
        body = f"{seg}_{s}"
        placed[label] = PlacedMarker(label, body, S.to_local(body, x + r * d), "skin", None, None,
                                     S.to_local(body, x), S.dir_local(body, d), t, None)
    for label in deferred:        # V.Sacral: midway between the PSIS, over the sacrum
        ps = [lms[f"{P}PSI"][1] for P in ("R", "L")]
        mid = 0.5 * (ps[0] + ps[1])
        gp = next(j for j in anat.model.joints if j.parent == "ground")
        back = -gp.child_offset.rotation[:, 0]
        t = t_of("PSI")
        placed[label] = PlacedMarker(label, "pelvis", mid + (t + r) * back, "skin", None, None, mid, back, t, None)
    return placed, tissue
