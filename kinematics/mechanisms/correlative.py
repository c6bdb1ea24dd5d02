"""Correlative joints: linear regression laws between joint coordinates.

Pronost, Sandholm & Thalmann (2010), *Correlative joint definition for motion
analysis and animation*: the translations of a six-DOF joint (e.g. the knee
joint centre) are linear functions of its rotations, fitted per motion (and
per sub-motion) by multiple linear regression (their eq. 1)::

    T_d(f) = c1_d a1(f) + c2_d a2(f) + ... + ck_d ak(f) + c0_d,     d = 1..D

(the seed's ``c4`` is ``c0`` here, stored last: coefficients ``[c1, ..., ck, c0]``).

`CorrelativeLaw` is the law (prediction with its standard error, transforms,
eq. (3) scaling, JSON ``law.json``, the coupling rows IK enforces) and
`LawFit` its goodness of fit.  Fitting: `kinematics.mechanisms.correlative_fit`;
transfer to another model: `kinematics.mechanisms.law_transfer`.

Units: independents in radians (or metres), dependents in metres (or radians);
slopes in dependent unit per independent unit (m/rad for the knee), intercept
in the dependent unit.  The law itself records them.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from lowerlimb.atomic import write_text
from lowerlimb.errors import FitError, InputError
from lowerlimb.json_format import json_text

__all__ = ["LawFit", "CorrelativeLaw"]


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
