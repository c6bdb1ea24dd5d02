"""Registration of MRI bone landmarks (scanner frame) to static-trial markers (lab frame).

Model
-----
Each landmark p_k (scanner frame, m) with a marker counterpart is moved out of
the bone along its outward surface normal n_k by the soft-tissue thickness plus
the marker radius, q_k = p_k + d_k n_k (the thickness is measured along the
bone normal; its prior mean and sd per site come from `kinematics.gait.soft_tissue`,
see `skin_prior`), and maps to the measured marker centre

    m_k = c + exp([ω]×) (R̂ q_k + t̂ - c) + δ + ε_k,   ε_k ~ N(0, Σ_k),
    Σ_k = R C_k Rᵀ + M_k,

with C_k the landmark covariance (plus d_k's variance along n_k and the
normal's angular variance across it), M_k the marker covariance (placement sd
and static-trial scatter), c the weighted marker centroid (the pivot that
decorrelates rotation and translation).  The rigid transform (R, t)
minimises the Mahalanobis sum

    χ² = Σ_k r_kᵀ Σ_k⁻¹ r_k,   r_k = m_k - (R q_k + t),

solved by Gauss-Newton on the six increments x = (ω, δ) (rad, m) started from
the closed-form weighted Kabsch/Horn solution, with the analytic Jacobian
∂(R q + t)/∂x = [-[R q + t - c]×, I].  The transform covariance is the inverse
information matrix (JᵀWJ)⁻¹ (W = blockdiag Σ_k⁻¹), inflated by χ²/dof only
when the χ² test rejects the declared noise (p < 0.01).

Outliers (a mislabelled or misplaced marker) are rejected one at a time by
leave-one-out prediction: the point whose residual against the fit of the
others has the largest Mahalanobis distance d_k² = rᵀ(Σ_k + J_k Cov₋ₖ J_kᵀ)⁻¹ r
is dropped while d_k exceeds the χ²₃ quantile equivalent to `k_outlier` sd
and more than `min_points` remain.

Every transferred quantity (point, direction, frame) carries the registration
covariance to first order: for y = R q + t, Cov y = J_y Cov(x) J_yᵀ + R C_q Rᵀ.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

from kinematics.gait.soft_tissue import DEFAULT_TISSUE, tissue_prior

from lowerlimb.bones import mirror_name
from lowerlimb.errors import InputError

__all__ = [
    "Registration", "SegmentRegistrations", "register_landmarks", "register_segments", "static_marker_positions", "express_in_frame",
    "SEGMENT_MARKERS", "SEGMENT_BONES", "SKIN_THICKNESS", "MARKER_RADIUS", "skin_prior", "GATE_P", "gate_statistic",
    "passes_gate",
]

#: soft-tissue thickness (m) and sd of a site absent from the per-site table `kinematics.gait.soft_tissue`
#: (an assumption, not a measured value); `skin_prior` gives each marker's (mean, sd) prior
SKIN_THICKNESS = DEFAULT_TISSUE.mean
SKIN_THICKNESS_SD = DEFAULT_TISSUE.sd
#: radius of a 14 mm reflective marker (m)
MARKER_RADIUS = 0.007
#: default sd (m) of marker placement (palpation) on top of the static-trial scatter
MARKER_PLACEMENT_SD = 0.003
#: p-value of a registration's full chi-square (`gate_statistic`) below which its bones are taken as another
#: person's.  Phantom subjects registered to their own bones: p >= 0.96 on every segment (3 seeds); a +3 sd
#: (54 mm) ASIS tissue with a bone-only label volume (the prior is then wrong): pelvis p = 0.0017; the pelvis
#: of another phantom: p = 7e-22, 2e-17, 2e-10 (statures apart) but 0.77-0.87 for two subjects of one size.
GATE_P = 1e-6
#: angular sd (deg) of an outward normal guessed from internal landmarks (no surface given)
GUESSED_NORMAL_SD_DEG = 30.0
#: angular sd (deg) of a normal taken from the bone surface
SURFACE_NORMAL_SD_DEG = 10.0

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


def _skew(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _tangent_sd_deg(cov: np.ndarray) -> float:
    """1-sd angle (deg) of a unit vector from its (rank-2) 3x3 covariance: sqrt(trace / 2)."""
    return float(np.degrees(np.sqrt(max(np.trace(cov) / 2.0, 0.0))))


@dataclass(frozen=True)
class Registration:
    """A rigid map scanner -> lab, y = R x + t, with its 6-DOF covariance.

    Attributes
    ----------
    R : (3, 3) rotation; t : (3,) m
    cov : (6, 6) covariance of x = (ω rad, δ m): ω a small rotation vector in
        the lab frame about the pivot `centre`, δ a lab translation
    centre : (3,) m, lab pivot of the perturbation (weighted marker centroid)
    names : names of the correspondences used; rejected : dict name -> Mahalanobis d
    residuals : (K, 3) m, lab residuals m_k - (R q_k + t) of the used points
    mahalanobis : (K,) per-point √(r_kᵀ Σ_k⁻¹ r_k)
    chi2, dof, p_value : goodness of fit against the declared noise
    inflation : factor applied to `cov` (1 unless the χ² test failed)
    segment : registration segment name; notes : human-readable remarks
    """

    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    centre: np.ndarray
    names: tuple[str, ...]
    rejected: dict
    residuals: np.ndarray
    mahalanobis: np.ndarray
    chi2: float
    dof: int
    p_value: float
    inflation: float = 1.0
    segment: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    # ------------------------------------------------------------------ summaries
    @property
    def rms(self) -> float:
        """rms residual distance (m) of the used correspondences."""
        return float(np.sqrt(np.mean(np.sum(self.residuals**2, axis=1))))

    @property
    def rotation_sd_deg(self) -> np.ndarray:
        """(3,) sd (deg) of the rotation-vector components (lab axes)."""
        return np.degrees(np.sqrt(np.diag(self.cov)[:3]))

    @property
    def translation_sd(self) -> np.ndarray:
        """(3,) sd (m) of the translation at the pivot `centre`."""
        return np.sqrt(np.diag(self.cov)[3:])

    def _jacobian(self, y: np.ndarray) -> np.ndarray:
        """∂y/∂x (3, 6) of a transferred lab point y: [-[y - c]×, I]."""
        return np.hstack([-_skew(y - self.centre), np.eye(3)])

    # ------------------------------------------------------------------ transfer
    def transfer_point(self, point, cov=None) -> tuple[np.ndarray, np.ndarray]:
        """Lab position and covariance of a scanner point.

        y = R p + t,  Cov y = J Cov(x) Jᵀ + R C_p Rᵀ,  J = [-[y - c]×, I].

        Parameters
        ----------
        point : (3,) m, scanner frame; cov : (3, 3) m² or None (exact point)

        Returns
        -------
        y : (3,) m lab; cov_y : (3, 3) m²
        """
        p = np.asarray(point, float).reshape(3)
        y = self.R @ p + self.t
        J = self._jacobian(y)
        C = J @ self.cov @ J.T
        if cov is not None:
            C = C + self.R @ np.asarray(cov, float).reshape(3, 3) @ self.R.T
        return y, 0.5 * (C + C.T)

    def transfer_points(self, points, covs=None) -> tuple[np.ndarray, np.ndarray]:
        """Lab positions of K scanner points and their joint covariance.

        y_a = R p_a + t;  Cov(y_a, y_b) = J_a Cov(x) J_bᵀ + δ_ab R C_a Rᵀ
        (J = [-[y - c]×, I]): every point shares the registration error, so
        points of one segment (e.g. both hip centres of the pelvis) are correlated.

        Parameters
        ----------
        points : (K, 3) m, scanner frame; covs : (K, 3, 3) m² or None (exact points)

        Returns
        -------
        y : (K, 3) m lab; cov : (3K, 3K) m², blocks in the order of the points
        """
        P = np.asarray(points, float).reshape(-1, 3)
        Y = P @ self.R.T + self.t
        J = np.concatenate([self._jacobian(y) for y in Y], axis=0)  # (3K, 6)
        C = J @ self.cov @ J.T
        if covs is not None:
            Cs = np.asarray(covs, float).reshape(len(P), 3, 3)
            for k, c in enumerate(Cs):
                C[3 * k:3 * k + 3, 3 * k:3 * k + 3] += self.R @ c @ self.R.T
        return Y, 0.5 * (C + C.T)

    def transfer_direction(self, direction, sd_deg: float = 0.0) -> tuple[np.ndarray, float, np.ndarray]:
        """Lab direction of a scanner unit vector with its angular uncertainty.

        u' = R u;  Cov u' = [u']× Cov(ω) [u']×ᵀ + σ² (I - u'u'ᵀ)  (σ = sd_deg in rad,
        isotropic across the direction).

        Returns
        -------
        u' : (3,) unit; sd_deg : combined 1-sd angle, √(tr Cov u' / 2) in deg;
        cov : (3, 3) rad² tangent-plane covariance
        """
        u = np.asarray(direction, float).reshape(3)
        nu = np.linalg.norm(u)
        if not np.isfinite(nu) or nu < 1e-12:
            raise InputError("direction", "direction to transfer is zero or not finite")
        u2 = self.R @ (u / nu)
        S = _skew(u2)
        s = np.radians(float(sd_deg))
        C = S @ self.cov[:3, :3] @ S.T + s * s * (np.eye(3) - np.outer(u2, u2))
        C = 0.5 * (C + C.T)
        return u2, _tangent_sd_deg(C), C

    def transfer_frame(self, origin, rotation, origin_cov=None, rotation_cov=None):
        """Lab pose of a scanner frame (origin, rotation with axes as columns).

        R_lab = R R_f; its uncertainty is a lab rotation vector with covariance
        Cov(ω) + R C_f Rᵀ (C_f the frame's own rotation-vector covariance, rad²,
        expressed in the scanner frame).  The origin follows `transfer_point`.

        Returns
        -------
        origin (3,) m, rotation (3, 3), origin_cov (3, 3) m², rotation_cov (3, 3) rad²
        """
        o, oc = self.transfer_point(origin, origin_cov)
        Rf = np.asarray(rotation, float).reshape(3, 3)
        Rc = self.cov[:3, :3].copy()
        if rotation_cov is not None:
            Rc = Rc + self.R @ np.asarray(rotation_cov, float).reshape(3, 3) @ self.R.T
        return o, self.R @ Rf, oc, 0.5 * (Rc + Rc.T)

    def transfer_bone(self, bone: dict) -> dict:
        """Transfer one bone entry of landmarks.json into the lab frame.

        Landmarks get ``position``/``cov``, axes ``point``/``point_cov``/
        ``direction``/``sd_deg``, frames ``origin``/``origin_cov``/
        ``rotation``/``rotation_cov``; scalars (lengths, radii) are frame-
        invariant and copied.  Axis points carry only the registration part of
        the covariance (the JSON gives none of their own).
        """
        out = {"landmarks": {}, "axes": {}, "frames": {}, "scalars": dict(bone.get("scalars", {}))}
        for name, lm in bone.get("landmarks", {}).items():
            y, c = self.transfer_point(lm["position"], lm.get("cov"))
            out["landmarks"][name] = {"position": y, "cov": c}
        for name, ax in bone.get("axes", {}).items():
            p, pc = self.transfer_point(ax["point"])
            u, sd, C = self.transfer_direction(ax["direction"], ax.get("sd_deg", 0.0))
            out["axes"][name] = {"point": p, "point_cov": pc, "direction": u, "sd_deg": sd, "cov": C}
        for name, fr in bone.get("frames", {}).items():
            o, Rl, oc, rc = self.transfer_frame(fr["origin"], fr["rotation"])
            out["frames"][name] = {"origin": o, "rotation": Rl, "origin_cov": oc, "rotation_cov": rc}
        return out

    def transfer_joints(self, joints: dict) -> dict:
        """Transfer joints.json entries (``origin``, ``origin_cov``, ``rotation``, ``axis_sd_deg``) to the lab.

        The rotation gains the registration's rotation covariance
        (``rotation_cov``, rad², lab rotation vector) and ``axis_sd_deg`` the
        registration's tilt of the main (Z) axis.
        """
        out = {}
        for name, j in joints.items():
            o, Rl, oc, rc = self.transfer_frame(j["origin"], j["rotation"], j.get("origin_cov"))
            sd_ax = float(j.get("axis_sd_deg", 0.0))
            _, sd, _ = self.transfer_direction(np.asarray(j["rotation"], float)[:, 2], sd_ax)
            out[name] = {"origin": o, "origin_cov": oc, "rotation": Rl, "rotation_cov": rc, "axis_sd_deg": sd}
        return out

    def summary(self) -> dict:
        """JSON-ready summary (SI units)."""
        return {
            "segment": self.segment, "units": "m, rad", "R": self.R.tolist(), "t": self.t.tolist(),
            "cov": self.cov.tolist(), "centre": self.centre.tolist(), "used": list(self.names),
            "rejected": {k: float(v) for k, v in self.rejected.items()}, "rms": self.rms,
            "chi2": self.chi2, "dof": self.dof, "p_value": self.p_value, "inflation": self.inflation,
            "rotation_sd_deg": self.rotation_sd_deg.tolist(), "translation_sd": self.translation_sd.tolist(),
            "notes": list(self.notes),
        }


def gate_statistic(reg: Registration) -> tuple[float, int, float]:
    """χ² of a registration over every correspondence, outliers included, its dof and p-value.

    χ²_all = Σ_used d_k² + Σ_rejected d_j² on 3 (K_used + K_rejected) - 6 degrees
    of freedom, d the Mahalanobis distances (a rejected point's from the fit
    without it).  Outlier rejection alone would hide a wrong subject: with
    another person's pelvis one of its four landmarks is rejected and the
    other three fit.
    """
    rej = np.asarray(list(reg.rejected.values()), float)
    chi2 = float(reg.chi2 + np.sum(rej**2))
    dof = int(reg.dof + 3 * len(rej))
    p = float(stats.chi2.sf(chi2, dof)) if dof > 0 else 1.0
    return chi2, dof, p


def passes_gate(reg: Registration, p_min: float = GATE_P) -> bool:
    """Whether the registration's full χ² (`gate_statistic`) is compatible with the declared noise at `p_min`."""
    return gate_statistic(reg)[2] >= p_min


def express_in_frame(point, cov, origin, rotation, origin_cov=None, rotation_cov=None):
    """A lab point in a segment frame, with first-order uncertainty of both.

    local = Rᵀ (y - o);  Cov local = Rᵀ (C_y + C_o + [y - o]× C_ω [y - o]×ᵀ) R,
    with C_ω the frame's lab rotation-vector covariance.  The point and the
    frame are taken as independent: when both come from the same
    registration, transfer the point into the scanner frame's own segment
    frame instead (the registration error then cancels).

    Returns
    -------
    local (3,) m, cov (3, 3) m²
    """
    y = np.asarray(point, float).reshape(3)
    o = np.asarray(origin, float).reshape(3)
    R = np.asarray(rotation, float).reshape(3, 3)
    C = np.zeros((3, 3)) if cov is None else np.asarray(cov, float).reshape(3, 3)
    if origin_cov is not None:
        C = C + np.asarray(origin_cov, float).reshape(3, 3)
    if rotation_cov is not None:
        S = _skew(y - o)
        C = C + S @ np.asarray(rotation_cov, float).reshape(3, 3) @ S.T
    L = R.T @ C @ R
    return R.T @ (y - o), 0.5 * (L + L.T)


# --------------------------------------------------------------------------- core solver


def _as_covs(x, K: int, name: str, default_sd: float) -> np.ndarray:
    """(K, 3, 3) covariances from None, a scalar sd, (K,) sds, (3, 3) or (K, 3, 3) covariances."""
    if x is None:
        return np.repeat((default_sd**2 * np.eye(3))[None], K, axis=0)
    a = np.asarray(x, float)
    if a.ndim == 0:
        return np.repeat((float(a) ** 2 * np.eye(3))[None], K, axis=0)
    if a.shape == (K,):
        return a[:, None, None] ** 2 * np.eye(3)
    if a.shape == (3, 3):
        return np.repeat(a[None], K, axis=0)
    if a.shape == (K, 3, 3):
        return a.copy()
    raise InputError(name, f"expected a sd, {K} sds or {K} 3x3 covariances, got shape {a.shape}")


def _kabsch(P: np.ndarray, M: np.ndarray, w: np.ndarray):
    """Weighted Horn/Kabsch: argmin Σ w_k ‖R p_k + t - m_k‖² (closed form, SVD)."""
    w = w / w.sum()
    pb, mb = w @ P, w @ M
    H = (P - pb).T @ (w[:, None] * (M - mb))
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mb - R @ pb


def _fit(Q, M, Cq, Cm, *, max_iter: int = 50, tol: float = 1e-13):
    """Gauss-Newton on χ² = Σ r_kᵀ Σ_k⁻¹ r_k; returns R, t, c, H (information), r, Σ."""
    K = len(Q)
    w0 = 1.0 / np.trace(Cq + Cm, axis1=1, axis2=2)
    R, t = _kabsch(Q, M, w0)
    c = (w0 @ M) / w0.sum()
    for _ in range(max_iter):
        S = np.einsum("ij,kjl,ml->kim", R, Cq, R) + Cm
        W = np.linalg.inv(S)
        y = Q @ R.T + t
        r = M - y
        J = np.zeros((K, 3, 6))
        J[:, :, :3] = -_skew(y - c)
        J[:, :, 3:] = np.eye(3)
        H = np.einsum("kai,kab,kbj->ij", J, W, J)
        g = np.einsum("kai,kab,kb->i", J, W, r)
        dx = np.linalg.lstsq(H, g, rcond=None)[0]
        dR = Rotation.from_rotvec(dx[:3]).as_matrix()
        # y ← c + dR (y - c) + δ  ⇒  R ← dR R,  t ← c + dR (t - c) + δ
        R = dR @ R
        t = c + dR @ (t - c) + dx[3:]
        if np.max(np.abs(dx)) < tol:
            break
    S = np.einsum("ij,kjl,ml->kim", R, Cq, R) + Cm
    W = np.linalg.inv(S)
    y = Q @ R.T + t
    J = np.zeros((K, 3, 6))
    J[:, :, :3] = -_skew(y - c)
    J[:, :, 3:] = np.eye(3)
    H = np.einsum("kai,kab,kbj->ij", J, W, J)
    return R, t, c, H, M - y, S, J


def register_landmarks(mri_points, marker_points, mri_cov=None, marker_sd=MARKER_PLACEMENT_SD, normals=None,
                       offset=SKIN_THICKNESS + MARKER_RADIUS, *, offset_sd: float = SKIN_THICKNESS_SD,
                       normal_sd_deg: float | np.ndarray = SURFACE_NORMAL_SD_DEG, names=None,
                       k_outlier: float = 3.0, min_points: int = 3, segment: str | None = None) -> Registration:
    """Weighted rigid registration of MRI landmarks to marker centres, with outlier rejection.

    See the module docstring for the model and the minimised χ².

    Parameters
    ----------
    mri_points : (K, 3) m, landmarks on the bone surface (scanner frame)
    marker_points : (K, 3) m, marker centres (lab frame)
    mri_cov : None, (K, 3, 3) or (3, 3) m², landmark covariances (None: exact)
    marker_sd : float, (K,) m sds or (K, 3, 3) m² covariances of the markers
    normals : (K, 3) outward unit normals at the landmarks (scanner frame) or
        None (the points are already marker centres: no offset applied)
    offset : float or (K,) m, skin thickness + marker radius along the normal
    offset_sd : float or (K,) m, sd of that offset
    normal_sd_deg : float or (K,), angular sd of the normals (adds
        offset² σ² across the normal)
    names : K names (for reporting); default "0", "1", ...
    k_outlier : rejection threshold in sd (converted to the χ²₃ quantile)
    min_points : never go below this many correspondences (≥ 3)

    Returns
    -------
    Registration
    """
    src = segment or "registration"
    P = np.asarray(mri_points, float)
    M = np.asarray(marker_points, float)
    if P.ndim != 2 or P.shape[1] != 3 or M.shape != P.shape:
        raise InputError(src, f"landmarks {P.shape} and markers {M.shape} must both be (K, 3)")
    K = len(P)
    names = tuple(str(i) for i in range(K)) if names is None else tuple(names)
    if len(names) != K:
        raise InputError(src, f"{len(names)} names for {K} correspondences")
    min_points = max(int(min_points), 3)
    if K < 3:
        raise InputError(src, f"needs at least 3 landmark/marker pairs, got {K}: {', '.join(names) or 'none'}")
    bad = [n for n, p, m in zip(names, P, M) if not (np.all(np.isfinite(p)) and np.all(np.isfinite(m)))]
    if bad:
        raise InputError(src, f"non-finite landmark or marker position for {', '.join(bad)}")
    Cq = np.zeros((K, 3, 3)) if mri_cov is None else _as_covs(mri_cov, K, src, 0.0)
    Cm = _as_covs(marker_sd, K, src, MARKER_PLACEMENT_SD)
    Q = P.copy()
    if normals is not None:
        N = np.asarray(normals, float).reshape(K, 3)
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
        d = np.broadcast_to(np.asarray(offset, float), (K,))
        ds = np.broadcast_to(np.asarray(offset_sd, float), (K,))
        ns = np.radians(np.broadcast_to(np.asarray(normal_sd_deg, float), (K,)))
        Q = P + d[:, None] * N
        nn = np.einsum("ki,kj->kij", N, N)
        Cq = Cq + ds[:, None, None] ** 2 * nn + (d * ns)[:, None, None] ** 2 * (np.eye(3) - nn)
    # Floor so that exact inputs keep the information matrix invertible.
    Cq = Cq + 1e-12 * np.eye(3)

    spread = np.linalg.svd(Q - Q.mean(axis=0), compute_uv=False)
    if spread[1] < 1e-3:
        raise InputError(src, f"landmarks {', '.join(names)} are (nearly) collinear: the rotation about their line is undetermined")

    thr = float(stats.chi2.ppf(1.0 - 2.0 * stats.norm.sf(k_outlier), 3))
    keep = list(range(K))
    rejected: dict[str, float] = {}
    while len(keep) > min_points:
        d2 = np.full(len(keep), -np.inf)
        for j, k in enumerate(keep):
            others = [i for i in keep if i != k]
            sp = np.linalg.svd(Q[others] - Q[others].mean(axis=0), compute_uv=False)
            if sp[1] < 1e-3:
                continue
            R, t, c, H, _, _, _ = _fit(Q[others], M[others], Cq[others], Cm[others])
            y = R @ Q[k] + t
            Jk = np.hstack([-_skew(y - c), np.eye(3)])
            S = R @ Cq[k] @ R.T + Cm[k] + Jk @ np.linalg.inv(H) @ Jk.T
            r = M[k] - y
            d2[j] = r @ np.linalg.solve(S, r)
        j = int(np.argmax(d2))
        if d2[j] <= thr:
            break
        rejected[names[keep[j]]] = float(np.sqrt(d2[j]))
        keep.pop(j)

    R, t, c, H, r, S, J = _fit(Q[keep], M[keep], Cq[keep], Cm[keep])
    if np.linalg.cond(H) > 1e14:
        raise InputError(src, "registration is degenerate: the landmarks do not fix all six degrees of freedom")
    maha2 = np.einsum("ka,kab,kb->k", r, np.linalg.inv(S), r)
    chi2 = float(maha2.sum())
    dof = 3 * len(keep) - 6
    p = float(stats.chi2.sf(chi2, dof)) if dof > 0 else 1.0
    cov = np.linalg.inv(H)
    notes = []
    inflation = 1.0
    if dof > 0 and p < 0.01:
        inflation = chi2 / dof
        cov = cov * inflation
        notes.append(f"residuals exceed the declared noise (chi2/dof = {inflation:.2f}); covariance inflated")
    if rejected:
        notes.append("rejected as outliers: " + ", ".join(f"{n} ({v:.1f} sd)" for n, v in rejected.items()))
    if len(keep) == 3:
        notes.append("only 3 correspondences: outliers cannot be detected")
    return Registration(R, t, 0.5 * (cov + cov.T), c, tuple(names[i] for i in keep), rejected, r,
                        np.sqrt(maha2), chi2, dof, p, inflation, segment, tuple(notes))


# --------------------------------------------------------------------------- per segment


def static_marker_positions(trial, names=None, placement_sd: float = MARKER_PLACEMENT_SD):
    """Robust static positions of markers and their measurement covariance.

    position = per-axis median over the finite frames; scatter = (1.4826 MAD)²
    per axis (the body's sway in the static trial), added to the placement
    variance: M = placement_sd² I + diag(scatter).

    Returns
    -------
    dict name -> (position (3,) m, cov (3, 3) m²) for markers with ≥ 1 finite frame
    """
    out = {}
    for n in (trial.names if names is None else names):
        if n not in trial.names:
            continue
        x = trial.marker(n)
        x = x[np.all(np.isfinite(x), axis=1)]
        if len(x) == 0:
            continue
        med = np.median(x, axis=0)
        mad = 1.4826 * np.median(np.abs(x - med), axis=0) if len(x) > 2 else np.zeros(3)
        out[n] = (med, placement_sd**2 * np.eye(3) + np.diag(mad**2))
    return out


def skin_prior(marker: str) -> tuple[float, float]:
    """Prior (mean, sd), m, of the soft tissue between `marker`'s bony landmark and the skin, along the bone normal.

    From the per-site table `kinematics.gait.soft_tissue.SOFT_TISSUE_THICKNESS` (ASIS 9.7 ± 7.0 mm,
    PSIS 19.6 ± 10.9 mm from pelvic CT, Mantovani et al. 2016; other sites assumed), else
    (`SKIN_THICKNESS`, `SKIN_THICKNESS_SD`).
    """
    p = tissue_prior(marker)
    return float(p.mean), float(p.sd)


def _segment_marker_names(seg: str, side: str | None) -> tuple[str, ...]:
    if seg == "pelvis":
        return SEGMENT_MARKERS["pelvis"]
    return tuple(side.upper() + m for m in SEGMENT_MARKERS[seg])


def _internal_reference(bones_json: dict, bone_names, marker_names, p: np.ndarray):
    """Nearest non-marker (internal: centres) landmark of the segment, or None."""
    best, bd = None, np.inf
    for b in bone_names:
        for name, lm in bones_json.get(b, {}).get("landmarks", {}).items():
            if name in marker_names or name in _ALL_MARKER_NAMES:
                continue
            q = np.asarray(lm["position"], float)
            dist = np.linalg.norm(q - p)
            if 1e-4 < dist < bd:
                best, bd = q, dist
    return best


_ALL_MARKER_NAMES = {m for v in SEGMENT_MARKERS.values() for m in v} | {
    s + m for s in "RL" for k, v in SEGMENT_MARKERS.items() if k != "pelvis" for m in v}


def _surface_normal(surface, p: np.ndarray):
    V = np.asarray(getattr(surface, "vertices"), float)
    N = getattr(surface, "vertex_normals", None)
    if N is None:
        N = getattr(surface, "normals")
    N = np.asarray(N, float)
    k = int(np.argmin(np.sum((V - p) ** 2, axis=1)))
    return N[k] / np.linalg.norm(N[k])


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


def _per_marker(value, name: str, k: int) -> float:
    """`value` for marker `name`: a number, a {name: number} dict, or None; else the site prior's mean (k=0) / sd (k=1)."""
    if isinstance(value, dict):
        value = value.get(name)
    return float(skin_prior(name)[k] if value is None else value)


def register_segments(landmarks: dict, static_trial, *, sides=("r", "l"), segments=None,
                      on_missing: str = "raise", normals: dict | None = None,
                      surfaces: dict | None = None, skin_thickness: float | dict | None = None,
                      skin_sd: float | dict | None = None, marker_radius: float = MARKER_RADIUS,
                      placement_sd: float = MARKER_PLACEMENT_SD, k_outlier: float = 3.0,
                      landmarks_source: str = "landmarks.json") -> SegmentRegistrations:
    """Register every segment's MRI landmarks to the static-trial markers.

    Segments: ``pelvis`` (RASI, LASI, RPSI, LPSI, SYMP), ``femur_s`` (TRO, KNE,
    MFC), ``tibia_s`` (tibia + fibula: TTB, HFB, ANK, MMA), ``calcn_s`` (calcn,
    talus, toes: HEE, D1M, D5M), each side letter prefixed (R/L).  Segments
    with no landmark and no marker at all are skipped; a segment with some
    but fewer than 3 usable correspondences raises.

    Outward normals come from `normals` ({marker name: (3,)}, scanner frame),
    else from `surfaces` ({bone: mesh with vertices and vertex_normals/normals},
    nearest vertex), else they are guessed from the nearest internal landmark
    of the segment (e.g. condyle centre -> epicondyle) with a 30° sd.

    Parameters
    ----------
    landmarks : dict, landmarks.json content (units m, scanner frame)
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

    Returns
    -------
    SegmentRegistrations (dict segment -> Registration, and ``.skipped``)

    Raises
    ------
    InputError : wrong units, fewer than 3 correspondences in a segment (named),
        or left/right labels mixed between the MRI and the markers
    """
    tsrc = static_trial.source or "static trial"
    if not isinstance(landmarks, dict) or "bones" not in landmarks:
        raise InputError(landmarks_source, "not a landmarks file (no 'bones')")
    if landmarks.get("units", "m") != "m":
        raise InputError(landmarks_source, f"landmark units must be 'm', got {landmarks.get('units')!r}")
    bones = landmarks["bones"]
    static = static_marker_positions(static_trial, placement_sd=placement_sd)
    mri_all = {n: np.asarray(lm["position"], float) for b in bones.values() for n, lm in b.get("landmarks", {}).items()
               if n in _ALL_MARKER_NAMES}
    lab_all = {n: v[0] for n, v in static.items() if n in _ALL_MARKER_NAMES}
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
        mri = {}
        covs = {}
        for b in bone_names:
            for n, lm in bones.get(b, {}).get("landmarks", {}).items():
                if n in wanted:
                    mri[n] = np.asarray(lm["position"], float)
                    covs[n] = np.asarray(lm.get("cov", np.zeros((3, 3))), float).reshape(3, 3)
        lab_names = [n for n in wanted if n in static]
        if not mri and not lab_names:
            continue
        pair = [n for n in wanted if n in mri and n in static]
        if len(pair) < 3:
            missing_mri = [n for n in wanted if n not in mri]
            missing_lab = [n for n in wanted if n not in static]
            problem = (f"segment {seg_name} has {len(pair)} usable landmark/marker pairs ({', '.join(pair) or 'none'}), needs 3; "
                       f"missing in MRI: {', '.join(missing_mri) or 'none'}, missing in static trial: {', '.join(missing_lab) or 'none'}")
            if on_missing == "skip":
                out.skipped[seg_name] = problem
                continue
            raise InputError(tsrc if len(mri) >= 3 else landmarks_source, problem)
        P = np.array([mri[n] for n in pair])
        N = np.zeros_like(P)
        nsd = np.zeros(len(pair))
        for i, n in enumerate(pair):
            if normals is not None and n in normals:
                N[i], nsd[i] = np.asarray(normals[n], float), SURFACE_NORMAL_SD_DEG
                continue
            surf = None
            if surfaces is not None:
                surf = next((surfaces[b] for b in bone_names if b in surfaces), None)
            if surf is not None:
                N[i], nsd[i] = _surface_normal(surf, P[i]), SURFACE_NORMAL_SD_DEG
                continue
            ref = _internal_reference(bones, bone_names, wanted, P[i])
            if ref is None:
                others = np.delete(P, i, axis=0)
                ref = others.mean(axis=0)
            N[i], nsd[i] = P[i] - ref, GUESSED_NORMAL_SD_DEG
        skin = np.array([_per_marker(skin_thickness, n, 0) for n in pair], float)
        skin_s = np.array([_per_marker(skin_sd, n, 1) for n in pair], float)
        out[seg_name] = register_landmarks(
            P, np.array([static[n][0] for n in pair]), np.array([covs[n] for n in pair]),
            np.array([static[n][1] for n in pair]), N, skin + marker_radius, offset_sd=skin_s, normal_sd_deg=nsd,
            names=pair, k_outlier=k_outlier, segment=seg_name)
    return out
