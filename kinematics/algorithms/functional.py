"""Functional joint centres and axes from the relative motion of two segments.

Inputs are segment poses (rotation R (F, 3, 3) segment -> lab, translation
t (F, 3) m), e.g. from `kinematics.algorithms.segments.rigid_pose` of marker clusters, or
marker trajectories expressed in the proximal segment frame.  Every estimator
returns its estimate with a covariance (first-order, from the residual
variance) and the rms residual.

- `sphere_fit` / `pivot_sphere_fit`: marker paths of the distal segment in the
  proximal frame lie on spheres about the joint centre (Gauss-Newton on the
  geometric distance, algebraic start).
- `centre_transformation`: the seed's centre transformation technique
  (Tändl et al. 2010, eqs. 30-37): the distal-fixed point whose path in the
  proximal frame has the least spread, optionally restricted to a plane.
- `score`: symmetrical centre of rotation estimation (Ehrig et al. 2006).
- `sara`: symmetrical axis of rotation approach (Ehrig et al. 2007).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.errors import FitError, InputError
from kinematics.io.markers import MarkerTrial

__all__ = ["SphereFit", "CentreEstimate", "AxisEstimate", "sphere_fit", "pivot_sphere_fit",
           "centre_transformation", "score", "sara", "relative_pose", "joint_centre_from_clusters"]


@dataclass(frozen=True)
class SphereFit:
    """centre (3,) m, radii (M,) m, cov (3, 3) m² of the centre, rms m, n points used."""

    centre: np.ndarray
    radii: np.ndarray
    cov: np.ndarray
    rms: float
    n_points: int

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))


@dataclass(frozen=True)
class CentreEstimate:
    """A functional joint centre.

    proximal : (3,) m, centre in the proximal segment frame
    distal : (3,) m, centre in the distal segment frame
    cov_proximal, cov_distal : (3, 3) m²
    rms : m, rms distance between the per-frame centre positions and their fit
    n_frames : frames used
    """

    proximal: np.ndarray
    distal: np.ndarray
    cov_proximal: np.ndarray
    cov_distal: np.ndarray
    rms: float
    n_frames: int

    @property
    def sd_proximal(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov_proximal))


@dataclass(frozen=True)
class AxisEstimate:
    """A functional hinge axis.

    point_proximal, direction_proximal : (3,) axis point (m) and unit direction in the proximal frame
    point_distal, direction_distal : same in the distal frame
    cov_point_proximal : (3, 3) m², covariance of the axis point
    direction_sd : rad, first-order angular sd of the axis direction
    rms : m ; condition : s₆/s₅, small for a well-defined axis
    """

    point_proximal: np.ndarray
    direction_proximal: np.ndarray
    point_distal: np.ndarray
    direction_distal: np.ndarray
    cov_point_proximal: np.ndarray
    direction_sd: float
    rms: float
    condition: float
    n_frames: int


def _check_poses(R, t, name):
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
        raise InputError(name, f"poses must be R (F, 3, 3) and t (F, 3), got {R.shape} and {t.shape}")
    return R, t


def relative_pose(R_prox, t_prox, R_dist, t_dist):
    """Distal pose in the proximal frame: R_i = R_pᵀ R_d, r_i = R_pᵀ (t_d - t_p)."""
    R_prox, t_prox = _check_poses(R_prox, t_prox, "proximal")
    R_dist, t_dist = _check_poses(R_dist, t_dist, "distal")
    Rr = np.einsum("fji,fjk->fik", R_prox, R_dist)
    rr = np.einsum("fji,fj->fi", R_prox, t_dist - t_prox)
    return Rr, rr


def _finite_frames(*arrays):
    ok = np.ones(arrays[0].shape[0], bool)
    for a in arrays:
        ok &= np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)
    return ok


# --------------------------------------------------------------------------- sphere fit


def pivot_sphere_fit(local: np.ndarray, *, max_iter: int = 50, tol: float = 1e-12) -> SphereFit:
    """Common centre of spheres traced by markers in the proximal frame.

    Model: marker m at frame f, p_fm = c + r_m u_fm + ε (‖u_fm‖ = 1).
    Minimises the geometric residual Σ_fm (‖p_fm - c‖ - r_m)² over c and the
    radii by Gauss-Newton with the analytic Jacobian
    ∂e/∂c = -(p - c)/‖p - c‖, ∂e/∂r_m = -1, started from the algebraic
    solution of 2 pᵀc + k_m = ‖p‖² (k_m = r_m² - ‖c‖²).

    Parameters
    ----------
    local : (F, M, 3) or (N, 3) m, NaN samples ignored

    Returns
    -------
    SphereFit, cov = σ² [(JᵀJ)⁻¹]_cc with σ² = RSS / (N - 3 - M)
    """
    p = np.asarray(local, float)
    if p.ndim == 2:
        p = p[:, None]
    if p.ndim != 3 or p.shape[2] != 3:
        raise InputError("sphere_fit", f"points must be (F, M, 3) or (N, 3), got {np.shape(local)}")
    F, M, _ = p.shape
    ok = np.all(np.isfinite(p), axis=2)
    pts = p[ok]
    idx = np.nonzero(ok)[1]
    n = len(pts)
    if n < 4 + M:
        raise FitError(f"sphere fit needs at least {4 + M} points, got {n}")
    # Algebraic start.
    A = np.zeros((n, 3 + M))
    A[:, :3] = 2 * pts
    A[np.arange(n), 3 + idx] = 1.0
    sol, *_ = np.linalg.lstsq(A, np.sum(pts**2, axis=1), rcond=None)
    c = sol[:3]
    r = np.array([np.mean(np.linalg.norm(pts[idx == m] - c, axis=1)) if np.any(idx == m) else np.nan for m in range(M)])
    if not np.all(np.isfinite(r)):
        raise FitError("a marker has no valid sample for the sphere fit")
    J = np.zeros((n, 3 + M))
    J[np.arange(n), 3 + idx] = -1.0
    for _ in range(max_iter):
        d = pts - c
        dist = np.linalg.norm(d, axis=1)
        e = dist - r[idx]
        J[:, :3] = -d / dist[:, None]
        step, *_ = np.linalg.lstsq(J, -e, rcond=None)
        c = c + step[:3]
        r = r + step[3:]
        if np.max(np.abs(step)) < tol:
            break
    d = pts - c
    dist = np.linalg.norm(d, axis=1)
    e = dist - r[idx]
    J[:, :3] = -d / dist[:, None]
    JtJ = J.T @ J
    if np.linalg.cond(JtJ) > 1e12:
        raise FitError("sphere fit is degenerate: the markers barely move about the joint")
    dof = max(n - 3 - M, 1)
    s2 = float(e @ e) / dof
    cov = s2 * np.linalg.inv(JtJ)[:3, :3]
    return SphereFit(c, r, cov, float(np.sqrt(np.mean(e**2))), n)


def sphere_fit(points: np.ndarray) -> SphereFit:
    """Least-squares sphere through points (N, 3): minimises Σ (‖p - c‖ - r)² (see `pivot_sphere_fit`)."""
    return pivot_sphere_fit(np.asarray(points, float).reshape(-1, 1, 3))


# --------------------------------------------------------------------------- centre transformation / SCoRE


def centre_transformation(R_prox, t_prox, R_dist, t_dist, *, basis: np.ndarray | None = None) -> CentreEstimate:
    """Centre transformation technique (Tändl et al. 2010, eqs. 30-37).

    A distal-fixed point x_d = B x (B (3, k) basis, k = 3 by default; the seed
    uses the plane z = 0 of the femur frame, B = [e₁ e₂]) has, in the proximal
    frame, the path h_i = R_i B x + r_i (R_i, r_i the relative pose).  The
    estimate minimises its spread about its centroid C = a + B̄ x::

        f(x) = Σ_i ‖(R_i B - B̄) x + (r_i - a)‖²,  a = mean r_i, B̄ = mean R_i B

    whose normal equations B₁ x = -a₁ (eq. 35) give x* = -B₁⁻¹ a₁ (eq. 36).

    Returns
    -------
    CentreEstimate: proximal = C, distal = B x*; cov from σ² B₁⁻¹ (σ² = f(x*)/(3m - k))
    """
    Rr, rr = relative_pose(R_prox, t_prox, R_dist, t_dist)
    ok = _finite_frames(Rr, rr)
    Rr, rr = Rr[ok], rr[ok]
    m = len(Rr)
    B = np.eye(3) if basis is None else np.asarray(basis, float).reshape(3, -1)
    k = B.shape[1]
    if m < 3:
        raise FitError(f"centre transformation needs at least 3 valid frames, got {m}")
    A = np.einsum("fij,jk->fik", Rr, B)  # (m, 3, k)
    Ac = A - A.mean(axis=0)
    bc = rr - rr.mean(axis=0)
    B1 = np.einsum("fik,fil->kl", Ac, Ac)
    a1 = np.einsum("fik,fi->k", Ac, bc)
    if np.linalg.cond(B1) > 1e12:
        raise FitError("centre transformation is degenerate: too little rotation between the segments")
    x = -np.linalg.solve(B1, a1)
    res = np.einsum("fik,k->fi", Ac, x) + bc
    s2 = float(np.sum(res**2)) / max(3 * m - k - 3, 1)
    cov_x = s2 * np.linalg.inv(B1)
    distal = B @ x
    proximal = rr.mean(axis=0) + A.mean(axis=0) @ x
    Abar = A.mean(axis=0)
    cov_prox = Abar @ cov_x @ Abar.T + s2 / m * np.eye(3)
    return CentreEstimate(proximal, distal, cov_prox, B @ cov_x @ B.T,
                          float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), m)


def _score_system(R_prox, t_prox, R_dist, t_dist):
    R_prox, t_prox = _check_poses(R_prox, t_prox, "proximal")
    R_dist, t_dist = _check_poses(R_dist, t_dist, "distal")
    ok = _finite_frames(R_prox, t_prox, R_dist, t_dist)
    R_prox, t_prox, R_dist, t_dist = R_prox[ok], t_prox[ok], R_dist[ok], t_dist[ok]
    m = len(R_prox)
    A = np.concatenate([R_prox, -R_dist], axis=2).reshape(3 * m, 6)
    b = (t_dist - t_prox).reshape(3 * m)
    return A, b, m


def score(R_prox, t_prox, R_dist, t_dist) -> CentreEstimate:
    """Symmetrical centre of rotation estimation, SCoRE (Ehrig et al. 2006).

    Model: one point fixed in both segments, c_p (proximal frame) and c_d
    (distal frame), coincides in the lab in every frame.  Minimises::

        Σ_i ‖(R_p,i c_p + t_p,i) - (R_d,i c_d + t_d,i)‖²

    a linear least-squares problem A [c_p; c_d] = t_d - t_p with A = [R_p  -R_d]
    stacked over frames; cov = σ² (AᵀA)⁻¹, σ² = RSS / (3m - 6).
    """
    A, b, m = _score_system(R_prox, t_prox, R_dist, t_dist)
    if m < 3:
        raise FitError(f"SCoRE needs at least 3 valid frames, got {m}")
    AtA = A.T @ A
    if np.linalg.cond(AtA) > 1e12:
        raise FitError("SCoRE is degenerate: the joint moved about one axis only (use SARA) or not at all")
    x = np.linalg.solve(AtA, A.T @ b)
    res = (A @ x - b).reshape(m, 3)
    s2 = float(np.sum(res**2)) / max(3 * m - 6, 1)
    cov = s2 * np.linalg.inv(AtA)
    return CentreEstimate(x[:3], x[3:], cov[:3, :3], cov[3:, 3:],
                          float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), m)


def sara(R_prox, t_prox, R_dist, t_dist) -> AxisEstimate:
    """Symmetrical axis of rotation approach, SARA (Ehrig et al. 2007).

    Model: the points of a hinge axis are fixed in both segments, so the SCoRE
    system A [c_p; c_d] = t_d - t_p (A = [R_p  -R_d]) has a one-dimensional
    null space: its right singular vector v₆ of the smallest singular value s₆
    gives the axis directions (v₆[:3] proximal, v₆[3:] distal).  The axis
    point is the minimum-norm least-squares solution over the other five
    singular directions::

        x = Σ_{j≤5} (u_jᵀ b / s_j) v_j,   cov = σ² Σ_{j≤5} v_j v_jᵀ / s_j²

    with σ² = RSS / (3m - 5).  The direction's first-order angular sd is
    σ_A / s₅ ·√2 with σ_A the noise of A estimated from s₆ (s₆² ≈ 3m σ_A²).
    """
    A, b, m = _score_system(R_prox, t_prox, R_dist, t_dist)
    if m < 3:
        raise FitError(f"SARA needs at least 3 valid frames, got {m}")
    U, S, Vt = np.linalg.svd(A, full_matrices=False)
    if S[4] < 1e-9 * S[0]:
        raise FitError("SARA is degenerate: too little rotation between the segments")
    coef = (U[:, :5].T @ b) / S[:5]
    x = Vt[:5].T @ coef
    res = (A @ x - b).reshape(m, 3)
    s2 = float(np.sum(res**2)) / max(3 * m - 5, 1)
    cov = s2 * (Vt[:5].T / S[:5] ** 2) @ Vt[:5]
    v = Vt[5]
    dp = v[:3] / np.linalg.norm(v[:3])
    dd = v[3:] / np.linalg.norm(v[3:])
    if dp @ np.array([0.0, 0.0, 1.0]) < 0:  # sign is arbitrary; point it along +z of the proximal frame
        dp, dd = -dp, -dd
    # Move the axis points to the foot of the perpendicular from the proximal origin.
    cp = x[:3] - (x[:3] @ dp) * dp
    cd = x[3:] - (x[3:] @ dd) * dd
    sigma_a = S[5] / np.sqrt(3 * m)
    direction_sd = float(np.sqrt(2.0) * sigma_a / S[4])
    P = np.eye(3) - np.outer(dp, dp)
    return AxisEstimate(cp, dp, cd, dd, P @ cov[:3, :3] @ P.T, direction_sd,
                        float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), float(S[5] / S[4]), m)


def joint_centre_from_clusters(trial: MarkerTrial, proximal_markers, distal_markers, method: str = "score",
                               *, weights_proximal=None, weights_distal=None):
    """Functional joint centre of two marker clusters of a trial.

    Each cluster's shape is its generalised-Procrustes mean over the trial
    (`cluster_reference`), its per-frame pose the Söderkvist-Wedin fit; the
    centre is then estimated by `method`: ``"score"``, ``"ctt"`` (centre
    transformation) or ``"sphere"`` (distal markers in the proximal frame).

    Returns
    -------
    (CentreEstimate, lab) : the estimate in the two cluster frames (whose
        origins are the cluster centroids, axes those of the most complete
        frame) and the centre's lab trajectory (F, 3) m, NaN where the
        proximal cluster has no pose.
    """
    from kinematics.algorithms.segments import cluster_reference, rigid_pose

    trial.require(list(proximal_markers) + list(distal_markers))
    if len(proximal_markers) < 3 or len(distal_markers) < 3:
        raise InputError(trial.source, "each cluster needs at least 3 markers")
    bp = trial.subset(proximal_markers).positions
    bd = trial.subset(distal_markers).positions
    try:
        ref_p, ref_d = cluster_reference(bp), cluster_reference(bd)
    except FitError as exc:
        raise InputError(trial.source, str(exc)) from None
    P = rigid_pose(ref_p, bp, weights_proximal)
    D = rigid_pose(ref_d, bd, weights_distal)
    if method == "score":
        est = score(P.R, P.t, D.R, D.t)
    elif method == "ctt":
        est = centre_transformation(P.R, P.t, D.R, D.t)
    elif method == "sphere":
        fit = pivot_sphere_fit(P.to_local(bd))
        lab = P.to_lab(fit.centre)
        local_d = D.to_local(lab)
        ok = np.all(np.isfinite(local_d), axis=1)
        M = np.einsum("fji,fjk->fik", D.R[ok], P.R[ok])  # proximal -> distal rotation per frame
        cov_d = np.mean(M @ fit.cov @ np.transpose(M, (0, 2, 1)), axis=0)
        est = CentreEstimate(fit.centre, local_d[ok].mean(axis=0), fit.cov, cov_d, fit.rms, int(ok.sum()))
    else:
        raise InputError("method", f"unknown functional method {method!r} (score, ctt, sphere)")
    return est, P.to_lab(est.proximal)
