"""The generic bones registered to the subject's, per body: the map that carries muscle points across.

For each body, the generic bone surface ``G`` (gait2392's meshes, its body frame) is registered to the subject's
bone surface ``S`` (the personalised body frame), both in metres:

1. start: the similarity ``x' = s R x + t`` that puts the body's generic joint centres on the subject's
   (`GenericModel.joint_points`; two joints: ``s`` their distances' ratio, ``R`` the least rotation turning one
   joint-to-joint line into the other, the mid-points matched; one joint: the neighbour's scale, no turn);
2. similarity ICP (Umeyama 1991's closed form on nearest-neighbour pairs taken both ways, G -> S and S -> G,
   pairs farther than ``max(3 median, 2 mm)`` dropped, so that a bone present in one set only, e.g. a sacrum,
   does not pull);
3. affine ICP: the same pairs, ``x' = A x + t`` by least squares, kept only when it lowers the symmetric mean
   surface distance by `AFFINE_GAIN` or more (an affine map follows a bone that is longer than it is wide in
   other proportions than the generic one).

`BoneMap` maps points (path points), directions and frames (wrap objects).  The distances it reports are the
symmetric mean nearest-neighbour distance of surface samples (mm).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["BoneMap", "register_bone", "register_bodies", "landmark_pairs", "similarity_from_joints", "umeyama",
           "surface_samples", "AFFINE_GAIN", "BORROWED", "MIN_LANDMARKS", "fit_twist", "twist_points",
           "twist_rotation", "TWIST_BODIES", "LANDMARK_BODIES"]

#: least relative gain in mean surface distance for the affine map to replace the similarity
AFFINE_GAIN = 0.05
#: surface samples per bone
N_SAMPLES = 4000
#: largest stretch of the affine map against the similarity's scale (singular values within [1/x, x])
AFFINE_STRETCH = 1.25
#: largest change of scale ICP may make from the start's (beyond it the start is kept)
MAX_SCALE_CHANGE = 1.2
#: share of the ICP's weight the joint-centre landmarks carry together
LANDMARK_SHARE = 0.2
#: joints whose centres are points on both models (the subtalar and mtp joints' are points on their axes only)
CENTRE_JOINTS = ("hip", "knee", "ankle")
#: least number of anatomical landmark pairs for a landmark start (a similarity needs three points off one line)
MIN_LANDMARKS = 3
#: bodies registered from their anatomical landmarks (`landmark_pairs`); the femur keeps the joint-centre start
#: and its own surface: on the ICL-MRI benchmark its landmarks on gait2392's coarse femur (456 vertices; trochanter
#: 7 mm, neck-shaft point 12 mm residuals) turned the proximal femur so that 67 % of the hip flexion moment arms
#: were within 15 % against 81 % from the surface
LANDMARK_BODIES = ("pelvis", "tibia", "talus", "calcn", "toes")
#: landmarks that are the joint centres the moment arms are taken about (the hip's: gait2392's and the subject's
#: hip centres are both the femoral head's centre), weighing `CENTRE_WEIGHT` times another landmark
CENTRE_LANDMARKS = ("acetabulum_centre_r", "acetabulum_centre_l", "femoral_head_centre")
CENTRE_WEIGHT = 5.0
#: long bones whose torsion the map follows (`fit_twist`), axis between their two joint centres
TWIST_BODIES = ("tibia",)
#: largest torsion a twist may take between a long bone's joints (deg)
MAX_TWIST_DEG = 60.0
#: body base name -> (parent body base name, the parent's landmarks that also place the body): the toes, which
#: carry no landmark of their own, by the metatarsal heads they articulate with
BORROWED = {"toes": ("calcn", ("met1_head_centre", "met5_head_centre"))}


def twist_points(x, twist) -> np.ndarray:
    """Points (..., 3) twisted about an axis: ``w(x) = c + R_u(κ (x - c)·u) (x - c)``, the rotation about the unit
    axis u through c by κ radians per metre along it (a bone's torsion); twist None: x unchanged.

    twist : (c (3,) m, u (3,), κ rad/m)
    """
    x = np.asarray(x, float)
    if twist is None:
        return x
    c, u, k = np.asarray(twist[0], float), np.asarray(twist[1], float), float(twist[2])  # (c, u, κ[, length])
    d = x - c
    a = k * (d @ u)
    ca, sa = np.cos(a)[..., None], np.sin(a)[..., None]
    # Rodrigues: R d = d cos a + (u x d) sin a + u (u·d)(1 - cos a)
    return c + d * ca + np.cross(u, d) * sa + u * (d @ u)[..., None] * (1.0 - ca)


def twist_rotation(x, twist) -> np.ndarray:
    """The twist's rotation (3, 3) at point x (the turn about u by ``κ (x - c)·u``); identity without a twist."""
    from scipy.spatial.transform import Rotation

    if twist is None:
        return np.eye(3)
    c, u, k = (np.asarray(v, float) for v in twist[:3])
    return Rotation.from_rotvec(u * float(k) * float((np.asarray(x, float) - c) @ u)).as_matrix()


@dataclass(frozen=True)
class BoneMap:
    """A body's map from the generic body frame to the personalised body frame, ``x' = A w(x) + t`` (m), w the
    bone's torsion (`twist_points`; identity for most bones).

    body : body name; A : (3, 3); t : (3,); kind : "joints" (the start only: landmark or joint-centre
    similarity), "similarity" or "affine"; distances_mm : {"joints" | "similarity" | "affine": symmetric mean
    surface distance, mm}; landmarks_mm : {landmark: |A g + t - q|, mm} over the registration's pairs
    """

    body: str
    A: np.ndarray
    t: np.ndarray
    kind: str
    distances_mm: dict = field(default_factory=dict)
    landmarks_mm: dict = field(default_factory=dict)
    twist: tuple | None = None

    def __call__(self, x) -> np.ndarray:
        """Mapped points: (..., 3) -> (..., 3)."""
        return twist_points(x, self.twist) @ self.A.T + self.t

    @property
    def twist_deg(self) -> float:
        """The torsion over the twist axis's length between the body's joints (deg; 0 without a twist)."""
        return 0.0 if self.twist is None else float(np.degrees(self.twist[2] * self.twist[3]))

    @property
    def scale(self) -> float:
        """Mean linear scale, ``det(A)^(1/3)``."""
        return float(np.cbrt(abs(np.linalg.det(self.A))))

    def frame(self, R, at=None) -> tuple[np.ndarray, np.ndarray]:
        """A frame's axes carried across at point `at` (generic frame; the twist's turn there, none if None):
        (rotation (3, 3), stretch (3,)) with ``A T R = R' diag(stretch)`` up to shear, T the twist's rotation at
        `at`: R' the orthonormal polar factor of ``A T R``, stretch the lengths of its columns."""
        T = np.eye(3) if at is None else twist_rotation(at, self.twist)
        M = self.A @ T @ np.asarray(R, float)
        U, _, Vt = np.linalg.svd(M)
        Rn = U @ Vt
        if np.linalg.det(Rn) < 0:
            U[:, -1] *= -1
            Rn = U @ Vt
        return Rn, np.linalg.norm(M, axis=0)

    def to_json(self) -> dict:
        return {"body": self.body, "kind": self.kind, "A": self.A.tolist(), "t": self.t.tolist(),
                "scale": round(self.scale, 4), "surface_distance_mm": {k: round(v, 2) for k, v in self.distances_mm.items()},
                "landmark_residual_mm": dict(self.landmarks_mm),
                "twist": None if self.twist is None else {"point": np.round(self.twist[0], 6).tolist(),
                                                          "axis": np.round(self.twist[1], 6).tolist(),
                                                          "rad_per_m": round(float(self.twist[2]), 4),
                                                          "deg_between_joints": round(self.twist_deg, 2)}}


def umeyama(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None,
            scaling: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted least-squares similarity Q ≈ s R P + t (Umeyama 1991): (s, R (3, 3), t (3,)).

    P, Q : (n, 3); w : (n,) non-negative weights (None: equal), minimising Σ w_i |Q_i - s R P_i - t|².
    """
    w = np.ones(len(P)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    mp, mq = w @ P, w @ Q
    X, Y = P - mp, Q - mq
    U, S, Vt = np.linalg.svd((Y * w[:, None]).T @ X)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (w @ (X**2).sum(1))) if scaling else 1.0
    return s, R, mq - s * R @ mp


def _least_rotation(u, v) -> np.ndarray:
    """The least rotation turning direction u into direction v."""
    from scipy.spatial.transform import Rotation

    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    ax = np.cross(u, v)
    sn, cs = float(np.linalg.norm(ax)), float(u @ v)
    return np.eye(3) if sn < 1e-12 else Rotation.from_rotvec(ax / sn * np.arctan2(sn, cs)).as_matrix()


def similarity_from_joints(generic: dict, subject: dict, scale: float | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """(A, t) putting the generic joint points on the subject's (joint name -> (3,) m, shared names; see the module
    docstring, step 1); None without a shared joint (or one joint and no `scale`)."""
    names = sorted(set(generic) & set(subject))
    if len(names) >= 2:
        a, b = names[:2]
        u, v = generic[b] - generic[a], subject[b] - subject[a]
        s = float(np.linalg.norm(v) / np.linalg.norm(u))
        R = _least_rotation(u, v)
        gm, sm = 0.5 * (generic[a] + generic[b]), 0.5 * (subject[a] + subject[b])
    elif names and scale is not None:
        s, R = float(scale), np.eye(3)
        gm, sm = generic[names[0]], subject[names[0]]
    else:
        return None
    A = s * R
    return A, sm - A @ gm


def surface_samples(mesh, n: int = N_SAMPLES, seed: int = 0) -> np.ndarray:
    """(n, 3) points spread evenly over a trimesh surface (area-weighted, fixed seed), with the vertices when fewer."""
    import trimesh

    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts, float)


def _pairs(X, Y, tX: cKDTree, tY: cKDTree):
    """Nearest-neighbour pairs both ways between X (mapped generic) and Y (subject), trimmed (module docstring)."""
    dY, iY = tY.query(X)
    dX, iX = tX.query(Y)
    d = np.concatenate([dY, dX])
    keep = d <= max(3.0 * np.median(d), 2e-3)
    src = np.concatenate([np.arange(len(X)), iX])[keep]
    dst = np.concatenate([iY, np.arange(len(Y))])[keep]
    return src, dst


def _distance(X, Y) -> float:
    """Symmetric mean nearest-neighbour distance (m)."""
    return 0.5 * float(cKDTree(Y).query(X)[0].mean() + cKDTree(X).query(Y)[0].mean())


def _icp(P, Y, A, t, affine: bool, landmarks=(), landmark_share: float | None = None, iterations: int = 40):
    """Trimmed two-way ICP from generic samples P to subject samples Y, starting at (A, t); `landmarks`, pairs
    (generic point, subject point), weigh `landmark_share` of the total together."""
    landmark_share = LANDMARK_SHARE if landmark_share is None else landmark_share
    tY = cKDTree(Y)
    L = np.array([p[0] for p in landmarks], float).reshape(-1, 3)
    M = np.array([p[1] for p in landmarks], float).reshape(-1, 3)
    rel = np.array([p[2] if len(p) > 2 else 1.0 for p in landmarks], float)
    for _ in range(iterations):
        X = P @ A.T + t
        src, dst = _pairs(X, Y, cKDTree(X), tY)
        if len(src) < 12:
            break
        S, Q = np.vstack([P[src], L]), np.vstack([Y[dst], M])
        w = np.ones(len(S))
        if len(L):
            w[len(src):] = landmark_share / (1.0 - landmark_share) * len(src) * rel / rel.sum()
        if affine:
            H = np.column_stack([S, np.ones(len(S))]) * np.sqrt(w)[:, None]
            B, *_ = np.linalg.lstsq(H, Q * np.sqrt(w)[:, None], rcond=None)
            A_new, t_new = B[:3].T, B[3]
        else:
            sc, R, t_new = umeyama(S, Q, w)
            A_new = sc * R
        step = np.abs(A_new - A).max() + np.abs(t_new - t).max()
        A, t = A_new, t_new
        if step < 1e-6:
            break
    return A, t


def register_bone(body: str, generic_mesh, subject_mesh, init: tuple[np.ndarray, np.ndarray], landmarks=(), *,
                  affine: bool = True, names=None, twist=None) -> BoneMap:
    """Register one body's generic bone to the subject's (module docstring, steps 2-3).

    generic_mesh, subject_mesh : trimesh.Trimesh in the generic / personalised body frames (m); subject_mesh None:
        the start alone (kind "joints"); init : (A (3, 3), t (3,)) start; landmarks : pairs (generic (3,), subject
        (3,)[, relative weight]) of points the map should keep together (anatomical landmarks or joint centres;
        together they weigh ``LANDMARK_SHARE`` of the ICP's total, split by their relative weights); names : the pairs' names (the map's
        `BoneMap.landmarks_mm` residuals); twist : (c, u, κ, length) the bone's torsion (`fit_twist`), applied to
        the generic bone before the registration, or None
    """
    A0, t0 = (np.asarray(v, float) for v in init)
    tw, original = (None if twist is None else twist[:3]), list(landmarks)
    if tw is not None:
        landmarks = [(twist_points(p[0], tw), *p[1:]) for p in landmarks]
        if generic_mesh is not None:
            generic_mesh = generic_mesh.copy()
            generic_mesh.vertices = twist_points(np.asarray(generic_mesh.vertices), tw)
    best = _register(body, generic_mesh, subject_mesh, A0, t0, landmarks, affine)
    out = BoneMap(best.body, best.A, best.t, best.kind, best.distances_mm, {}, twist)
    if names is not None:
        out.landmarks_mm.update({n: round(1e3 * float(np.linalg.norm(out(p[0]) - p[1])), 2)
                                 for n, p in zip(names, original)})
    return out


def _register(body, generic_mesh, subject_mesh, A0, t0, landmarks, affine) -> BoneMap:
    """`register_bone` without the landmark residuals."""
    if subject_mesh is None or generic_mesh is None:
        return BoneMap(body, A0, t0, "joints")
    P, Y = surface_samples(generic_mesh), surface_samples(subject_mesh)
    dist = {"joints": 1e3 * _distance(P @ A0.T + t0, Y)}
    A1, t1 = _icp(P, Y, A0, t0, affine=False, landmarks=landmarks)
    dist["similarity"] = 1e3 * _distance(P @ A1.T + t1, Y)
    best = BoneMap(body, A1, t1, "similarity", dist)
    s0 = float(np.cbrt(abs(np.linalg.det(A0))))
    if dist["similarity"] > dist["joints"] or not (1.0 / MAX_SCALE_CHANGE <= best.scale / s0 <= MAX_SCALE_CHANGE):
        # ICP wandered off (or grew / shrank the bone past the joints' say, as on a partial toes mesh): keep the start
        best = BoneMap(body, A0, t0, "joints", dist)
    if affine:
        A2, t2 = _icp(P, Y, best.A, best.t, affine=True, landmarks=landmarks)
        dist["affine"] = 1e3 * _distance(P @ A2.T + t2, Y)
        sv = np.linalg.svd(A2, compute_uv=False) / best.scale
        if (dist["affine"] <= (1.0 - AFFINE_GAIN) * min(dist["similarity"], dist["joints"])
                and sv.max() <= AFFINE_STRETCH and sv.min() >= 1.0 / AFFINE_STRETCH):
            best = BoneMap(body, A2, t2, "affine", dist)
    return best


def fit_twist(P: np.ndarray, Q: np.ndarray, c: np.ndarray, u: np.ndarray, length: float, w=None):
    """The torsion of a long bone from its landmark pairs: ``min_κ min_(s,R,t) Σ w_i |s R w_κ(P_i) + t - Q_i|²``
    (`twist_points`; the inner problem Umeyama's closed form, κ by bounded scalar search within ±`MAX_TWIST_DEG`
    over `length`).  P, Q : (n, 3) generic / subject landmarks (m); c, u : the twist axis (generic frame);
    length : the bone's joint-to-joint length (m); w : (n,) weights (None: equal).  Returns ((c, u, κ, length), (s R (3, 3), t (3,)))."""
    from scipy.optimize import minimize_scalar

    def cost(k):
        W = twist_points(P, (c, u, k))
        s, R, t = umeyama(W, Q, w)
        return float(np.sum((np.ones(len(P)) if w is None else w) * np.sum((W @ (s * R).T + t - Q) ** 2, axis=1)))

    kmax = np.radians(MAX_TWIST_DEG) / length
    k = float(minimize_scalar(cost, bounds=(-kmax, kmax), method="bounded", options={"xatol": 1e-4}).x)
    s, R, t = umeyama(twist_points(P, (c, u, k)), Q, w)
    return (c, u, k, length), (s * R, t)


def _rel(poses: dict, parent: str, child: str) -> np.ndarray:
    """4x4 child-body -> parent-body transform from ground poses."""
    return np.linalg.solve(poses[parent], poses[child])


def _carried(T: np.ndarray, x) -> np.ndarray:
    """Points (..., 3) of a parent body's frame in a child's, T the 4x4 child -> parent transform."""
    return (np.asarray(x, float) - T[:3, 3]) @ T[:3, :3]


def landmark_pairs(generic, subject_landmarks: dict, subject_poses: dict, body: str) -> dict:
    """name -> (generic (3,), subject (3,)) in the body's two frames (m): the landmarks both models have on `body`
    (`GenericModel.landmarks`, `subject_landmarks` by name), and `BORROWED` ones from the parent body carried
    through each model's all-zero-pose relative placement."""
    gl, sl = (generic.landmarks or {}).get(body, {}), subject_landmarks.get(body, {})
    out = {n: (np.asarray(gl[n], float), np.asarray(sl[n], float)) for n in sorted(set(gl) & set(sl))}
    base, _, side = body.rpartition("_")
    if base in BORROWED:
        pbase, names = BORROWED[base]
        parent = f"{pbase}_{side}"
        gp, sp = (generic.landmarks or {}).get(parent, {}), subject_landmarks.get(parent, {})
        if parent in generic.poses and parent in subject_poses:
            Tg, Ts = _rel(generic.poses, parent, body), _rel(subject_poses, parent, body)
            out.update({n: (_carried(Tg, gp[n]), _carried(Ts, sp[n])) for n in names if n in gp and n in sp})
    return out


def register_bodies(generic, subject_meshes: dict, subject_joints: dict, subject_poses: dict, *,
                    affine: bool = True, subject_landmarks: dict | None = None, twist: bool = True) -> dict:
    """Every leg body's `BoneMap`, in chain order (pelvis, femur, tibia, talus, calcaneus, toes).

    generic : `personalize.muscles.generic.GenericModel`; subject_meshes : body -> trimesh (personalised body
    frame, m) or absent; subject_joints : `generic.joint_points` of the personalised model at its all-zero pose;
    subject_poses : `generic.body_poses` at that pose; subject_landmarks : body -> {name: (3,) m, body frame}
    (`personalize.muscles.subject_body_landmarks`) or None.

    Start of a body of `LANDMARK_BODIES` with `MIN_LANDMARKS` or more anatomical landmark pairs (`landmark_pairs`): their least-squares
    similarity (`umeyama`), and the pairs are the ICP's landmarks, so that a nearly axisymmetric bone (the tibia)
    cannot settle turned about its shaft; with `twist`, a long bone (`TWIST_BODIES`) with five pairs or more
    first takes the torsion its landmarks show about its joint-to-joint axis (`fit_twist`: the subject's tibial
    torsion is not gait2392's, and no similarity or affine map turns the two ends by different angles).  Otherwise (module docstring, step 1): a body with two joint centres
    (pelvis: both hips; femur: hip, knee; tibia: knee, ankle) starts from `similarity_from_joints`, a foot bone
    from the parent's map carried through both models' all-zero-pose relative body placements,
    ``M_b = T_s(p<-b)^-1 M_p T_g(p<-b)``, and the joint centres (hip, knee, ankle) are the ICP's landmarks.
    """
    chain = [("pelvis", None)]
    for s in ("r", "l"):
        chain += [(f"femur_{s}", "pelvis"), (f"tibia_{s}", f"femur_{s}"), (f"talus_{s}", f"tibia_{s}"),
                  (f"calcn_{s}", f"talus_{s}"), (f"toes_{s}", f"calcn_{s}")]
    maps: dict = {}
    for body, parent in chain:
        if body not in subject_poses or body not in generic.joint_points:
            continue
        pairs = landmark_pairs(generic, subject_landmarks or {}, subject_poses, body) \
            if body.rsplit("_", 1)[0] in LANDMARK_BODIES else {}
        gj, sj = generic.joint_points[body], subject_joints.get(body, {})
        centres = [j for j in sorted(set(gj) & set(sj)) if j.rsplit("_", 1)[0] in CENTRE_JOINTS]
        if len(pairs) >= MIN_LANDMARKS:
            P = np.array([g for g, _ in pairs.values()])
            Q = np.array([q for _, q in pairs.values()])
            wl = np.array([CENTRE_WEIGHT if n in CENTRE_LANDMARKS else 1.0 for n in pairs])
            sc, R, t = umeyama(P, Q, wl)
            init, tw = (sc * R, t), None
            if twist and body.rsplit("_", 1)[0] in TWIST_BODIES and len(pairs) >= MIN_LANDMARKS + 2 \
                    and len(centres) >= 2:
                a, b = gj[centres[0]], gj[centres[1]]
                length = float(np.linalg.norm(b - a))
                tw, init = fit_twist(P, Q, 0.5 * (a + b), (b - a) / length, length, wl)
            maps[body] = register_bone(body, generic.meshes.get(body), subject_meshes.get(body), init,
                                       [(g, q, w) for (g, q), w in zip(pairs.values(), wl)], affine=affine,
                                       names=list(pairs), twist=tw)
            continue
        init = similarity_from_joints({j: gj[j] for j in centres}, {j: sj[j] for j in centres}) \
            if len(centres) >= 2 else None
        if init is None and parent in maps:
            Tg, Ts = _rel(generic.poses, parent, body), _rel(subject_poses, parent, body)
            Mp = np.eye(4)
            Mp[:3, :3], Mp[:3, 3] = maps[parent].A, maps[parent].t
            M = np.linalg.solve(Ts, Mp @ Tg)
            init = (M[:3, :3], M[:3, 3])
        if init is None:
            continue
        pairs.update({j: (gj[j], sj[j]) for j in centres})
        maps[body] = register_bone(body, generic.meshes.get(body), subject_meshes.get(body), init,
                                   list(pairs.values()), affine=affine, names=list(pairs))
    return maps
