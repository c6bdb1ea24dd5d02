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

solved by damped Levenberg-Marquardt (a step is kept only if χ² decreases;
see `_fit`) on the six increments x = (ω, δ) (rad, m) started from
the closed-form weighted Kabsch/Horn solution, with the analytic Jacobian
∂(R q + t)/∂x = [-[R q + t - c]×, I].  The transform covariance is the inverse
information matrix (JᵀWJ)⁻¹ (W = blockdiag Σ_k⁻¹), inflated by χ²/dof only
when the χ² test rejects the declared noise (p < 0.01).

Outliers (a mislabelled or misplaced marker) are rejected one at a time by
leave-one-out prediction: the point whose residual against the fit of the
others has the largest Mahalanobis distance d_k² = rᵀ(Σ_k + J_k Cov₋ₖ J_kᵀ)⁻¹ r
is dropped while d_k exceeds the χ²₃ quantile equivalent to `k_outlier` sd
and more than `min_points` remain.  The `fixed` points (joint centres and axes
that tie a segment to its neighbour: constraints, not observations) are never
dropped: when one of them is the worst, rejection stops there and the χ² gate
shows the conflict.

Every transferred quantity (point, direction) carries the registration
covariance to first order: for y = R q + t, Cov y = J_y Cov(x) J_yᵀ + R C_q Rᵀ.
The correspondences of each segment (landmarks named like markers, offset
along the bone normal) and the registration of every segment of a static
trial are `personalize.marker_registration`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

from kinematics.gait.soft_tissue import DEFAULT_TISSUE, tissue_prior

from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS, kabsch, skew

__all__ = [
    "Registration", "register_landmarks", "static_marker_positions", "express_in_frame", "SKIN_THICKNESS",
    "skin_prior", "scaled_skin_prior", "GATE_P", "gate_statistic", "MARKER_PLACEMENT_SD", "SURFACE_NORMAL_SD_DEG", "PALPATION_SD",
    "PALPATION_SD_BY_SITE", "palpation_sd",
]

#: soft-tissue thickness (m) and sd of a site absent from the per-site table `kinematics.gait.soft_tissue`
#: (an assumption, not a measured value); `skin_prior` gives each marker's (mean, sd) prior
SKIN_THICKNESS = DEFAULT_TISSUE.mean
SKIN_THICKNESS_SD = DEFAULT_TISSUE.sd
#: default sd (m) of marker placement (palpation) on top of the static-trial scatter
MARKER_PLACEMENT_SD = 0.003
#: p-value of a registration's full chi-square (`gate_statistic`) below which its bones are taken as another
#: person's.  Phantom subjects registered to their own bones: p >= 0.96 on every segment (3 seeds); a +3 sd
#: (54 mm) ASIS tissue with a bone-only label volume (the prior is then wrong): pelvis p = 0.0017; the pelvis
#: of another phantom: p = 7e-22, 2e-17, 2e-10 (statures apart) but 0.77-0.87 for two subjects of one size.
#: Real anatomy (`phantoms.real_subject`, Plug-in-Gait): the ICL_MRI bones scaled by 0.85 with a LHDL_CT
#: subject's markers, pelvis p = 2e-7; unscaled (two adults of one size) p = 7e-4, which no gate can refuse:
#: the sum of all seven segments' chi2 gives p = 4e-9 there but 7e-7 for a child's own ICL_MRI bones (seed 0,
#: subject 011: its feet registrations' chi2 exceed their dof), so a same-size wrong subject is not detected.
GATE_P = 1e-6
#: angular sd (deg) of a normal taken from the bone surface
SURFACE_NORMAL_SD_DEG = 10.0
#: tangential sd (m) of a palpated bony-landmark marker whose soft tissue is estimated (`register_landmarks`
#: with a tissue prior): the lower end of the inter-examiner dispersion of Della Croce, Cappozzo & Kerrigan 1999
#: (Med Biol Eng Comput 37:155; pelvis and lower-limb landmarks, rms 6-21 mm).  The measured-tissue path keeps
#: `MARKER_PLACEMENT_SD` alone: its scales were calibrated on phantoms whose markers sit exactly.
PALPATION_SD = 0.006
#: m, palpation sd across the bone normal per landmark site (per axis: the 2-D rms misplacement / sqrt 2), after
#: the inter-examiner dispersions of Della Croce, Cappozzo & Kerrigan 1999 (Med Biol Eng Comput 37:155) and
#: Della Croce et al. 2005 (Med Biol Eng Comput 43:143): the greater trochanter worst, the malleoli best;
#: `PALPATION_SD` for a site not listed
PALPATION_SD_BY_SITE = {k: v * 1e-3 / np.sqrt(2.0) for k, v in {
    "ASI": 8.0, "PSI": 10.0, "TRO": 15.0, "KNE": 10.0, "MFC": 10.0, "TTB": 7.0, "HFB": 9.0, "ANK": 5.0,
    "MMA": 5.0, "HEE": 8.0, "LCA": 8.0, "D1M": 5.0, "D5M": 5.0, "P1M": 7.0, "P5M": 7.0, "TOE": 6.0}.items()}


def palpation_sd(marker: str) -> float:
    """`PALPATION_SD_BY_SITE` of a marker's site (``"RTRO"`` -> TRO; ``SACR`` lies over the PSIS)."""
    m = str(marker).upper()
    m = {"SACR": "PSI"}.get(m, m)
    if len(m) > 1 and m[0] in "RL" and m[1:] in PALPATION_SD_BY_SITE:
        return float(PALPATION_SD_BY_SITE[m[1:]])
    return float(PALPATION_SD_BY_SITE.get(m, PALPATION_SD))

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
    tissue_scale, tissue_scale_log_sd : soft-tissue scale k estimated with the pose and the sd of ln k
        (None: not estimated); tissue : marker -> (thickness, sd) m of the estimated soft tissue
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
    tissue_scale: float | None = None
    tissue_scale_log_sd: float = 0.0
    tissue: dict = field(default_factory=dict)

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

    def as_matrix(self) -> np.ndarray:
        """(4, 4) homogeneous scanner -> lab map [[R, t], [0, 1]]."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T

    def shifted(self, d) -> "Registration":
        """The map translated by d (3,) m in the lab: t + d, its pivot `centre` moved with it (so `cov` still
        describes the same error) and the residuals those of the moved map; chi2 and the Mahalanobis distances
        stay the fit's, which judged the correspondences before the shift."""
        d = np.asarray(d, float).reshape(3)
        return replace(self, t=self.t + d, centre=self.centre + d, residuals=self.residuals - d)

    def _jacobian(self, y: np.ndarray) -> np.ndarray:
        """∂y/∂x (3, 6) of a transferred lab point y: [-[y - c]×, I]."""
        return np.hstack([-skew(y - self.centre), np.eye(3)])

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

    def transfer_estimate(self, estimate: Gaussian) -> Gaussian:
        """`transfer_point` of a scanner-frame `Gaussian`: N(R x + t, J Cov(x) Jᵀ + R C Rᵀ)."""
        return Gaussian(*self.transfer_point(estimate.mean, estimate.cov))

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
        S = skew(u2)
        s = np.radians(float(sd_deg))
        C = S @ self.cov[:3, :3] @ S.T + s * s * (np.eye(3) - np.outer(u2, u2))
        C = 0.5 * (C + C.T)
        return u2, _tangent_sd_deg(C), C

    def summary(self) -> dict:
        """JSON-ready summary (SI units)."""
        return {
            "segment": self.segment, "units": "m, rad", "R": self.R.tolist(), "t": self.t.tolist(),
            "cov": self.cov.tolist(), "centre": self.centre.tolist(), "used": list(self.names),
            "rejected": {k: float(v) for k, v in self.rejected.items()}, "rms": self.rms,
            "chi2": self.chi2, "dof": self.dof, "p_value": self.p_value, "inflation": self.inflation,
            "rotation_sd_deg": self.rotation_sd_deg.tolist(), "translation_sd": self.translation_sd.tolist(),
            "notes": list(self.notes),
            **({"tissue_scale": self.tissue_scale, "tissue_scale_log_sd": self.tissue_scale_log_sd,
                "tissue": {k: {"thickness": v[0], "sd": v[1]} for k, v in self.tissue.items()}}
               if self.tissue_scale is not None else {}),
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
        S = skew(y - o)
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


#: Levenberg-Marquardt controls of `_fit`: initial damping relative to max diag(H), the factor it is divided by
#: on an accepted step (multiplied by on a rejected one), the largest damping before giving up, and the
#: convergence tests (relative χ² decrease, largest step component in rad or m).  Values chosen so that
#: a well-posed fit ends where the former 50 undamped Gauss-Newton iterations did (to ~1e-10).
LM_LAMBDA0 = 1e-3
LM_FACTOR = 10.0
LM_LAMBDA_MAX = 1e16
LM_RTOL = 1e-14
LM_XTOL = 1e-13
#: the relative-χ² test stops only once the step is also below this (rad or m): χ² is quadratic near the
#: minimum, so a 1e-14 relative change alone would stop about 1e-7 short of it
LM_XTOL_RTOL = 1e-10


def _pose_terms(Q, M, Cq, Cm, R, t, c, n: int = 6):
    """r = M - (R Q + t), Σ = R C_q Rᵀ + C_m, W = Σ⁻¹ and the (K, 3, n) Jacobian with its pose columns
    [-[y - c]×, I] filled (columns 6.. left for extra parameters)."""
    S = np.einsum("ij,kjl,ml->kim", R, Cq, R) + Cm
    W = np.linalg.inv(S)
    y = Q @ R.T + t
    J = np.zeros((len(Q), 3, n))
    J[:, :, :3] = -skew(y - c)
    J[:, :, 3:6] = np.eye(3)
    return M - y, S, W, J


def _information(J, W, r):
    """H = JᵀWJ, g = JᵀWr, χ² = rᵀWr summed over the points."""
    return (np.einsum("kai,kab,kbj->ij", J, W, J), np.einsum("kai,kab,kb->i", J, W, r),
            float(np.einsum("ka,kab,kb->", r, W, r)))


def _linearise(Q, M, Cq, Cm, R, t, c):
    """Residuals, noise, Jacobian, information and gradient at (R, t): r, Σ, J, H = JᵀWJ, g = JᵀWr, χ²."""
    r, S, W, J = _pose_terms(Q, M, Cq, Cm, R, t, c)
    H, g, chi2 = _information(J, W, r)
    return r, S, J, H, g, chi2


def _step(R, t, c, dx):
    """Apply the increment x = (ω, δ): y ← c + exp([ω]×)(y - c) + δ, i.e. R ← dR R, t ← c + dR (t - c) + δ."""
    dR = Rotation.from_rotvec(dx[:3]).as_matrix()
    return dR @ R, c + dR @ (t - c) + dx[3:]


def _levenberg_marquardt(state, linearise, step, trial_chi2, max_iter: int):
    """The damped loop of `_fit` over any parameter `state`: returns the final state and its linearisation.

    ``linearise(state) -> (r, Σ, J, H, g, χ²)``, ``step(state, dx) -> state``, ``trial_chi2(state, W) -> χ²``
    (Σ held at the current estimate).  See `_fit` for the rules.
    """
    r, S, J, H, g, chi2 = linearise(state)
    W = np.linalg.inv(S)
    lam = LM_LAMBDA0 * float(np.max(np.diag(H)))
    for _ in range(max_iter):
        D = np.diag(np.diag(H))
        dx = np.linalg.lstsq(H + lam * D, g, rcond=None)[0]
        state1 = step(state, dx)
        chi2_1 = trial_chi2(state1, W)
        small = np.max(np.abs(dx)) < LM_XTOL
        if chi2_1 <= chi2:
            decrease = chi2 - chi2_1
            state = state1
            r, S, J, H, g, chi2 = linearise(state)
            W = np.linalg.inv(S)
            lam /= LM_FACTOR
            if small or (decrease <= LM_RTOL * max(chi2, 1e-300) and np.max(np.abs(dx)) < LM_XTOL_RTOL):
                break
        else:
            if small:
                break
            lam *= LM_FACTOR
            if lam > LM_LAMBDA_MAX * float(np.max(np.diag(H))):
                break
    return state, (r, S, J, H, g, chi2)


def _fit(Q, M, Cq, Cm, *, max_iter: int = 100, R0=None, t0=None):
    """Levenberg-Marquardt on χ² = Σ r_kᵀ Σ_k⁻¹ r_k; returns R, t, c, H (information), r, Σ, J.

    Each step solves (H + λ diag H) x = g (H = JᵀWJ, g = JᵀWr, Marquardt's
    scaling, so rad and m are commensurate) and is accepted only if χ²
    decreases with Σ_k held at the current rotation (the same linearisation
    as Gauss-Newton, so the fixed point g = 0 is Gauss-Newton's); then
    λ ← λ / 10 and Σ_k is re-evaluated, else λ ← 10 λ and the step is
    retried.  Stops when a step is below `LM_XTOL`, or an accepted one
    changes χ² by less than `LM_RTOL` relative (with the step below
    `LM_XTOL_RTOL`), or λ exceeds `LM_LAMBDA_MAX` max diag H (no decrease
    possible: the current point is kept).  Near the optimum λ → 0 and the
    steps are Gauss-Newton's, so a well-posed problem reaches the same
    minimum.  Undamped Gauss-Newton from the same start can diverge when the
    linearisation is poor (large residuals, mislabelled markers): see
    tests/test_registration.py::test_damped_fit_cannot_diverge.  Start:
    weighted Kabsch/Horn, or R0, t0 when given.
    """
    w0 = 1.0 / np.trace(Cq + Cm, axis1=1, axis2=2)
    if R0 is None:
        R, t = kabsch(Q, M, w0)
    else:
        R, t = np.asarray(R0, float), np.asarray(t0, float)
    c = (w0 @ M) / w0.sum()

    def trial(st, W):
        r1 = M - (Q @ st[0].T + st[1])
        return float(np.einsum("ka,kab,kb->", r1, W, r1))

    (R, t), (r, S, J, H, _, _) = _levenberg_marquardt(
        (R, t), lambda st: _linearise(Q, M, Cq, Cm, st[0], st[1], c), lambda st, dx: _step(st[0], st[1], c, dx),
        trial, max_iter)
    return R, t, c, H, r, S, J


@dataclass(frozen=True)
class _Tissue:
    """Offsets of skin markers whose soft tissue is estimated with one scale k = exp(u) (`register_landmarks`).

    Point k sits at q_k(u) = p_k + (f_k + e^u μ_k) n_k: f_k the fixed part (marker radius, tissue not
    estimated), μ_k the prior tissue scaled (0: not scaled); its variance along n_k is s_k² + (e^u μ_k σ_s)²
    and across n_k (d_k(u) σ_n,k)² + σ_p,k² (σ_p,k the point's palpation sd); ln k ~ N(u₀, σ_u²).
    """

    P: np.ndarray
    N: np.ndarray
    fixed: np.ndarray
    mu: np.ndarray
    sd_fixed: np.ndarray
    site_log_sd: float
    normal_sd: np.ndarray
    C0: np.ndarray
    u0: float
    su: float
    palp: np.ndarray

    def take(self, idx) -> "_Tissue":
        return _Tissue(self.P[idx], self.N[idx], self.fixed[idx], self.mu[idx], self.sd_fixed[idx], self.site_log_sd,
                       self.normal_sd[idx], self.C0[idx], self.u0, self.su, self.palp[idx])

    def points(self, u: float) -> np.ndarray:
        return self.P + (self.fixed + np.exp(u) * self.mu)[:, None] * self.N

    def covs(self, u: float) -> np.ndarray:
        k = np.exp(u)
        d = self.fixed + k * self.mu
        sd2 = self.sd_fixed ** 2 + (k * self.mu * self.site_log_sd) ** 2
        nn = np.einsum("ki,kj->kij", self.N, self.N)
        across = (d * self.normal_sd) ** 2 + self.palp ** 2
        return self.C0 + sd2[:, None, None] * nn + across[:, None, None] * (np.eye(3) - nn) + 1e-12 * np.eye(3)


def _linearise_tissue(tis: _Tissue, M, Cm, R, t, u, c):
    """`_linearise` of the 7 parameters (ω, δ, u = ln k) with the prior on u as one more residual."""
    r, S, W, J = _pose_terms(tis.points(u), M, tis.covs(u), Cm, R, t, c, n=7)
    J[:, :, 6] = (np.exp(u) * tis.mu)[:, None] * (tis.N @ R.T)
    H, g, chi2 = _information(J, W, r)
    H[6, 6] += 1.0 / tis.su ** 2
    g[6] += (tis.u0 - u) / tis.su ** 2
    return r, S, J, H, g, chi2 + ((u - tis.u0) / tis.su) ** 2


def _fit_tissue(tis: _Tissue, M, Cm, *, max_iter: int = 100):
    """`_fit` with the tissue scale u = ln k as a seventh parameter: returns R, t, u, c, H (7x7), r, Σ, J.

    Minimises χ² = Σ r_kᵀ Σ_k(u)⁻¹ r_k + ((u - u₀)/σ_u)², r_k = m_k - (R q_k(u) + t), by the same damped
    loop (Σ held at the current estimate within a step); started at u₀ from weighted Kabsch/Horn.
    """
    Q0, C0 = tis.points(tis.u0), tis.covs(tis.u0)
    w0 = 1.0 / np.trace(C0 + Cm, axis1=1, axis2=2)
    R, t = kabsch(Q0, M, w0)
    c = (w0 @ M) / w0.sum()

    def step(st, dx):
        R1, t1 = _step(st[0], st[1], c, dx[:6])
        return R1, t1, st[2] + float(dx[6])

    def trial(st, W):
        r1 = M - (tis.points(st[2]) @ st[0].T + st[1])
        return float(np.einsum("ka,kab,kb->", r1, W, r1)) + ((st[2] - tis.u0) / tis.su) ** 2

    (R, t, u), (r, S, J, H, _, _) = _levenberg_marquardt(
        (R, t, tis.u0), lambda st: _linearise_tissue(tis, M, Cm, st[0], st[1], st[2], c), step, trial, max_iter)
    return R, t, u, c, H, r, S, J


def register_landmarks(mri_points, marker_points, mri_cov=None, marker_sd=MARKER_PLACEMENT_SD, normals=None,
                       offset=SKIN_THICKNESS + DEFAULT_MARKER_RADIUS, *, offset_sd: float = SKIN_THICKNESS_SD,
                       normal_sd_deg: float | np.ndarray = SURFACE_NORMAL_SD_DEG, names=None,
                       k_outlier: float = 3.0, min_points: int = 3, segment: str | None = None,
                       tissue=None, tissue_prior=None, palpation_sd=None, fixed=()) -> Registration:
    """Weighted rigid registration of MRI landmarks to marker centres, with outlier rejection.

    See the module docstring for the model and the minimised χ².

    Soft tissue estimated with the pose (``tissue`` and ``tissue_prior`` given, `normals` needed): the
    tissue of point k is t_k = k μ_k (μ_k = ``tissue[k]``, the prior's mean, included in ``offset[k]``;
    0 for points whose offset is known), one scale k per call with the prior
    ln k ~ N(ln k₀, σ_k²) (`kinematics.gait.soft_tissue.TissueScalePrior`): the marker centres are

        m_k = R (p_k + (f_k + k μ_k) n_k) + t + ε_k,   f_k = offset_k - μ_k,

    and (ω, δ, ln k) minimise χ² + ((ln k - ln k₀)/σ_k)², the sd of t_k along n_k being k μ_k σ_site
    (the site's own departure from the scaled table) instead of ``offset_sd``, and such a marker's
    palpation `PALPATION_SD` across n_k added to its noise.  The inter-marker
    distances on the skin against those on the bone (ASIS to PSIS depth) identify k.  The 6x6 ``cov``
    is the pose block of the 7x7 inverse information (k's uncertainty included); ``tissue_scale``,
    ``tissue_scale_log_sd`` and ``tissue`` (name -> (t_k, sd) m) report the estimate.

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
    min_points : never go below this many correspondences (≥ 3; ≥ 4 with the tissue scale estimated)
    tissue : (K,) m prior tissue means to scale (0 where the offset is known), or None
    tissue_prior : `kinematics.gait.soft_tissue.TissueScalePrior` (median, log_sd, site_log_sd), or None
    palpation_sd : float or (K,) m, palpation sd across the normal of each point (0 for a point known in both
        frames; `palpation_sd` per marker site); None: `PALPATION_SD` for the points whose tissue is estimated
    fixed : names of points never rejected as outliers

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
    tis = None
    if normals is not None:
        N = np.asarray(normals, float).reshape(K, 3)
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
        d = np.broadcast_to(np.asarray(offset, float), (K,))
        ds = np.broadcast_to(np.asarray(offset_sd, float), (K,))
        ns = np.radians(np.broadcast_to(np.asarray(normal_sd_deg, float), (K,)))
        if tissue is not None and tissue_prior is not None:
            mu = np.broadcast_to(np.asarray(tissue, float), (K,)).copy()
            if np.any(mu < 0) or not np.all(np.isfinite(mu)):
                raise InputError(src, "prior tissue means must be finite and >= 0")
            if np.any(mu > 0):
                palp = (np.where(mu > 0, PALPATION_SD, 0.0) if palpation_sd is None
                        else np.broadcast_to(np.asarray(palpation_sd, float), (K,)).copy())
                tis = _Tissue(P, N, d - mu, mu, np.where(mu > 0, 0.0, ds), float(tissue_prior.site_log_sd), ns,
                              Cq.copy(), float(np.log(tissue_prior.median)), float(tissue_prior.log_sd), palp)
        Q = P + d[:, None] * N
        nn = np.einsum("ki,kj->kij", N, N)
        ps = np.zeros(K) if palpation_sd is None else np.broadcast_to(np.asarray(palpation_sd, float), (K,))
        Cq = Cq + ds[:, None, None] ** 2 * nn + ((d * ns) ** 2 + ps ** 2)[:, None, None] * (np.eye(3) - nn)
    # Floor so that exact inputs keep the information matrix invertible.
    Cq = Cq + 1e-12 * np.eye(3)

    spread = np.linalg.svd(Q - Q.mean(axis=0), compute_uv=False)
    if spread[1] < 1e-3:
        raise InputError(src, f"landmarks {', '.join(names)} are (nearly) collinear: the rotation about their line is undetermined")

    thr = float(stats.chi2.ppf(1.0 - 2.0 * stats.norm.sf(k_outlier), 3))
    if tis is not None:
        # three points with the tissue scale free leave two redundant equations: the fit of the others then
        # bends pose and scale round any point, and the one left out looks like an outlier (an obese pelvis's
        # RASI "rejected" at 5.6 sd, the pelvis rotated until RASI sat 128 mm off its bone)
        min_points = max(min_points, 4)
    keep = list(range(K))
    rejected: dict[str, float] = {}
    while len(keep) > min_points:
        d2 = np.full(len(keep), -np.inf)
        for j, k in enumerate(keep):
            others = [i for i in keep if i != k]
            sp = np.linalg.svd(Q[others] - Q[others].mean(axis=0), compute_uv=False)
            if sp[1] < 1e-3:
                continue
            if tis is None:
                R, t, c, H, _, _, _ = _fit(Q[others], M[others], Cq[others], Cm[others])
                y = R @ Q[k] + t
                Jk = np.hstack([-skew(y - c), np.eye(3)])
                Ck = Cq[k]
            else:
                R, t, u, c, H, _, _, _ = _fit_tissue(tis.take(others), M[others], Cm[others])
                one = tis.take([k])
                y = R @ one.points(u)[0] + t
                Jk = np.hstack([-skew(y - c), np.eye(3), (np.exp(u) * one.mu[0] * (R @ one.N[0]))[:, None]])
                Ck = one.covs(u)[0]
            S = R @ Ck @ R.T + Cm[k] + Jk @ np.linalg.inv(H) @ Jk.T
            r = M[k] - y
            d2[j] = r @ np.linalg.solve(S, r)
        j = int(np.argmax(d2))
        if d2[j] <= thr or names[keep[j]] in fixed:
            # the worst point is a constraint: the others are not to blame; the chi-square shows the conflict
            break
        rejected[names[keep[j]]] = float(np.sqrt(d2[j]))
        keep.pop(j)

    scale, scale_sd, tissue_out = None, 0.0, {}
    if tis is None:
        R, t, c, H, r, S, J = _fit(Q[keep], M[keep], Cq[keep], Cm[keep])
        prior_chi2 = 0.0
    else:
        sub = tis.take(keep)
        R, t, u, c, H7, r, S, J = _fit_tissue(sub, M[keep], Cm[keep])
        if np.linalg.cond(H7) > 1e14:
            raise InputError(src, "registration is degenerate: the landmarks do not fix all six degrees of freedom")
        C7 = np.linalg.inv(H7)
        scale, scale_sd = float(np.exp(u)), float(np.sqrt(C7[6, 6]))
        H = np.linalg.inv(C7[:6, :6])                  # information of the pose with k marginalised
        prior_chi2 = ((u - sub.u0) / sub.su) ** 2
        for i in range(K):
            if tis.mu[i] > 0:
                ti = scale * tis.mu[i]
                tissue_out[names[i]] = (ti, float(ti * np.hypot(scale_sd, tis.site_log_sd)))
    if np.linalg.cond(H) > 1e14:
        raise InputError(src, "registration is degenerate: the landmarks do not fix all six degrees of freedom")
    maha2 = np.einsum("ka,kab,kb->k", r, np.linalg.inv(S), r)
    chi2 = float(maha2.sum()) + float(prior_chi2)
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
    if scale is not None:
        notes.append(f"soft tissue estimated: {scale:.2f} x the site table (log sd {scale_sd:.2f}; prior "
                     f"{tissue_prior.median:.2f}, log sd {tissue_prior.log_sd:.2f}, {tissue_prior.basis})")
    return Registration(R, t, 0.5 * (cov + cov.T), c, tuple(names[i] for i in keep), rejected, r,
                        np.sqrt(maha2), chi2, dof, p, inflation, segment, tuple(notes), scale, scale_sd, tissue_out)


# --------------------------------------------------------------------------- per segment


def static_marker_positions(trial, names=None, placement_sd: float = MARKER_PLACEMENT_SD):
    """Robust static positions of markers and their measurement covariance.

    position = per-axis median over the finite frames; scatter = (1.4826 MAD)²
    per axis (the body's sway in the static trial), added to the placement
    variance: M = placement_sd² I + diag(scatter).

    Returns
    -------
    dict name -> `Gaussian` (position (3,) m, cov (3, 3) m²) for markers with ≥ 1 finite frame
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
        out[n] = Gaussian(med, placement_sd**2 * np.eye(3) + np.diag(mad**2))
    return out


def scaled_skin_prior(marker: str, k: float, log_sd: float) -> tuple[float, float]:
    """`skin_prior` (t0, sd0) times a subject's soft-tissue scale k (ln k with sd `log_sd`): (k t0, sd) m with
    sd² = (k sd0)² + (k t0 log_sd)²."""
    t0, sd0 = skin_prior(marker)
    return k * t0, float(np.hypot(k * sd0, k * t0 * log_sd))


def skin_prior(marker: str) -> tuple[float, float]:
    """Prior (mean, sd), m, of the soft tissue between `marker`'s bony landmark and the skin, along the bone normal.

    From the per-site table `kinematics.gait.soft_tissue.SOFT_TISSUE_THICKNESS` (ASIS 9.7 ± 7.0 mm,
    PSIS 19.6 ± 10.9 mm from pelvic CT, Mantovani et al. 2016; other sites assumed), else
    (`SKIN_THICKNESS`, `SKIN_THICKNESS_SD`).
    """
    p = tissue_prior(marker)
    return float(p.mean), float(p.sd)
