"""Correlative joints: linear regression laws between joint coordinates.

Pronost, Sandholm & Thalmann (2010), *Correlative joint definition for motion
analysis and animation*: the translations of a six-DOF joint (e.g. the knee
joint centre) are linear functions of its rotations, fitted per motion (and
per sub-motion) by multiple linear regression (their eq. 1)::

    T_d(f) = c1_d a1(f) + c2_d a2(f) + ... + ck_d ak(f) + c0_d,     d = 1..D

(the seed's ``c4`` is ``c0`` here, stored last: coefficients ``[c1, ..., ck, c0]``).

`fit_law` solves the least-squares problem on the design matrix
``M = [a1 ... ak 1]`` (F, k+1) by a QR factorisation after checking its rank
and condition number itself (a non-varying or collinear independent coordinate
is a `FitError`, never a silent minimum-norm solution).  Statistics: R squared,
residual RMS, maximum absolute deviation, the seed's validation criterion
(section 3.2 step 5), the Table 2 mean deviation (mean Euclidean distance
between data and law) and, with trial groups, leave-one-trial-out errors.

`scale_factor` and `CorrelativeLaw.scaled` implement eq. (3); `transfer_law`
the five-step transfer of section 4.2 to a model with other segment frames.
Tables in the form of the seed's Tables 1 and 2 and a Figure 3 style deviation
plot are produced by `coefficient_table`, `deviation_table` and `plot_deviation`.

Units: independents in radians (or metres), dependents in metres (or radians);
slopes in dependent unit per independent unit (m/rad for the knee), intercept
in the dependent unit.  The law itself records them.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from scipy.linalg import solve_triangular

from lowerlimb.atomic import atomic_path, write_text
from lowerlimb.errors import FitError, InputError

__all__ = [
    "LawFit",
    "CorrelativeLaw",
    "fit_law",
    "fit_laws_by_group",
    "scale_factor",
    "knee_landmark_frame",
    "LawTransfer",
    "transfer_law",
    "TextTable",
    "coefficient_table",
    "deviation_table",
    "plot_deviation",
    "CONDITION_LIMIT",
    "CONDITION_WARN",
    "json_text",
]

#: Condition number (of the standardised design) above which the fit is refused.
CONDITION_LIMIT = 1e8
#: Condition number above which the fit is flagged as poorly determined.
CONDITION_WARN = 1e3


# --------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class LawFit:
    """Goodness of fit of a `CorrelativeLaw` on the data it was fitted to.

    Attributes (per dependent arrays have shape (D,))
    ----------
    r2 : R squared, ``1 - SS_res / SS_tot`` (NaN when the dependent is constant)
    rms : residual root mean square, dependent unit
    max_abs : maximum absolute residual, dependent unit
    seed_criterion : bool per dependent, ``max|M C - E| < min|E|`` (seed, 3.2 step 5)
    valid : bool, every seed criterion holds and the design is well conditioned
    n_frames : frames used (rows without NaN)
    n_dropped : frames dropped because a value was missing
    condition : condition number of the standardised design matrix
    well_conditioned : ``condition < CONDITION_WARN``
    mean_deviation : mean Euclidean norm of the residual vector over frames
        (the seed's Table 2 "average deviation"), NaN when dependents mix units
    n_groups : number of trials (groups); 1 when none given
    loto_rms : leave-one-trial-out residual RMS per dependent (None without groups)
    loto_mean_deviation : leave-one-trial-out mean deviation (None without groups)
    """

    r2: np.ndarray
    rms: np.ndarray
    max_abs: np.ndarray
    seed_criterion: np.ndarray
    valid: bool
    n_frames: int
    n_dropped: int
    condition: float
    well_conditioned: bool
    mean_deviation: float
    n_groups: int = 1
    loto_rms: np.ndarray | None = None
    loto_mean_deviation: float | None = None

    def to_dict(self) -> dict:
        d = {
            "r2": _list(self.r2), "rms": _list(self.rms), "max_abs": _list(self.max_abs),
            "valid": bool(self.valid), "seed_criterion": [bool(v) for v in self.seed_criterion],
            "n_frames": int(self.n_frames), "n_dropped": int(self.n_dropped),
            "condition_number": _num(self.condition), "well_conditioned": bool(self.well_conditioned),
            "mean_deviation": _num(self.mean_deviation), "n_groups": int(self.n_groups),
        }
        if self.loto_rms is not None:
            d["loto_rms"] = _list(self.loto_rms)
            d["loto_mean_deviation"] = _num(self.loto_mean_deviation)
        return d

    @classmethod
    def from_dict(cls, d: Mapping, n_dep: int, source=None) -> "LawFit":
        def arr(key, default=math.nan):
            v = d.get(key)
            if v is None:
                return np.full(n_dep, default)
            a = np.asarray(v, dtype=float).ravel()
            if a.size == 1:
                a = np.full(n_dep, float(a[0]))
            if a.size != n_dep:
                raise InputError(source, f"fit.{key} has {a.size} entries for {n_dep} dependents")
            return a

        valid = d.get("valid", False)
        seed = d.get("seed_criterion", [bool(valid)] * n_dep if isinstance(valid, bool) else valid)
        loto = d.get("loto_rms")
        return cls(
            r2=arr("r2"), rms=arr("rms"), max_abs=arr("max_abs"),
            seed_criterion=np.asarray(seed, dtype=bool).ravel(),
            valid=bool(np.all(valid)), n_frames=int(d.get("n_frames", 0)), n_dropped=int(d.get("n_dropped", 0)),
            condition=float(d.get("condition_number", math.nan) or math.nan),
            well_conditioned=bool(d.get("well_conditioned", True)),
            mean_deviation=float(d.get("mean_deviation", math.nan) or math.nan),
            n_groups=int(d.get("n_groups", 1)),
            loto_rms=None if loto is None else np.asarray(loto, dtype=float),
            loto_mean_deviation=d.get("loto_mean_deviation"),
        )


def json_text(obj) -> str:
    """Indented JSON with innermost number lists kept on one line."""
    text = json.dumps(obj, indent=2)
    return re.sub(r"\[\s*([-0-9.eE+, \n\r\tnulltruefals]*?)\s*\]",
                  lambda m: "[" + ", ".join(t.strip() for t in m.group(1).split(",")) + "]"
                  if m.group(1).strip() else "[]", text)


def _num(x):
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _list(a):
    return [_num(v) for v in np.asarray(a, dtype=float).ravel()]


@dataclass(frozen=True, eq=False)
class CorrelativeLaw:
    """Dependent coordinates as linear functions of independent ones.

    Model::

        y = C[:, :k] @ a + C[:, k]          a (k,) independents, y (D,) dependents

    Attributes
    ----------
    joint : str
        Joint name (e.g. ``knee_r``).
    independent : tuple of str, length k
    dependent : tuple of str, length D
    coefficients : ndarray, shape (D, k + 1)
        Row d is ``[c1_d, ..., ck_d, c0_d]`` (the seed's ``[c1, c2, c3, c4]``).
    independent_units, dependent_units : tuple of str
        ``"rad"`` or ``"m"`` per coordinate.
    residual_covariance : ndarray (D, D) or None
        Covariance of the residuals across dependents (unit^2), ``E^T E / (F - k - 1)``.
    normal_inverse : ndarray (k+1, k+1) or None
        ``(M^T M)^-1`` of the design matrix; with `residual_covariance` it gives
        the coefficient covariance ``Cov(C[i], C[j]) = S_ij (M^T M)^-1``.
    fit : LawFit or None
        Statistics on the fitted data.
    """

    joint: str
    independent: tuple[str, ...]
    dependent: tuple[str, ...]
    coefficients: np.ndarray
    independent_units: tuple[str, ...] = ()
    dependent_units: tuple[str, ...] = ()
    residual_covariance: np.ndarray | None = None
    normal_inverse: np.ndarray | None = None
    fit: LawFit | None = field(default=None, compare=False)

    def __post_init__(self):
        ind, dep = tuple(self.independent), tuple(self.dependent)
        c = np.array(self.coefficients, dtype=float)
        if c.ndim == 1:
            c = c[None, :]
        if c.shape != (len(dep), len(ind) + 1):
            raise InputError(None, f"law {self.joint!r}: coefficients of shape {c.shape}, expected ({len(dep)}, {len(ind) + 1})")
        if not np.all(np.isfinite(c)):
            raise InputError(None, f"law {self.joint!r}: non-finite coefficients")
        if set(ind) & set(dep):
            raise InputError(None, f"law {self.joint!r}: {sorted(set(ind) & set(dep))} both dependent and independent")
        iu = tuple(self.independent_units) or ("rad",) * len(ind)
        du = tuple(self.dependent_units) or ("m",) * len(dep)
        if len(iu) != len(ind) or len(du) != len(dep):
            raise InputError(None, f"law {self.joint!r}: one unit per coordinate needed")
        c.setflags(write=False)
        object.__setattr__(self, "coefficients", c)
        object.__setattr__(self, "independent", ind)
        object.__setattr__(self, "dependent", dep)
        object.__setattr__(self, "independent_units", iu)
        object.__setattr__(self, "dependent_units", du)
        for name, shape in (("residual_covariance", (len(dep), len(dep))), ("normal_inverse", (len(ind) + 1,) * 2)):
            v = getattr(self, name)
            if v is not None:
                v = np.array(v, dtype=float)
                if v.shape != shape:
                    raise InputError(None, f"law {self.joint!r}: {name} of shape {v.shape}, expected {shape}")
                v.setflags(write=False)
                object.__setattr__(self, name, v)

    def same_as(self, other: "CorrelativeLaw", atol: float = 1e-12) -> bool:
        """Same coordinates, units and coefficients (within `atol`)."""
        return (self.independent == other.independent and self.dependent == other.dependent
                and self.independent_units == other.independent_units
                and self.dependent_units == other.dependent_units
                and np.allclose(self.coefficients, other.coefficients, rtol=0, atol=atol))

    def distance_to(self, other: "CorrelativeLaw", angles) -> np.ndarray:
        """Per-frame distance between the two laws' predictions at `angles` (F, k), shape (F,).

        For validating a fitted law against a known one (e.g. a phantom's truth) over
        the range of motion actually used, rather than coefficient by coefficient.
        """
        if self.independent != other.independent or self.dependent != other.dependent:
            raise InputError(None, f"laws {self.joint!r} and {other.joint!r} relate different coordinates")
        return np.linalg.norm(self.predict(np.atleast_2d(angles)) - other.predict(np.atleast_2d(angles)), axis=1)

    # ---------------------------------------------------------------- evaluation
    @property
    def slopes(self) -> np.ndarray:
        """(D, k) partial derivatives dy/da (constant: the Jacobian of the law)."""
        return self.coefficients[:, :-1]

    @property
    def intercepts(self) -> np.ndarray:
        """(D,) values at a = 0."""
        return self.coefficients[:, -1]

    def _angles(self, angles) -> tuple[np.ndarray, bool]:
        a = np.asarray(angles, dtype=float)
        single = a.ndim == 1
        a = np.atleast_2d(a)
        if a.shape[-1] != len(self.independent):
            raise InputError(None, f"law {self.joint!r} takes {len(self.independent)} independents "
                                   f"({', '.join(self.independent)}); got shape {np.shape(angles)}")
        return a, single

    def predict(self, angles) -> np.ndarray:
        """Dependent values: (k,) -> (D,), (F, k) -> (F, D)."""
        a, single = self._angles(angles)
        y = a @ self.slopes.T + self.intercepts
        return y[0] if single else y

    def predict_sd(self, angles) -> np.ndarray:
        """Standard error of the predicted mean, same shape as `predict` (needs covariance).

        ``sd_d(a) = sqrt(S_dd m^T (M^T M)^-1 m)``, ``m = [a, 1]``.
        """
        if self.residual_covariance is None or self.normal_inverse is None:
            raise FitError(f"law {self.joint!r} carries no covariance")
        a, single = self._angles(angles)
        m = np.column_stack([a, np.ones(len(a))])
        q = np.einsum("fi,ij,fj->f", m, self.normal_inverse, m)
        sd = np.sqrt(np.outer(np.maximum(q, 0.0), np.diag(self.residual_covariance)))
        return sd[0] if single else sd

    @property
    def covariance(self) -> np.ndarray | None:
        """Coefficient covariance per dependent, shape (D, k+1, k+1) (order ``[c1..ck, c0]``)."""
        if self.residual_covariance is None or self.normal_inverse is None:
            return None
        return np.diag(self.residual_covariance)[:, None, None] * self.normal_inverse[None]

    @property
    def coefficient_sd(self) -> np.ndarray | None:
        """Standard deviations of the coefficients, shape (D, k+1)."""
        cov = self.covariance
        return None if cov is None else np.sqrt(np.einsum("dii->di", cov))

    def residuals(self, independent, dependent) -> np.ndarray:
        """Data minus law, shape (F, D)."""
        return np.asarray(dependent, dtype=float) - self.predict(np.atleast_2d(independent))

    def deviation(self, independent, dependent) -> np.ndarray:
        """Per-frame Euclidean norm of the residual vector, shape (F,) (the seed's Figure 3 colour)."""
        return np.linalg.norm(self.residuals(independent, dependent), axis=1)

    # ---------------------------------------------------------------- transforms
    def transformed(self, matrix, offset=None, joint: str | None = None) -> "CorrelativeLaw":
        """The law of ``y' = A y + b``: slopes ``A C``, intercept ``A c0 + b``, covariance ``A S A^T``."""
        A = np.asarray(matrix, dtype=float)
        D = len(self.dependent)
        if A.shape != (D, D):
            raise InputError(None, f"transform of shape {A.shape} for {D} dependents")
        b = np.zeros(D) if offset is None else np.asarray(offset, dtype=float).reshape(D)
        c = A @ self.coefficients
        c[:, -1] += b
        rc = None if self.residual_covariance is None else A @ self.residual_covariance @ A.T
        return replace(self, coefficients=c, residual_covariance=rc, fit=None,
                       joint=self.joint if joint is None else joint)

    def scaled(self, s: float) -> "CorrelativeLaw":
        """Seed eq. (3): every coefficient of the length dependents multiplied by `s`.

        Angular dependents (e.g. a transmission) are scale invariant and kept.
        """
        if not (math.isfinite(s) and s > 0):
            raise InputError(None, f"scale factor {s} must be positive")
        A = np.diag([s if u == "m" else 1.0 for u in self.dependent_units])
        return self.transformed(A)

    # ---------------------------------------------------------------- JSON
    def to_json(self) -> dict:
        """JSON-ready dict (schema of ``law.json``)."""
        k = len(self.independent)
        coef_units = [[f"{du}/{iu}" for iu in self.independent_units] + [du] for du in self.dependent_units]
        uniform = len(set(self.independent_units)) <= 1 and len(set(self.dependent_units)) <= 1
        units = {
            "independent": self.independent_units[0] if uniform and k else list(self.independent_units),
            "dependent": self.dependent_units[0] if uniform else list(self.dependent_units),
            "coefficients": coef_units[0] if uniform else coef_units,
            "order": "[c1..ck, c0]: slope per independent, last the constant term",
        }
        d = {
            "joint": self.joint,
            "dependent": list(self.dependent),
            "independent": list(self.independent),
            "coefficients": [[float(v) for v in row] for row in self.coefficients],
            "units": units,
        }
        sd = self.coefficient_sd
        if sd is not None:
            d["coefficient_sd"] = [[float(v) for v in row] for row in sd]
            d["covariance"] = [[[float(v) for v in r] for r in blk] for blk in self.covariance]
            d["residual_covariance"] = [[float(v) for v in r] for r in self.residual_covariance]
            d["normal_inverse"] = [[float(v) for v in r] for r in self.normal_inverse]
        if self.fit is not None:
            d["fit"] = self.fit.to_dict()
        return d

    def dumps(self) -> str:
        return json_text(self.to_json())

    @classmethod
    def from_json(cls, data: Mapping | str | os.PathLike, source=None) -> "CorrelativeLaw":
        """Build a law from a dict (or a path to a JSON file); tolerant of missing optional keys."""
        if isinstance(data, (str, os.PathLike)):
            source = source or os.fspath(data)
            try:
                data = json.loads(Path(data).read_text(encoding="utf-8"))
            except FileNotFoundError:
                raise InputError(source, "file not found") from None
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise InputError(source, f"not valid JSON ({exc})") from None
        if not isinstance(data, Mapping):
            raise InputError(source, "a correlative law must be a JSON object")
        for key in ("dependent", "independent", "coefficients"):
            if key not in data:
                raise InputError(source, f"correlative law lacks {key!r}")
        dep, ind = list(data["dependent"]), list(data["independent"])
        units = data.get("units", {}) or {}

        def unit_list(key, n, default):
            u = units.get(key, default) if isinstance(units, Mapping) else default
            if isinstance(u, str):
                return (u,) * n
            u = tuple(u)
            if len(u) != n:
                raise InputError(source, f"units.{key} has {len(u)} entries for {n} coordinates")
            return u

        try:
            coef = np.asarray(data["coefficients"], dtype=float)
        except (TypeError, ValueError):
            raise InputError(source, "coefficients must be numbers") from None
        try:
            law = cls(
                joint=str(data.get("joint", "")), independent=tuple(ind), dependent=tuple(dep), coefficients=coef,
                independent_units=unit_list("independent", len(ind), "rad"),
                dependent_units=unit_list("dependent", len(dep), "m"),
                residual_covariance=data.get("residual_covariance"), normal_inverse=data.get("normal_inverse"),
            )
        except InputError as exc:
            raise InputError(source, exc.problem) from None
        if isinstance(data.get("fit"), Mapping):
            object.__setattr__(law, "fit", LawFit.from_dict(data["fit"], len(dep), source))
        return law

    def write(self, path: str | os.PathLike) -> Path:
        """Atomically write ``to_json()`` to `path`."""
        return write_text(path, self.dumps() + "\n")

    def as_linear_forms(self) -> list[tuple[str, tuple[str, ...], np.ndarray, float]]:
        """One ``(dependent, independents, slopes (k,), constant)`` per dependent: seed eq. (2),
        ``X = sum_i c_i Y_i + c_{n+1}``, the form of a linear coordinate coupling."""
        return [(d, self.independent, self.slopes[i].copy(), float(self.intercepts[i]))
                for i, d in enumerate(self.dependent)]

    def to_coupling(self, coordinates: Sequence[str] | None = None):
        """The law as `kinematics.multibody.coupling.LinearCoupling` rows (one per dependent) for IK/FK.

        `coordinates` orders the columns (default: independents then dependents).
        """
        from kinematics.multibody.coupling import LinearCoupling

        coords = tuple(coordinates) if coordinates is not None else self.independent + self.dependent
        missing = [n for n in self.independent + self.dependent if n not in coords]
        if missing:
            raise InputError(None, f"law {self.joint!r}: coordinates {', '.join(missing)} are not in the model")
        rows = [LinearCoupling.correlative(coords, d, dict(zip(self.independent, self.slopes[i])),
                                           float(self.intercepts[i])) for i, d in enumerate(self.dependent)]
        out = rows[0]
        for r in rows[1:]:
            out = out.stack(r)
        return out


# --------------------------------------------------------------------- fitting
def _prepare(independent, dependent, independent_names, dependent_names, source):
    X = np.asarray(independent, dtype=float)
    Y = np.asarray(dependent, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    if Y.ndim == 1:
        Y = Y[:, None]
    ind = tuple(independent_names) if independent_names is not None else tuple(f"a{i + 1}" for i in range(X.shape[1]))
    dep = tuple(dependent_names) if dependent_names is not None else tuple(f"y{i + 1}" for i in range(Y.shape[1]))
    if X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0]:
        raise InputError(source, f"independent {X.shape} and dependent {Y.shape} arrays must share the frame count")
    if X.shape[1] != len(ind) or Y.shape[1] != len(dep):
        raise InputError(source, "one name per independent and dependent column needed")
    if not ind or not dep:
        raise InputError(source, "at least one independent and one dependent coordinate needed")
    both = [n for n in dep if n in ind]
    if both:
        raise InputError(source, f"{', '.join(both)} listed both as dependent and independent")
    for names, what in ((ind, "independent"), (dep, "dependent")):
        if len(set(names)) != len(names):
            raise InputError(source, f"duplicate {what} names")
    if np.isinf(X).any() or np.isinf(Y).any():
        raise InputError(source, "infinite values in the kinematics")
    return X, Y, ind, dep


def _check_design(X, names, intercept, source):
    """Rank and condition of the design, on standardised columns (units cancel).

    Returns the condition number; raises FitError for a non-varying
    independent or a rank-deficient design.
    """
    F, k = X.shape
    p = k + int(intercept)
    if F < p:
        raise InputError(source, f"{F} frames for {p} coefficients per dependent: at least {p + 1} frames needed")
    if F == p:
        raise InputError(source, f"{F} frames for {p} coefficients: no residual degree of freedom to judge the fit; "
                                 f"at least {p + 1} frames needed")
    mean = X.mean(axis=0)
    sd = X.std(axis=0)
    scale = np.maximum(np.abs(mean), 1.0)
    flat = [names[i] for i in range(k) if sd[i] <= 1e-9 * scale[i]]
    if flat and intercept:
        raise FitError(f"{source + ': ' if source else ''}independent coordinate(s) {', '.join(flat)} do not vary "
                       f"(sd {', '.join(f'{sd[names.index(n)]:.3g}' for n in flat)}): the design matrix is rank deficient")
    if intercept:
        Z = np.column_stack([(X - mean) / np.where(sd > 0, sd, 1.0), np.ones(F)])
    else:
        rms = np.sqrt(np.mean(X ** 2, axis=0))
        if np.any(rms == 0):
            raise FitError(f"{source + ': ' if source else ''}independent coordinate(s) "
                           f"{', '.join(n for n, r in zip(names, rms) if r == 0)} are identically zero")
        Z = X / rms
    s = np.linalg.svd(Z, compute_uv=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
    rank = int(np.sum(s > s[0] * max(F, p) * np.finfo(float).eps))
    if rank < p or cond > CONDITION_LIMIT:
        _, _, vt = np.linalg.svd(Z)
        null = vt[-1][:k]
        involved = [names[i] for i in np.argsort(-np.abs(null)) if abs(null[i]) > 0.1]
        raise FitError(f"{source + ': ' if source else ''}design matrix rank {rank} < {p} (condition number "
                       f"{cond:.3g}): independents {', '.join(involved) or names} are (nearly) collinear")
    return cond


def _solve(X, Y, intercept):
    """QR least squares. Returns coefficients (D, k+1), residuals (F, D), (M^T M)^-1."""
    F = X.shape[0]
    M = np.column_stack([X, np.ones(F)]) if intercept else X
    Q, R = np.linalg.qr(M, mode="reduced")
    B = solve_triangular(R, Q.T @ Y)  # (p, D)
    Rinv = solve_triangular(R, np.eye(R.shape[0]))
    N_inv = Rinv @ Rinv.T
    E = Y - M @ B
    if not intercept:
        B = np.vstack([B, np.zeros((1, Y.shape[1]))])
        pad = np.zeros((N_inv.shape[0] + 1,) * 2)
        pad[:-1, :-1] = N_inv
        N_inv = pad
    return B.T, E, N_inv


def fit_law(independent, dependent, independent_names: Sequence[str] | None = None,
            dependent_names: Sequence[str] | None = None, groups=None, joint: str = "",
            independent_units: Sequence[str] | str = "rad", dependent_units: Sequence[str] | str = "m",
            intercept: bool = True, source: str | None = None) -> CorrelativeLaw:
    """Fit a correlative law by multiple linear least squares (seed section 3.2).

    Model and minimised quantity, for each dependent d separately::

        E_d = M c_d + e,   M = [a1 ... ak 1] (F, k+1),   min_c || M c - E_d ||^2

    Parameters
    ----------
    independent : array (F, k)
        Controlling coordinates per frame (e.g. the three knee rotations, rad).
    dependent : array (F, D)
        Correlative coordinates per frame (e.g. the three translations, m).
    independent_names, dependent_names : sequences of str
    groups : array (F,), optional
        Trial label per frame; enables leave-one-trial-out statistics.
    joint : str
    independent_units, dependent_units : str or sequence of str
        ``"rad"`` or ``"m"``.
    intercept : bool
        Fit the constant term ``c0`` (seed eq. 1); False for laws through
        the origin (a gear pair, ``R_b = beta R_a``).
    source : str, optional
        Named in error messages.

    Returns
    -------
    CorrelativeLaw
        With coefficient covariance ``S_ij (M^T M)^-1`` (ordinary least squares;
        frames of a motion are serially correlated, so treat it as a lower
        bound and prefer the leave-one-trial-out error as a prediction error).

    Raises
    ------
    InputError
        Shapes/names inconsistent, a coordinate both dependent and independent,
        fewer frames than coefficients + 1.
    FitError
        An independent coordinate that does not vary, collinear independents
        (rank-deficient or condition number > `CONDITION_LIMIT`).
    """
    X, Y, ind, dep = _prepare(independent, dependent, independent_names, dependent_names, source)
    iu = (independent_units,) * len(ind) if isinstance(independent_units, str) else tuple(independent_units)
    du = (dependent_units,) * len(dep) if isinstance(dependent_units, str) else tuple(dependent_units)
    if groups is not None and len(np.asarray(groups)) != len(X):
        raise InputError(source, "one group label per frame needed")
    ok = np.isfinite(X).all(axis=1) & np.isfinite(Y).all(axis=1)
    n_dropped = int((~ok).sum())
    X, Y = X[ok], Y[ok]
    g = None if groups is None else np.asarray(groups)[ok]
    if n_dropped and len(X) <= X.shape[1] + int(intercept):
        raise InputError(source, f"only {len(X)} complete frames ({n_dropped} with missing values dropped) "
                                 f"for {X.shape[1] + int(intercept)} coefficients")
    cond = _check_design(X, list(ind), intercept, source)
    coef, E, N_inv = _solve(X, Y, intercept)
    F, p = X.shape[0], X.shape[1] + int(intercept)
    S = E.T @ E / (F - p)

    # Statistics.
    ss_res = np.sum(E ** 2, axis=0)
    ss_tot = np.sum((Y - Y.mean(axis=0)) ** 2, axis=0) if intercept else np.sum(Y ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = np.where(ss_tot > 0, 1.0 - ss_res / ss_tot, np.nan)
    rms = np.sqrt(ss_res / F)
    max_abs = np.max(np.abs(E), axis=0)
    # Seed 3.2 step 5: max|MC - E| < min(E).  Taken on magnitudes: the seed's
    # own T_y (about -0.5 m) could never pass the signed form, yet it is reported valid.
    seed = max_abs < np.min(np.abs(Y), axis=0)
    same_unit = len(set(du)) == 1
    mean_dev = float(np.mean(np.linalg.norm(E, axis=1))) if same_unit else math.nan
    well = cond < CONDITION_WARN

    loto_rms = loto_dev = None
    n_groups = 1
    if g is not None:
        labels = list(dict.fromkeys(g.tolist()))
        n_groups = len(labels)
        if n_groups >= 2:
            held = np.full_like(Y, np.nan)
            for lab in labels:
                test = g == lab
                try:
                    _check_design(X[~test], list(ind), intercept, source)
                except (FitError, InputError):
                    continue  # the remaining trials cannot determine the law: leave NaN
                c_k, _, _ = _solve(X[~test], Y[~test], intercept)
                held[test] = Y[test] - (X[test] @ c_k[:, :-1].T + c_k[:, -1])
            good = np.isfinite(held).all(axis=1)
            loto_rms = np.sqrt(np.mean(held[good] ** 2, axis=0)) if good.any() else np.full(len(dep), np.nan)
            loto_dev = float(np.mean(np.linalg.norm(held[good], axis=1))) if good.any() and same_unit else math.nan

    fit = LawFit(r2=r2, rms=rms, max_abs=max_abs, seed_criterion=seed, valid=bool(seed.all() and well),
                 n_frames=F, n_dropped=n_dropped, condition=cond, well_conditioned=well,
                 mean_deviation=mean_dev, n_groups=n_groups, loto_rms=loto_rms, loto_mean_deviation=loto_dev)
    return CorrelativeLaw(joint=joint, independent=ind, dependent=dep, coefficients=coef,
                          independent_units=iu, dependent_units=du, residual_covariance=S,
                          normal_inverse=N_inv, fit=fit)


def fit_laws_by_group(independent, dependent, groups, independent_names=None, dependent_names=None,
                      **kwargs) -> dict:
    """One law per group label (per trial or per sub-motion, e.g. crouch per foot angle).

    Returns ``{label: CorrelativeLaw}`` in order of first appearance.
    """
    X = np.asarray(independent, dtype=float)
    Y = np.asarray(dependent, dtype=float)
    g = np.asarray(groups)
    if len(g) != len(X):
        raise InputError(kwargs.get("source"), "one group label per frame needed")
    src = kwargs.pop("source", None)
    out = {}
    for lab in dict.fromkeys(g.tolist()):
        sel = g == lab
        out[lab] = fit_law(X[sel], Y[sel], independent_names, dependent_names,
                           source=f"{src} [{lab}]" if src else f"group {lab}", **kwargs)
    return out


# --------------------------------------------------------------------- scaling and transfer
def scale_factor(target: Mapping[str, np.ndarray], source: Mapping[str, np.ndarray],
                 trochanter: str = "RGT", lateral: str = "RLFE", medial: str = "RMFE") -> float:
    """Seed eq. (3): ``s = (s1 + s2) / 2``.

    ``s1 = |GT - LFE|_target / |GT - LFE|_source``,
    ``s2 = |MFE - LFE|_target / |MFE - LFE|_source``; landmarks in metres
    (any frame of each model: only distances are used).
    """
    for lm, name in ((target, "target"), (source, "source")):
        missing = [n for n in (trochanter, lateral, medial) if n not in lm]
        if missing:
            raise InputError(name, f"landmarks missing: {', '.join(missing)}")

    def dist(lm, a, b):
        d = float(np.linalg.norm(np.asarray(lm[a], float) - np.asarray(lm[b], float)))
        if not d > 1e-6:
            raise InputError(None, f"landmarks {a} and {b} coincide")
        return d

    s1 = dist(target, trochanter, lateral) / dist(source, trochanter, lateral)
    s2 = dist(target, medial, lateral) / dist(source, medial, lateral)
    return 0.5 * (s1 + s2)


def knee_landmark_frame(trochanter, lateral, medial, side: str = "r") -> np.ndarray:
    """Seed section 3.1 knee frame from three femoral landmarks, as a (3, 3) rotation.

    Columns are the axes in the input coordinates: Z parallel to the
    epicondyle line pointing to the subject's right, Y in the plane of the
    epicondyles and the trochanter, orthogonal to Z, pointing cranially,
    X = Y x Z pointing anteriorly.
    """
    gt, lfe, mfe = (np.asarray(v, dtype=float).reshape(3) for v in (trochanter, lateral, medial))
    z = (lfe - mfe) if side == "r" else (mfe - lfe)
    nz = np.linalg.norm(z)
    if nz < 1e-6:
        raise InputError(None, "epicondyle landmarks coincide")
    z /= nz
    up = gt - 0.5 * (lfe + mfe)
    y = up - np.dot(up, z) * z
    ny = np.linalg.norm(y)
    if ny < 1e-6:
        raise InputError(None, "trochanter lies on the epicondyle line: knee frame undefined")
    y /= ny
    x = np.cross(y, z)
    return np.column_stack([x, y, z])


@dataclass(frozen=True, eq=False)
class LawTransfer:
    """Result of `transfer_law`.

    Attributes
    ----------
    law : CorrelativeLaw
        The law expressed in the target model's parent frame.
    rotation : ndarray (3, 3)
        ``R = R_target R_source^T``: maps directions of the source law frame to
        the target parent frame; it is the orientation to give the correlative
        joint's frame (its rotation axes) in the target parent body (step 5).
    scale : float
        Eq. (3) factor applied.
    """

    law: CorrelativeLaw
    rotation: np.ndarray
    scale: float


def transfer_law(law: CorrelativeLaw, source_landmarks: Mapping[str, np.ndarray],
                 target_landmarks: Mapping[str, np.ndarray], names: Sequence[str] = ("RGT", "RLFE", "RMFE"),
                 side: str = "r", source_origin=None, target_origin=None) -> LawTransfer:
    """Five-step transfer of a knee law to a model with other segment frames (seed 4.2).

    1-2. three landmarks (trochanter, lateral and medial epicondyle, `names`) on
         the parent body of the source and of the target model, each in that
         model's parent-body frame (metres);
    3.   scale factor ``s`` by eq. (3);
    4.   landmark frames ``R_source``, ``R_target`` (`knee_landmark_frame`);
    5.   composition ``R = R_target R_source^T``; the translations map as::

             T_target = o_target + s R (T_source - o_source)

         so the new slopes are ``s R C`` and the new constant
         ``o_target + s R (c0 - o_source)``.  The origins default to zero: the
         law's translations are measured from the parent-joint origin (the hip
         for the knee, seed 3.2), which is where eq. (3) scales about.

    The dependents must be the three translations (m) along the source frame axes.
    """
    if len(law.dependent) != 3 or any(u != "m" for u in law.dependent_units):
        raise InputError(None, f"law {law.joint!r}: transfer needs three translational dependents (m)")
    gt, lat, med = names
    s = scale_factor(target_landmarks, source_landmarks, gt, lat, med)
    Rs = knee_landmark_frame(source_landmarks[gt], source_landmarks[lat], source_landmarks[med], side)
    Rt = knee_landmark_frame(target_landmarks[gt], target_landmarks[lat], target_landmarks[med], side)
    R = Rt @ Rs.T
    o_s = np.zeros(3) if source_origin is None else np.asarray(source_origin, float)
    o_t = np.zeros(3) if target_origin is None else np.asarray(target_origin, float)
    new = law.transformed(s * R, o_t - s * R @ o_s)
    return LawTransfer(law=new, rotation=R, scale=s)


# --------------------------------------------------------------------- tables and plot
@dataclass(frozen=True)
class TextTable:
    """A small table with CSV and Markdown renderings."""

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    title: str = ""

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.header)
        w.writerows(self.rows)
        return buf.getvalue()

    def to_markdown(self) -> str:
        widths = [max(len(str(r[i])) for r in (self.header,) + self.rows) for i in range(len(self.header))]
        line = lambda r: "| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
        out = [f"{self.title}\n" if self.title else ""]
        out.append(line(self.header))
        out.append("| " + " | ".join("-" * w for w in widths) + " |")
        out.extend(line(r) for r in self.rows)
        return "\n".join(out).lstrip("\n") + "\n"


def coefficient_table(laws: Mapping[str, CorrelativeLaw], digits: int = 4, with_sd: bool = True) -> TextTable:
    """Seed Table 1 form: one column per law, rows ``c1_d..ck_d, c0_d`` grouped by dependent.

    Slopes in the law's dependent unit per independent unit, constants in the
    dependent unit; ``value ± sd`` when the law has a covariance.
    """
    laws = dict(laws)
    if not laws:
        raise InputError(None, "no law to tabulate")
    first = next(iter(laws.values()))
    for name, law in laws.items():
        if law.dependent != first.dependent or law.independent != first.independent:
            raise InputError(None, f"law {name!r} has other coordinates than {first.joint!r}: cannot share a table")
    k = len(first.independent)
    rows = []
    for d, dn in enumerate(first.dependent):
        for i in range(k + 1):
            label = f"c{i + 1}" if i < k else f"c{k + 1}"
            what = first.independent[i] if i < k else "constant"
            unit = (f"{first.dependent_units[d]}/{first.independent_units[i]}" if i < k else first.dependent_units[d])
            row = [dn, f"{label} ({what})", unit]
            for law in laws.values():
                v = law.coefficients[d, i]
                sd = law.coefficient_sd
                row.append(f"{v:.{digits}f}" + (f" ± {sd[d, i]:.{digits}f}" if with_sd and sd is not None else ""))
            rows.append(tuple(row))
    header = ("dependent", "coefficient", "unit") + tuple(laws)
    return TextTable(header, tuple(rows), "Multiple regression coefficients (seed Table 1 form)")


def deviation_table(cells: Mapping[str, Mapping[str, tuple[float, float | None]]], unit: str = "mm",
                    digits: int = 2) -> TextTable:
    """Seed Table 2 form: average deviation, ``motion specific / sub-motion specific``.

    Parameters
    ----------
    cells : ``{row (motion): {column (subject): (motion_law_dev, submotion_law_dev or None)}}``
        Deviations in metres (mean Euclidean distance between data and law).
    unit : ``"mm"`` or ``"m"``
    """
    f = {"mm": 1e3, "m": 1.0}[unit]
    cols = list(dict.fromkeys(c for row in cells.values() for c in row))
    rows = []
    for rname, row in cells.items():
        out = [rname]
        for c in cols:
            if c not in row:
                out.append("")
                continue
            a, b = row[c]
            sa = "-" if a is None or not math.isfinite(a) else f"{a * f:.{digits}f}"
            sb = "-" if b is None or not math.isfinite(b) else f"{b * f:.{digits}f}"
            out.append(f"{sa} / {sb}")
        rows.append(tuple(out))
    return TextTable(("motion",) + tuple(cols), tuple(rows),
                     f"Average deviation ({unit}) between data and law (motion specific / sub-motion specific)")


def plot_deviation(path: str | os.PathLike, independent, deviation, names: Sequence[str],
                   title: str = "", unit: str = "mm", angle_unit: str = "deg") -> Path:
    """Seed Figure 3 form: deviation coloured over the independent coordinates (PNG, Agg).

    Parameters
    ----------
    independent : array (F, k), radians (shown in degrees when `angle_unit` is ``deg``)
    deviation : array (F,), metres
    names : independent names (axis labels)
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    X = np.asarray(independent, float)
    X = np.atleast_2d(X.T).T
    dev = np.asarray(deviation, float) * {"mm": 1e3, "m": 1.0}[unit]
    if angle_unit == "deg":
        X = np.degrees(X)
    k = X.shape[1]
    fig = Figure(figsize=(7.5, 6.0), dpi=110)
    if k >= 3:
        ax = fig.add_subplot(111, projection="3d")
        sc = ax.scatter(X[:, 0], X[:, 1], X[:, 2], c=dev, cmap="jet", s=8, vmin=dev.min(), vmax=dev.max())
        ax.set_zlabel(f"{names[2]} ({angle_unit})", labelpad=8)
        ax.set_box_aspect(None, zoom=0.85)
    elif k == 2:
        ax = fig.add_subplot(111)
        sc = ax.scatter(X[:, 0], X[:, 1], c=dev, cmap="jet", s=8)
    else:
        ax = fig.add_subplot(111)
        sc = ax.scatter(X[:, 0], dev, c=dev, cmap="jet", s=8)
        ax.set_ylabel(f"deviation ({unit})")
    ax.set_xlabel(f"{names[0]} ({angle_unit})")
    if k >= 2:
        ax.set_ylabel(f"{names[1]} ({angle_unit})")
    fig.colorbar(sc, ax=ax, shrink=0.7, pad=0.12, label=f"deviation ({unit}), blue = min, red = max")
    ax.set_title(title or "Deviation between data and correlative law")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
