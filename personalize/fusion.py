"""Gaussian fusion of MRI and motion estimates (Tändl et al. 2010, sec. 4.5).

Every joint parameter that both sources estimate (hip centre in the pelvis
frame, knee centre and axis in the femur frame, ankle axis, segment lengths,
correlative-law intercepts) is a Gaussian N(x_i, C_i) per source.  Their
product is the Gaussian of the information-weighted estimate

    P = Σ_i P_i,   P_i = C_i⁻¹,
    x = P⁻¹ Σ_i P_i x_i,   C = P⁻¹,

i.e. the minimiser of Σ_i (x - x_i)ᵀ P_i (x - x_i).  When sources observe
parts of a larger state with correlated errors (both hip centres of one MRI
share its pelvis registration error), `fuse_linear` solves the generalised
least-squares form: z_i = H_i x + e_i, e = (e_1, ..., e_n) ~ N(0, Σ) with Σ
full (cross-covariances), x = (Hᵀ Σ⁻¹ H)⁻¹ Hᵀ Σ⁻¹ z.  Source i receives the
matrix weight W_i = C P_i (Σ_i W_i = I, x = Σ_i W_i x_i) and the scalar share
tr(W_i) / d.  The same residual, χ² = Σ_i (x_i - x)ᵀ P_i (x_i - x) with
(n - 1) d degrees of freedom, tests whether the sources agree.

Directions live on the sphere: they are fused in the tangent plane at the
current mean (logarithmic map, each covariance parallel-transported there),
then mapped back (exponential map), iterated to the fixed point; the sign of
each axis is aligned first.

Per frame, segment poses of two kinematic chains (top-down Plug-in-Gait and
foot-to-hip) are blended with the same Gaussian weights, each chain's pose
error variance taken as its marker residual squared:
w_b = r_a² / (r_a² + r_b²), R = R_a exp(w_b log(R_aᵀ R_b)) (the weighted
geodesic mean on SO(3)), t = (1 - w_b) t_a + w_b t_b.  That part lives in
`kinematics.gait.chain_blend` (the marker-driven side uses it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian

__all__ = ["Fused", "FusedAxis", "as_gaussian", "as_axis", "fuse_gaussian", "fuse_intersection", "fuse_linear", "fuse_axis",
           "fuse_axes", "fusion_monte_carlo"]


@dataclass(frozen=True)
class Fused:
    """Product of Gaussian estimates.

    mean : (d,) fused estimate; cov : (d, d) its covariance
    weights : (n, d, d) matrix weights W_i = C C_i⁻¹ (sum to I)
    shares : (n,) scalar weight of each source, tr(W_i) / d (sum to 1)
    chi2, dof, p_value : agreement of the sources (small p: they disagree)
    names : source names
    """

    mean: np.ndarray
    cov: np.ndarray
    weights: np.ndarray
    shares: np.ndarray
    chi2: float
    dof: int
    p_value: float
    names: tuple[str, ...]

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def gaussian(self) -> Gaussian:
        """The fused estimate N(mean, cov)."""
        return Gaussian(self.mean, self.cov)

    @property
    def consistent(self) -> bool:
        """False when the sources disagree beyond their covariances (p < 0.01)."""
        return self.p_value >= 0.01

    def summary(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.cov.tolist(), "sd": self.sd.tolist(),
                "weights": dict(zip(self.names, self.shares.tolist())), "chi2": self.chi2,
                "dof": self.dof, "p_value": self.p_value, "consistent": self.consistent}


def _as_cov(c, d: int, name: str) -> np.ndarray:
    c = np.asarray(c, float)
    if c.ndim == 0:  # a variance for a scalar, or an isotropic variance
        c = float(c) * np.eye(d)
    c = c.reshape(d, d) if c.size == d * d else c
    if c.shape != (d, d) or not np.all(np.isfinite(c)):
        raise InputError(name, f"covariance must be a finite {d}x{d} matrix, got shape {c.shape}")
    c = 0.5 * (c + c.T)
    if np.linalg.eigvalsh(c)[0] <= 0:
        raise InputError(name, "covariance is not positive definite (a source cannot be exact)")
    return c


def as_gaussian(estimate, *, frame: str = "proximal"):
    """(mean, cov) of any estimate the project produces.

    Accepts a `lowerlimb.estimates.Gaussian` (or a value holding one: a `personalize.landmarks.Landmark`,
    a `Fused`, a `personalize.frames.Joint`), a ``(mean, cov)`` pair, a `kinematics.algorithms.functional.CentreEstimate`
    (``frame`` "proximal" or "distal"), a `SphereFit` (centre, cov), a
    landmarks.json landmark ``{"position", "cov"}`` or a joints.json joint
    ``{"origin", "origin_cov"}``.
    """
    if isinstance(estimate, tuple) and len(estimate) == 2:
        return estimate
    if isinstance(estimate, Gaussian):
        return estimate.mean, estimate.cov
    if isinstance(getattr(estimate, "gaussian", None), Gaussian):     # a landmark, a fused estimate
        return estimate.gaussian.mean, estimate.gaussian.cov
    if isinstance(getattr(estimate, "centre", None), Gaussian):       # a `personalize.frames.Joint`
        return estimate.centre.mean, estimate.centre.cov
    if isinstance(estimate, dict):
        if "position" in estimate and "cov" in estimate:
            return np.asarray(estimate["position"], float), np.asarray(estimate["cov"], float)
        if "origin" in estimate and "origin_cov" in estimate:
            return np.asarray(estimate["origin"], float), np.asarray(estimate["origin_cov"], float)
    if hasattr(estimate, "cov_proximal"):
        if frame not in ("proximal", "distal"):
            raise InputError("frame", f"frame must be 'proximal' or 'distal', got {frame!r}")
        return getattr(estimate, frame), getattr(estimate, f"cov_{frame}")
    if hasattr(estimate, "centre") and hasattr(estimate, "cov"):
        return estimate.centre, estimate.cov
    raise InputError("fusion", f"cannot read a mean and covariance from {type(estimate).__name__}")


def _information_form(estimates, names):
    """(names, means (n, d), information matrices (n, d, d)) of the estimates, checked (one-line errors)."""
    est = [as_gaussian(e) for e in estimates]
    if not est:
        raise InputError("fusion", "nothing to fuse")
    names = tuple(names) if names is not None else tuple(f"source{i}" for i in range(len(est)))
    if len(names) != len(est):
        raise InputError("fusion", f"{len(names)} names for {len(est)} estimates")
    xs = [np.atleast_1d(np.asarray(m, float)).ravel() for m, _ in est]
    d = xs[0].size
    for n, x in zip(names, xs):
        if x.size != d or not np.all(np.isfinite(x)):
            raise InputError(n, f"estimate must be {d} finite numbers, got {x}")
    return names, np.array(xs), np.array([np.linalg.inv(_as_cov(c, d, n)) for (_, c), n in zip(est, names)])


def fuse_gaussian(estimates, names=None) -> Fused:
    """Information-weighted fusion (product of Gaussians) of n ≥ 1 estimates.

    Model: x_i = x + e_i, e_i ~ N(0, C_i) independent.  Minimises
    Σ_i (x - x_i)ᵀ C_i⁻¹ (x - x_i), so that

        C = (Σ_i C_i⁻¹)⁻¹,   x = C Σ_i C_i⁻¹ x_i,   W_i = C C_i⁻¹.

    Parameters
    ----------
    estimates : sequence of (mean, cov): mean a scalar or (d,), cov a variance
        (scalar, isotropic) or (d, d) matrix, same units as the mean squared;
        or any object `as_gaussian` reads (CentreEstimate, landmark dict, ...)
    names : source names (default "source0", ...)

    Returns
    -------
    Fused
    """
    names, xs, Ps = _information_form(estimates, names)
    d = xs.shape[1]
    P = Ps.sum(axis=0)
    C = np.linalg.inv(P)
    C = 0.5 * (C + C.T)
    x = C @ np.einsum("nij,nj->i", Ps, np.array(xs))
    W = np.einsum("ij,njk->nik", C, Ps)
    shares = np.trace(W, axis1=1, axis2=2) / d
    r = np.array(xs) - x
    chi2 = float(np.einsum("ni,nij,nj->", r, Ps, r))
    dof = (len(xs) - 1) * d
    p = float(stats.chi2.sf(chi2, dof)) if dof > 0 else 1.0
    return Fused(x, C, W, shares, chi2, dof, p, names)


def fuse_intersection(estimates, names=None) -> Fused:
    """Covariance intersection (Julier & Uhlmann 1997) of n ≥ 1 estimates whose errors correlate by an unknown
    amount: the MRI and motion knee (ankle) centres both rest on the same palpated epicondyle (malleolus) markers,
    so their product (`fuse_gaussian`) states a covariance half as large as the truth allows.

        C⁻¹ = Σ_i ω_i C_i⁻¹,   x = C Σ_i ω_i C_i⁻¹ x_i,   ω_i ≥ 0, Σ ω_i = 1,

    ω minimising det C (Nelder-Mead on the simplex's softmax coordinates; for two estimates a bounded scalar
    search).  C is consistent (covers the error) for any cross-correlation when each C_i is.  Weights W_i, shares,
    chi² and p as `fuse_gaussian` reports them, the chi² of the sources against the intersection.
    """
    from scipy.optimize import minimize, minimize_scalar

    names, xs, Ps = _information_form(estimates, names)
    d = xs.shape[1]

    def logdet(w):
        return -float(np.linalg.slogdet(np.einsum("n,nij->ij", w, Ps))[1])

    n = len(xs)
    if n == 1:
        w = np.ones(1)
    elif n == 2:
        r = minimize_scalar(lambda a: logdet(np.array([a, 1.0 - a])), bounds=(0.0, 1.0), method="bounded",
                            options={"xatol": 1e-6})
        w = np.array([r.x, 1.0 - r.x])
    else:
        soft = lambda z: np.exp(z - z.max()) / np.exp(z - z.max()).sum()      # noqa: E731
        w = soft(minimize(lambda z: logdet(soft(z)), np.zeros(n), method="Nelder-Mead").x)
    P = np.einsum("n,nij->ij", w, Ps)
    C = np.linalg.inv(P)
    C = 0.5 * (C + C.T)
    x = C @ np.einsum("n,nij,nj->i", w, Ps, xs)
    W = np.einsum("ij,n,njk->nik", C, w, Ps)
    shares = np.trace(W, axis1=1, axis2=2) / d
    rr = xs - x
    chi2 = float(np.einsum("ni,nij,nj->", rr, Ps, rr))
    dof = (n - 1) * d
    p = float(stats.chi2.sf(chi2, dof)) if dof > 0 else 1.0
    return Fused(x, C, W, shares, chi2, dof, p, names)


def fuse_linear(observations, names=None, *, cross=None) -> Fused:
    """Generalised least-squares fusion of sources that observe (parts of) one state with correlated errors.

    Model: z_i = H_i x + e_i (i = 1..n), e = (e_1, ..., e_n) ~ N(0, Σ) where Σ
    has the blocks Σ_ii = C_i and Σ_ij = ``cross[(i, j)]`` (zero unless given).
    Minimises (z - H x)ᵀ Σ⁻¹ (z - H x) over x (z, H stacked), so that

        C = (Hᵀ Σ⁻¹ H)⁻¹,   x = C Hᵀ Σ⁻¹ z = Σ_i K_i z_i,

    K_i the column block of C Hᵀ Σ⁻¹ belonging to source i.  Source i's
    matrix weight is W_i = K_i H_i (Σ_i W_i = I, so x = Σ_i W_i x when every
    source agrees) and its share tr(W_i) / d.  With one H_i = I per source
    and no cross-covariance this is `fuse_gaussian`.  χ² = rᵀ Σ⁻¹ r
    (r = z - H x) with Σ_i d_i - d degrees of freedom tests agreement.

    Parameters
    ----------
    observations : sequence of (z_i, C_i) or (z_i, C_i, H_i): z_i (d_i,), C_i (d_i, d_i),
        H_i (d_i, d) (default identity, d_i = d)
    names : source names (default "source0", ...)
    cross : dict {(i, j): (d_i, d_j) cross-covariance of e_i and e_j}, i != j

    Returns
    -------
    Fused (weights (n, d, d), shares (n,))
    """
    obs = list(observations)
    if not obs:
        raise InputError("fusion", "nothing to fuse")
    names = tuple(names) if names is not None else tuple(f"source{i}" for i in range(len(obs)))
    if len(names) != len(obs):
        raise InputError("fusion", f"{len(names)} names for {len(obs)} observations")
    zs, Cs, Hs = [], [], []
    for o, nm in zip(obs, names):
        z = np.atleast_1d(np.asarray(o[0], float)).ravel()
        H = np.eye(z.size) if len(o) < 3 or o[2] is None else np.atleast_2d(np.asarray(o[2], float))
        if H.shape[0] != z.size or not np.all(np.isfinite(z)):
            raise InputError(nm, f"observation must be {H.shape[0]} finite numbers matching H {H.shape}, got {z}")
        zs.append(z)
        Cs.append(_as_cov(o[1], z.size, nm))
        Hs.append(H)
    d = Hs[0].shape[1]
    if any(H.shape[1] != d for H in Hs):
        raise InputError("fusion", "every H_i must have the same number of columns (the state size)")
    off = np.cumsum([0] + [z.size for z in zs])
    S = np.zeros((off[-1], off[-1]))
    for i, C in enumerate(Cs):
        S[off[i]:off[i + 1], off[i]:off[i + 1]] = C
    for (i, j), X in (cross or {}).items():
        X = np.asarray(X, float)
        if i == j or X.shape != (zs[i].size, zs[j].size):
            raise InputError("fusion", f"cross-covariance ({i}, {j}) must be {zs[i].size}x{zs[j].size} between two sources")
        S[off[i]:off[i + 1], off[j]:off[j + 1]] = X
        S[off[j]:off[j + 1], off[i]:off[i + 1]] = X.T
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise InputError("fusion", "the joint error covariance (with cross-covariances) is not positive definite") from None
    z, H = np.concatenate(zs), np.vstack(Hs)
    Si_H = np.linalg.solve(L.T, np.linalg.solve(L, H))
    info = H.T @ Si_H
    if np.linalg.cond(info) > 1e14:
        raise InputError("fusion", "the observations do not determine every state component")
    C = np.linalg.inv(info)
    C = 0.5 * (C + C.T)
    K = C @ Si_H.T  # (d, Σ d_i)
    x = K @ z
    W = np.array([K[:, off[i]:off[i + 1]] @ Hs[i] for i in range(len(zs))])
    r = z - H @ x
    chi2 = float(r @ np.linalg.solve(L.T, np.linalg.solve(L, r)))
    dof = int(off[-1] - d)
    p = float(stats.chi2.sf(chi2, dof)) if dof > 0 else 1.0
    return Fused(x, C, W, np.trace(W, axis1=1, axis2=2) / d, chi2, dof, p, names)


def fusion_monte_carlo(cov_a, cov_b, *, n: int = 20000, seed: int = 0, bias_a=None, bias_b=None) -> dict:
    """How often Gaussian fusion of two sources beats both, for given error distributions.

    Draws e_a ~ N(b_a, C_a), e_b ~ N(b_b, C_b) independently, fuses them with the
    weights of `fuse_gaussian` (C_a, C_b taken as the sources' covariances) and
    counts the draws where ‖e_fused‖ < min(‖e_a‖, ‖e_b‖).  The upper bound of
    the fraction of legs a fusion can win when the errors really have these
    distributions (units of the covariances' square roots).

    Returns
    -------
    dict: fraction_below_both, fraction_below_a, median_a, median_b, median_fused
    """
    Ca, Cb = _as_cov(cov_a, 3, "cov_a"), _as_cov(cov_b, 3, "cov_b")
    rng = np.random.default_rng(seed)
    ea = rng.multivariate_normal(np.zeros(3) if bias_a is None else bias_a, Ca, n)
    eb = rng.multivariate_normal(np.zeros(3) if bias_b is None else bias_b, Cb, n)
    Pa, Pb = np.linalg.inv(Ca), np.linalg.inv(Cb)
    C = np.linalg.inv(Pa + Pb)
    ef = ea @ (C @ Pa).T + eb @ (C @ Pb).T
    na, nb, nf = (np.linalg.norm(e, axis=1) for e in (ea, eb, ef))
    return {"fraction_below_both": float(np.mean(nf < np.minimum(na, nb))), "fraction_below_a": float(np.mean(nf < na)),
            "median_a": float(np.median(na)), "median_b": float(np.median(nb)), "median_fused": float(np.median(nf)),
            "n": n}


# --------------------------------------------------------------------------- axes


@dataclass(frozen=True)
class FusedAxis:
    """Fused axis.

    direction : (3,) unit; sd_deg : 1-sd angle √(tr cov / 2) in degrees
    cov : (3, 3) rad², tangent-plane covariance of the direction
    shares : (n,) scalar weight of each source; flipped : (n,) bool, sources whose sign was reversed
    chi2, dof, p_value : agreement of the directions (dof = 2 (n - 1))
    point, point_cov : fused axis point (m) and covariance (across the axis), or None
    """

    direction: np.ndarray
    sd_deg: float
    cov: np.ndarray
    shares: np.ndarray
    flipped: np.ndarray
    chi2: float
    dof: int
    p_value: float
    names: tuple[str, ...]
    point: np.ndarray | None = None
    point_cov: np.ndarray | None = None

    @property
    def consistent(self) -> bool:
        return self.p_value >= 0.01


def _tangent_basis(u: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane ⟂ u."""
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1)], axis=1)


def _log(ref: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Logarithmic map of the sphere at ref: tangent vector (3,) of length = angle."""
    c = np.clip(u @ ref, -1.0, 1.0)
    v = u - c * ref
    s = np.linalg.norm(v)
    return np.zeros(3) if s < 1e-15 else np.arctan2(s, c) * v / s


def _exp(ref: np.ndarray, v: np.ndarray) -> np.ndarray:
    a = np.linalg.norm(v)
    return ref if a < 1e-15 else np.cos(a) * ref + np.sin(a) * v / a


def _transport(cov: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Parallel transport of a tangent covariance at u to the tangent plane at v
    (the minimal rotation taking u to v, about u × v)."""
    w = np.cross(u, v)
    s = np.linalg.norm(w)
    if s < 1e-15:
        return cov
    Rm = Rotation.from_rotvec(w / s * np.arctan2(s, u @ v)).as_matrix()
    return Rm @ cov @ Rm.T


def _direction_cov(sd, u: np.ndarray, name: str) -> np.ndarray:
    """Tangent covariance (3, 3) rad² from an sd in degrees or a 3x3 covariance (rad²)."""
    s = np.asarray(sd, float)
    Pu = np.eye(3) - np.outer(u, u)
    if s.ndim == 0:
        if not np.isfinite(s) or s <= 0:
            raise InputError(name, f"axis sd must be a positive number of degrees, got {sd}")
        return np.radians(float(s)) ** 2 * Pu
    if s.shape != (3, 3):
        raise InputError(name, f"axis uncertainty must be an sd in degrees or a 3x3 covariance, got shape {s.shape}")
    return Pu @ (0.5 * (s + s.T)) @ Pu


def fuse_axis(directions, sd_deg, names=None, points=None, point_covs=None, *, max_iter: int = 50) -> FusedAxis:
    """Fuse axis directions (and optionally axis points) as Gaussians on the sphere.

    Model: u_i = exp_u(e_i), e_i ~ N(0, Σ_i) in the tangent plane at the true
    axis u (Σ_i = σ_i² (I - uuᵀ) for an sd σ_i).  Signs are aligned with the
    most precise source (an axis has no preferred sense).  At the current
    mean ū, with B (3x2) a tangent basis, v_i = Bᵀ log_ū(u_i) with the
    covariances Bᵀ T_i Σ_i T_iᵀ B (T_i the parallel transport u_i → ū) are fused as
    2-D Gaussians (`fuse_gaussian`) and ū ← exp_ū(B v̄) until v̄ = 0: the
    Karcher mean under the Mahalanobis metric.

    Axis points are determined only across the axis: each point's
    information is restricted to the plane ⟂ ū, P_i = Π (Π C_i Π)⁺ Π
    (Π = I - ūūᵀ), fused as x = (Σ P_i)⁺ Σ P_i x_i, which is the point of the
    fused line nearest to the others' foot points.

    Parameters
    ----------
    directions : (n, 3) directions (any length, any sense)
    sd_deg : n entries, each an sd in degrees or a 3x3 tangent covariance in rad²
    points : (n, 3) m or None; point_covs : (n, 3, 3) m² or None

    Returns
    -------
    FusedAxis
    """
    U = np.asarray(directions, float)
    if U.ndim != 2 or U.shape[1] != 3 or len(U) == 0:
        raise InputError("fuse_axis", f"directions must be (n, 3), got {U.shape}")
    n = len(U)
    names = tuple(names) if names is not None else tuple(f"source{i}" for i in range(n))
    norms = np.linalg.norm(U, axis=1)
    if not np.all(np.isfinite(norms)) or np.any(norms < 1e-12):
        raise InputError("fuse_axis", "an axis direction is zero or not finite")
    U = U / norms[:, None]
    sds = [sd_deg] * n if np.isscalar(sd_deg) or np.asarray(sd_deg, dtype=object).ndim == 0 else list(sd_deg)
    if len(sds) != n:
        raise InputError("fuse_axis", f"{len(sds)} uncertainties for {n} directions")
    covs = [_direction_cov(s, u, nm) for s, u, nm in zip(sds, U, names)]
    ref = U[int(np.argmin([np.trace(c) for c in covs]))]
    flipped = U @ ref < 0
    U[flipped] *= -1
    mean = ref.copy()
    for _ in range(max_iter):
        B = _tangent_basis(mean)
        est = []
        for u, c in zip(U, covs):
            est.append((B.T @ _log(mean, u), B.T @ _transport(c, u, mean) @ B))
        f = fuse_gaussian(est, names)
        mean = _exp(mean, B @ f.mean)
        if np.linalg.norm(f.mean) < 1e-14:
            break
    B = _tangent_basis(mean)
    f = fuse_gaussian([(B.T @ _log(mean, u), B.T @ _transport(c, u, mean) @ B) for u, c in zip(U, covs)], names)
    cov3 = B @ f.cov @ B.T
    point = point_cov = None
    if points is not None:
        X = np.asarray(points, float).reshape(n, 3)
        Cs = np.asarray(point_covs, float).reshape(n, 3, 3) if point_covs is not None else None
        if Cs is None:
            raise InputError("fuse_axis", "axis points need their covariances")
        Pi = np.eye(3) - np.outer(mean, mean)
        Ps = np.array([Pi @ np.linalg.pinv(Pi @ C @ Pi, rcond=1e-12, hermitian=True) @ Pi for C in Cs])
        Ptot = Ps.sum(axis=0)
        point_cov = np.linalg.pinv(Ptot, rcond=1e-12, hermitian=True)
        point = point_cov @ np.einsum("nij,nj->i", Ps, X)
        # Put the point at the mean position along the axis so it stays near the data.
        point = point + (np.mean(X, axis=0) - point) @ mean * mean
    return FusedAxis(mean, float(np.degrees(np.sqrt(np.trace(cov3) / 2.0))), cov3, f.shares, flipped,
                     f.chi2, f.dof, f.p_value, names, point, point_cov)


def as_axis(estimate, *, frame: str = "proximal"):
    """(direction, sd_deg, point, point_cov) of an axis estimate.

    Accepts a `kinematics.algorithms.functional.AxisEstimate` (``direction_sd`` in rad,
    taken as the per-tangent-component sd), a landmarks.json axis
    ``{"point", "direction", "sd_deg"}`` (point covariance unknown: None), a
    joints.json joint ``{"origin", "origin_cov", "rotation", "axis_sd_deg"}``
    (axis = third rotation column) or a 4-tuple.
    """
    if isinstance(estimate, tuple) and len(estimate) == 4:
        return estimate
    if isinstance(estimate, dict):
        if "direction" in estimate:
            return (np.asarray(estimate["direction"], float), float(estimate["sd_deg"]),
                    np.asarray(estimate["point"], float), estimate.get("point_cov"))
        if "rotation" in estimate:
            return (np.asarray(estimate["rotation"], float)[:, 2], float(estimate["axis_sd_deg"]),
                    np.asarray(estimate["origin"], float), estimate.get("origin_cov"))
    if hasattr(estimate, "direction_sd"):
        if frame not in ("proximal", "distal"):
            raise InputError("frame", f"frame must be 'proximal' or 'distal', got {frame!r}")
        cov = estimate.cov_point_proximal if frame == "proximal" else None
        return (getattr(estimate, f"direction_{frame}"), float(np.degrees(estimate.direction_sd)),
                getattr(estimate, f"point_{frame}"), cov)
    raise InputError("fusion", f"cannot read an axis from {type(estimate).__name__}")


def fuse_axes(estimates, names=None, *, frame: str = "proximal") -> FusedAxis:
    """`fuse_axis` on estimates read by `as_axis`; points are fused when every source has a point covariance."""
    ax = [as_axis(e, frame=frame) for e in estimates]
    with_points = all(a[3] is not None for a in ax)
    return fuse_axis([a[0] for a in ax], [a[1] for a in ax], names,
                     points=[a[2] for a in ax] if with_points else None,
                     point_covs=[a[3] for a in ax] if with_points else None)


