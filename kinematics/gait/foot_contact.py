r"""Elastokinematic two-segment foot with circle-plane ground contacts (Tändl et al. 2010, sec. 3.2).

Model (sagittal plane of the foot: ``u`` along the progression, ``v`` up, moments
about ``w = u × v``, angles counter-clockwise, i.e. toes-up positive)::

    hind foot   input frame K at the ankle centre A = (u_A, v_A), angle phi to the ground
                (x_K = (cos phi, sin phi)); x_K is parallel to the ground in the neutral pose
    heel circle centre  c_2 = A + R(phi) (-l_heel, -h),      radius R_2
    midfoot     revolute joint (axis parallel to the ankle axis z_K)
                J = A + R(phi) (l_joint, -h)
    fore foot   angle phi + theta, fore circle centre c_1 = J + R(phi + theta) (l_fore, 0), radius R_1
    spring      M_s(theta, theta_dot) = k theta (1 + (theta / theta_s)^2) + d theta_dot

The five identified parameters are ``x = (k, l_heel, l_joint, l_fore, h)``:
the midfoot stiffness and the in-sole components of the three offsets
Δr_2 = (-l_heel, -h), Δr_3 = (l_joint, -h), Δr_1 = (l_fore, 0) of the paper
(both circles and the joint on the sole line at depth ``h`` below the ankle in
the neutral pose).  The radii, the contact law and the spring's shape are
fixed constants of `FootElement`.

Contacts.  Each circle lies in a plane parallel to the x-z plane of its
segment; its rim point lowest in the sagittal plane is

.. math::

    P_i = c_i - R_i\, s(\alpha_i)\, x_i, \qquad
    s(\alpha) = \frac{\sin\alpha}{\sqrt{\sin^2\alpha + \varepsilon^2}}

(the regularisation ε replaces the jump of the lowest point from the back to
the front rim at α = 0 by a smooth roll over the circle's width, so a flat
circle carries a centre of pressure anywhere within ±R_i).  The penetration
:math:`\delta_i = g - P_{i,v}` (g the ground height) gives the normal force
:math:`N_i = k_c\,\langle\delta_i\rangle^{3/2}` with the smooth ramp
:math:`\langle\delta\rangle = (\delta + \sqrt{\delta^2 + \eta^2})/2`.
In the static equilibrium the foot sticks: the horizontal position of A is
the measured one and each contact's friction makes its force parallel to the
total ground reaction, :math:`F_i = N_i (t, 1)`, ``t = f_u / f_v``.

Static equilibrium under the ankle wrench ``(f, m_a)`` (the load the leg
applies to K at A), unknowns ``(v_A, phi, theta)`` per frame:

.. math::

    N_1 + N_2 + f_v = 0, \qquad
    m_a + \sum_i (P_i - A) \times F_i = 0, \qquad
    (P_1 - J) \times F_1 - M_s(\theta, 0) = 0,

solved by a damped Newton iteration vectorised over frames.

Identification (paper's eq. 25) over m loaded frames:

.. math::

    F(x) = \tfrac12 \sum_{i=1}^m \bigl[ w_r^2 (v_{meas,i} - v_{sim,i}(x))^2
                                      + w_p^2 (\phi_{meas,i} - \phi_{sim,i}(x))^2 \bigr],

(metres and radians, ``w_r = w_p = 1`` as in the paper; the horizontal
position and the heading are held at the measured ones by friction), minimised
with `scipy.optimize.least_squares` (trust-region reflective, bounds keeping
the lengths and the stiffness positive).  Every equilibrium solve starts from
the measured pose: a foot balanced on its fore-foot rim can have two
equilibrium pitches, and the one nearest the measurement is the one compared.
Parameter sd: :math:`s^2 (J^T J)^{-1}` with :math:`s^2 = 2F/(2m - 5)`.  The damper and the dynamic contact
terms do not act in the static equilibrium; `spring_moment` and
`contact_forces` carry them for forward simulation.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from lowerlimb.errors import FitError

__all__ = [
    "FootElement",
    "FootEquilibrium",
    "FootFit",
    "FootParameters",
    "contact_forces",
    "fit_foot_parameters",
    "foot_geometry",
    "sagittal_stance",
    "spring_moment",
    "static_equilibrium",
]


@dataclass(frozen=True)
class FootElement:
    """Fixed constants of the foot element (SI units).

    Attributes
    ----------
    heel_radius, fore_radius : float, m
        R_2 and R_1, radii of the heel and fore-foot contact circles.
    contact_stiffness : float, N m^-1.5
        k_c of the Hertzian normal law N = k_c δ^1.5 (heel-pad range: 800 N at ~5 mm).
    contact_damping : float, s/m
        Hunt-Crossley factor c: N = k_c δ^1.5 (1 + c δ_dot) in `contact_forces` (dynamics only).
    regularisation : float
        ε of the circle's lowest point (dimensionless, ~ sine of the roll-over angle).
    ramp : float, m
        η of the smooth penetration ramp.
    spring_scale : float, rad
        θ_s of the progressive midfoot spring.
    spring_damping : float, N m s/rad
        d of the midfoot damper (dynamics only).
    """

    heel_radius: float = 0.03
    fore_radius: float = 0.035
    contact_stiffness: float = 2.0e6
    contact_damping: float = 1.0
    regularisation: float = 0.05
    ramp: float = 5e-4
    spring_scale: float = 0.15
    spring_damping: float = 1.0


@dataclass(frozen=True)
class FootParameters:
    """The five identified parameters x.

    Attributes
    ----------
    stiffness : float, N m/rad
        k, linear term of the midfoot spring.
    heel_offset : float, m
        l_heel, heel circle centre behind the ankle along x_K.
    joint_offset : float, m
        l_joint, midfoot joint in front of the ankle along x_K.
    fore_offset : float, m
        l_fore, fore circle centre in front of the midfoot joint along the fore foot.
    sole_depth : float, m
        h, depth of the sole line (circles and joint) below the ankle along -y_K.
    """

    stiffness: float
    heel_offset: float
    joint_offset: float
    fore_offset: float
    sole_depth: float

    NAMES = ("stiffness", "heel_offset", "joint_offset", "fore_offset", "sole_depth")
    UNITS = ("N m/rad", "m", "m", "m", "m")

    def as_vector(self) -> np.ndarray:
        return np.array([getattr(self, n) for n in self.NAMES])

    @classmethod
    def from_vector(cls, x) -> FootParameters:
        return cls(*(float(v) for v in x))


@dataclass(frozen=True)
class FootEquilibrium:
    """Static equilibrium poses, one row per frame.

    Attributes
    ----------
    height : (m,) m, v_A of the ankle centre
    angle : (m,) rad, phi of the hind foot to the ground (toes up positive)
    midfoot : (m,) rad, theta of the fore foot to the hind foot
    normal : (m, 2) N, N_1 (fore) and N_2 (heel) vertical contact force components
    contact_points : (m, 2, 2) m, P_1 and P_2 as (u, v)
    converged : (m,) bool, equilibrium residual below tolerance
    """

    height: np.ndarray
    angle: np.ndarray
    midfoot: np.ndarray
    normal: np.ndarray
    contact_points: np.ndarray
    converged: np.ndarray


@dataclass(frozen=True)
class FootFit:
    """Identified foot parameters.

    Attributes
    ----------
    parameters : FootParameters
    sd : (5,) standard deviations of x from s² (JᵀJ)⁻¹ (same units as x)
    equilibrium : FootEquilibrium at the identified parameters
    rms_angle : float, rad, RMS of phi_meas - phi_sim over the balanced frames
    rms_height : float, m, RMS of v_meas - v_sim over the balanced frames
        (``equilibrium.converged`` marks them; a fit with fewer than 90 % is refused)
    cost : float, F(x) of eq. 25
    n_evaluations : int
    """

    parameters: FootParameters
    sd: np.ndarray
    equilibrium: FootEquilibrium = field(repr=False)
    rms_angle: float
    rms_height: float
    cost: float
    n_evaluations: int


_EQ_WEIGHT = 30.0  # weight of a frame's (dimensionless) imbalance where no equilibrium was found


def _rot(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def foot_geometry(element: FootElement, x: np.ndarray, ankle: np.ndarray, phi: np.ndarray,
                  theta: np.ndarray) -> dict:
    """Joint, circle centres and lowest rim points of the element.

    Parameters
    ----------
    x : (5,) parameters (see `FootParameters`)
    ankle : (m, 2) m, A in (u, v)
    phi, theta : (m,) rad

    Returns
    -------
    dict with ``joint, heel_centre, fore_centre, heel_point, fore_point`` (m, 2) m
    """
    _, l_heel, l_joint, l_fore, h = x
    Rh, Rf = _rot(phi), _rot(phi + theta)
    heel_c = ankle + Rh @ np.array([-l_heel, -h])
    joint = ankle + Rh @ np.array([l_joint, -h])
    fore_c = joint + Rf @ np.array([l_fore, 0.0])
    eps = element.regularisation

    def lowest(c, R, ang, rot):
        s = np.sin(ang) / np.sqrt(np.sin(ang) ** 2 + eps**2)
        return c - R * s[:, None] * rot[..., :, 0]

    return {"joint": joint, "heel_centre": heel_c, "fore_centre": fore_c,
            "heel_point": lowest(heel_c, element.heel_radius, phi, Rh),
            "fore_point": lowest(fore_c, element.fore_radius, phi + theta, Rf)}


def _normal_force(element: FootElement, depth: np.ndarray, rate: np.ndarray | None = None) -> np.ndarray:
    d = 0.5 * (depth + np.sqrt(depth**2 + element.ramp**2))
    n = element.contact_stiffness * d**1.5
    if rate is not None:
        n = n * np.maximum(1.0 + element.contact_damping * rate, 0.0)
    return n


def contact_forces(element: FootElement, x, ankle, phi, theta, ground, depth_rate=None) -> np.ndarray:
    """Vertical contact forces (m, 2) N (fore, heel) of the element at a pose.

    `ground` (m,) m is the ground height under the foot; `depth_rate` (m, 2)
    m/s (optional) adds the Hunt-Crossley damping of forward simulation.
    """
    g = foot_geometry(element, np.asarray(x, float), ankle, phi, theta)
    depth = np.stack([ground - g["fore_point"][:, 1], ground - g["heel_point"][:, 1]], -1)
    return _normal_force(element, depth, depth_rate)


def spring_moment(element: FootElement, stiffness: float, theta, theta_rate=0.0):
    """Midfoot spring-damper moment M_s (N m) at angle `theta` (rad) and rate `theta_rate` (rad/s)."""
    theta = np.asarray(theta, float)
    return stiffness * theta * (1.0 + (theta / element.spring_scale) ** 2) + element.spring_damping * np.asarray(theta_rate)


def _residuals(element, x, z, ankle_u, force, moment, ground):
    v, phi, theta = z.T
    A = np.stack([ankle_u, v], -1)
    g = foot_geometry(element, x, A, phi, theta)
    P1, P2 = g["fore_point"], g["heel_point"]
    N = _normal_force(element, np.stack([ground - P1[:, 1], ground - P2[:, 1]], -1))
    t = force[:, 0] / force[:, 1]
    dirn = np.stack([t, np.ones_like(t)], -1)
    F1, F2 = N[:, :1] * dirn, N[:, 1:] * dirn
    W = np.abs(force[:, 1]) + 1.0
    L = 0.1
    r = np.stack([(N[:, 0] + N[:, 1] + force[:, 1]) / W,
                  (moment + _cross(P1 - A, F1) + _cross(P2 - A, F2)) / (W * L),
                  (_cross(P1 - g["joint"], F1) - spring_moment(element, x[0], theta, 0.0)) / (W * L)], -1)
    return r, N, np.stack([P1, P2], 1)


def static_equilibrium(element: FootElement, params: FootParameters | np.ndarray, ankle_u: np.ndarray,
                       force: np.ndarray, moment: np.ndarray, ground: np.ndarray, *,
                       start: np.ndarray | None = None, tol: float = 1e-11, max_iter: int = 80) -> FootEquilibrium:
    """Equilibrium poses of the element under ankle wrenches (see module docstring).

    Parameters
    ----------
    params : FootParameters or (5,) vector x
    ankle_u : (m,) m, horizontal position of the ankle centre (held by friction)
    force : (m, 2) N, force (f_u, f_v) the leg applies to the foot at A (f_v < 0 when loaded)
    moment : (m,) N m, moment m_a the leg applies to the foot about w
    ground : (m,) m, ground height under the foot
    start : (m, 3) optional start (v_A, phi, theta); default: unloaded sole at the ground, phi = theta = 0

    Returns
    -------
    FootEquilibrium
    """
    x = params.as_vector() if isinstance(params, FootParameters) else np.asarray(params, float)
    ankle_u, moment, ground = (np.asarray(a, float) for a in (ankle_u, moment, ground))
    force = np.asarray(force, float)
    m = len(ankle_u)
    if start is None:
        z = np.stack([ground + x[4], np.zeros(m), np.zeros(m)], -1)
    else:
        z = np.array(start, float, copy=True)
    args = (ankle_u, force, moment, ground)
    r, _, _ = _residuals(element, x, z, *args)
    norm = np.linalg.norm(r, axis=1)
    steps = np.array([1e-7, 1e-7, 1e-7])
    limit = np.array([0.005, 0.05, 0.05])
    for _ in range(max_iter):
        active = norm > tol
        if not active.any():
            break
        J = np.empty((m, 3, 3))
        for k in range(3):
            dz = z.copy()
            dz[:, k] += steps[k]
            J[:, :, k] = (_residuals(element, x, dz, *args)[0] - r) / steps[k]
        # Levenberg-Marquardt step: Newton's where an equilibrium exists, and a frame without one
        # settles at its least-imbalance pose (a continuous penalty for the identification)
        JtJ = np.einsum("fki,fkj->fij", J, J)
        JtJ = JtJ + 1e-9 * np.einsum("fii->fi", JtJ)[:, :, None] * np.eye(3) + 1e-18 * np.eye(3)
        with np.errstate(all="ignore"):
            try:
                dz = -np.linalg.solve(JtJ, np.einsum("fki,fk->fi", J, r)[..., None])[..., 0]
            except np.linalg.LinAlgError:
                dz = -np.einsum("fij,fj->fi", np.linalg.pinv(J), r)
        dz = np.where(np.isfinite(dz), dz, 0.0)
        scale = np.min(np.where(np.abs(dz) > limit, limit / np.maximum(np.abs(dz), 1e-300), 1.0), axis=1)
        dz *= scale[:, None]
        dz[~active] = 0.0
        alpha = np.ones(m)
        accepted = np.zeros(m, bool) | ~active
        z_new, r_new, n_new = z.copy(), r.copy(), norm.copy()
        for _ in range(12):
            trial = z + alpha[:, None] * dz
            rt, _, _ = _residuals(element, x, trial, *args)
            nt = np.linalg.norm(rt, axis=1)
            ok = ~accepted & (nt < norm)
            z_new[ok], r_new[ok], n_new[ok] = trial[ok], rt[ok], nt[ok]
            accepted |= ok
            if accepted.all():
                break
            alpha = np.where(accepted, alpha, 0.5 * alpha)
        if not (n_new < norm).any():
            break
        z, r, norm = z_new, r_new, n_new
    _, N, P = _residuals(element, x, z, *args)
    return FootEquilibrium(z[:, 0], z[:, 1], z[:, 2], N, P, norm <= max(tol, 1e-8))


def fit_foot_parameters(element: FootElement, ankle: np.ndarray, angle: np.ndarray, force: np.ndarray,
                        moment: np.ndarray, ground: np.ndarray, x0: FootParameters, *,
                        weights: tuple[float, float] = (1.0, 1.0), bounds: tuple | None = None,
                        n_starts: int = 3) -> FootFit:
    """Identify the five foot parameters by minimising eq. 25 (see module docstring).

    Parameters
    ----------
    ankle : (m, 2) m, measured ankle centre (u, v) in the sagittal plane
    angle : (m,) rad, measured hind-foot angle to the ground (toes up positive, 0 in the neutral pose)
    force : (m, 2) N, ankle force on the foot (f_u, f_v); frames must be loaded (f_v < 0)
    moment : (m,) N m, ankle moment on the foot about w
    ground : (m,) m, ground height under the foot
    x0 : FootParameters, start of the search
    weights : (w_r, w_p), weights of the height (1/m) and angle (1/rad) residuals
    bounds : optional (lower (5,), upper (5,)); default: k in [1, 1e5] N m/rad, lengths in [5 mm, 0.3 m]
    n_starts : 1-3 searches, from `x0` and from `x0` with 3x and 1/3 its stiffness; the lowest cost is kept

    Returns
    -------
    FootFit

    Raises
    ------
    FitError
        if no frame is loaded or the equilibrium fails at the identified parameters.
    """
    ankle, angle, force = np.asarray(ankle, float), np.asarray(angle, float), np.asarray(force, float)
    moment, ground = np.asarray(moment, float), np.asarray(ground, float)
    if len(ankle) < 5 or not np.all(force[:, 1] < 0):
        raise FitError("foot identification needs at least 5 loaded frames (f_v < 0)")
    m = len(angle)
    wr, wp = weights
    n_eval = [0]
    x0v = x0.as_vector()
    if bounds is None:
        bounds = (np.array([1.0, 0.005, 0.005, 0.005, 0.005]), np.array([1e5, 0.3, 0.3, 0.3, 0.3]))
    lo, hi = (np.asarray(b, float) for b in bounds)
    x0v = np.clip(x0v, lo * 1.0001, hi * 0.9999)
    args = (ankle[:, 0], force, moment, ground)
    # Each solve starts from the measured pose, so the equilibrium branch is the one nearest the
    # measurement (a foot on its fore-foot rim can balance in two pitches).
    start = np.stack([ankle[:, 1], angle, np.zeros(m)], -1)

    def fun(x):
        n_eval[0] += 1
        eq = static_equilibrium(element, x, *args, start=start)
        z = np.stack([eq.height, eq.angle, eq.midfoot], -1)
        # a frame without equilibrium at x keeps a continuous cost: its pose error grown by its imbalance
        pen = _EQ_WEIGHT * np.linalg.norm(_residuals(element, x, z, *args)[0], axis=1)
        return np.concatenate([np.hypot(wr * (ankle[:, 1] - eq.height), pen), np.hypot(wp * (angle - eq.angle), pen)])

    # The cost has local minima where the midfoot stiffness collapses; starting also from a third and
    # three times the given stiffness and keeping the best reaches the global one in practice.
    res = None
    for k_scale in (1.0, 3.0, 1.0 / 3.0)[:max(int(n_starts), 1)]:
        xs = np.clip(x0v * np.array([k_scale, 1, 1, 1, 1]), lo * 1.0001, hi * 0.9999)
        r = least_squares(fun, xs, bounds=(lo, hi), x_scale=np.abs(xs), diff_step=1e-6,
                          xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100)
        if res is None or r.cost < res.cost:
            res = r
    eq = static_equilibrium(element, res.x, *args, start=start)
    if eq.converged.mean() < 0.9:
        raise FitError(f"foot equilibrium not found in {int((~eq.converged).sum())} of {m} frames "
                       "at the identified parameters (loads outside the foot's support?)")
    ok = eq.converged
    dof = max(2 * m - 5, 1)
    s2 = 2 * res.cost / dof
    try:
        cov = s2 * np.linalg.inv(res.jac.T @ res.jac)
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        sd = np.full(5, np.inf)
    return FootFit(FootParameters.from_vector(res.x), sd, eq,
                   float(np.sqrt(np.mean((angle - eq.angle)[ok] ** 2))),
                   float(np.sqrt(np.mean((ankle[:, 1] - eq.height)[ok] ** 2))), float(res.cost), n_eval[0])


def sagittal_stance(ankle_centre: np.ndarray, foot_axis: np.ndarray, grf: np.ndarray, cop: np.ndarray,
                    up=(0.0, 0.0, 1.0)) -> dict:
    """Project a stance phase into the foot's sagittal plane for `fit_foot_parameters`.

    Parameters
    ----------
    ankle_centre : (m, 3) m, lab frame
    foot_axis : (m, 3), unit heel-to-toe axis of the foot (parallel to the ground in the neutral pose)
    grf : (m, 3) N, ground reaction force on the foot (lab frame)
    cop : (m, 3) m, centre of pressure (lab frame)
    up : (3,) lab vertical

    Returns
    -------
    dict with ``ankle`` (m, 2) m, ``angle`` (m,) rad, ``force`` (m, 2) N, ``moment`` (m,) N m,
    ``ground`` (m,) m (CoP height), ``progression`` (3,) the unit u direction
    (mean horizontal foot axis), and ``lateral`` w = u × v.
    The ankle wrench on the massless foot is minus the ground reaction moved to A.
    """
    up = np.asarray(up, float) / np.linalg.norm(up)
    horiz = foot_axis - np.outer(foot_axis @ up, up)
    u = np.nanmean(horiz, axis=0)
    u /= np.linalg.norm(u)
    w = np.cross(u, up)
    a = foot_axis
    angle = np.arctan2(a @ up, a @ u)
    moment_lab = np.cross(cop - ankle_centre, grf)
    return {"ankle": np.stack([ankle_centre @ u, ankle_centre @ up], -1), "angle": angle,
            "force": -np.stack([grf @ u, grf @ up], -1), "moment": -(moment_lab @ w),
            "ground": cop @ up, "progression": u, "lateral": w}
