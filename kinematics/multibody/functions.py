"""Scalar functions of generalized coordinates used by joints and couplers.

Every function maps ``n_inputs`` coordinates to one value and is evaluated
vectorised over N samples::

    f : R^(N, n_inputs) -> R^N,   gradient  df/dx : (N, n_inputs),
    hessian d2f/dx2 : (N, n_inputs, n_inputs)

They reproduce OpenSim's ``Constant``, ``LinearFunction``, ``SimmSpline``,
``NaturalCubicSpline``, ``MultiplierFunction`` and a multivariate linear form
``f(x) = c0 + sum_i c_i x_i`` (the correlative joint of Pronost et al. 2010,
eq. 2; OpenSim's order-1 ``MultivariatePolynomialFunction``).

All functions are immutable (frozen dataclasses with read-only arrays).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Function", "Constant", "Linear", "NaturalCubicSpline", "SimmSpline",
    "Multiplier", "MultivariateLinear", "read_only",
]


def read_only(a, dtype=float) -> np.ndarray:
    """A read-only copy of `a` (the arrays of immutable models, joints and functions)."""
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


def _as_input(x, n_inputs: int) -> np.ndarray:
    """Coerce `x` to shape (N, n_inputs)."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        x = x.reshape(1, 1)
    elif x.ndim == 1:
        x = x[:, None] if n_inputs == 1 else x[None, :]
    if x.shape[-1] != n_inputs:
        raise ValueError(f"function of {n_inputs} inputs evaluated on array of shape {x.shape}")
    return x


class Function:
    """Base class: a smooth scalar function of ``n_inputs`` coordinates."""

    n_inputs: int = 1

    def evaluate(self, x, order: int = 1):
        """Value and derivatives.

        Parameters
        ----------
        x : array_like, shape (N, n_inputs) (or (N,) when n_inputs == 1)
        order : {0, 1, 2}
            Highest derivative wanted.

        Returns
        -------
        value : ndarray (N,)
        gradient : ndarray (N, n_inputs), if order >= 1
        hessian : ndarray (N, n_inputs, n_inputs), if order >= 2
        """
        raise NotImplementedError

    def __call__(self, x) -> np.ndarray:
        return self.evaluate(x, order=0)[0]


@dataclass(frozen=True)
class Constant(Function):
    """f(x) = value (no input; ``n_inputs`` may be 0 or 1 for OpenSim axes)."""

    value: float
    n_inputs: int = 0

    def evaluate(self, x=None, order: int = 1):
        x = np.zeros((1, self.n_inputs)) if x is None else np.asarray(x, dtype=float)
        n = x.shape[0] if x.ndim >= 1 else 1
        out = [np.full(n, float(self.value))]
        if order >= 1:
            out.append(np.zeros((n, self.n_inputs)))
        if order >= 2:
            out.append(np.zeros((n, self.n_inputs, self.n_inputs)))
        return tuple(out)


@dataclass(frozen=True)
class Linear(Function):
    """f(x) = slope * x + intercept  (OpenSim ``LinearFunction`` coefficients ``slope intercept``)."""

    slope: float = 1.0
    intercept: float = 0.0
    n_inputs: int = field(default=1, init=False)

    def evaluate(self, x, order: int = 1):
        x = _as_input(x, 1)[:, 0]
        out = [self.slope * x + self.intercept]
        if order >= 1:
            out.append(np.full((x.size, 1), float(self.slope)))
        if order >= 2:
            out.append(np.zeros((x.size, 1, 1)))
        return tuple(out)


@dataclass(frozen=True, eq=False)
class _PiecewiseCubic(Function):
    """Cubic pieces y_k + b_k dx + c_k dx^2 + d_k dx^3 on [x_k, x_k+1], linear outside."""

    x: np.ndarray
    y: np.ndarray
    n_inputs: int = field(default=1, init=False)
    b: np.ndarray = field(init=False, repr=False, compare=False)
    c: np.ndarray = field(init=False, repr=False, compare=False)
    d: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        x = read_only(self.x)
        y = read_only(self.y)
        if x.ndim != 1 or x.shape != y.shape or x.size < 2:
            raise ValueError("spline needs matching 1-D x and y with at least 2 points")
        if np.any(np.diff(x) <= 0):
            raise ValueError("spline abscissae must be strictly increasing")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)
        b, c, d = self._coefficients(x, y)
        object.__setattr__(self, "b", read_only(b))
        object.__setattr__(self, "c", read_only(c))
        object.__setattr__(self, "d", read_only(d))

    @staticmethod
    def _coefficients(x, y):
        raise NotImplementedError

    def evaluate(self, x, order: int = 1):
        t = _as_input(x, 1)[:, 0]
        xs, n = self.x, self.x.size
        k = np.clip(np.searchsorted(xs, t, side="right") - 1, 0, n - 2)
        dx = t - xs[k]
        b, c, d = self.b[k], self.c[k], self.d[k]
        val = self.y[k] + dx * (b + dx * (c + dx * d))
        der = b + dx * (2.0 * c + 3.0 * dx * d)
        sec = 2.0 * c + 6.0 * dx * d
        # Outside the knots OpenSim extrapolates linearly with the end slopes.
        lo, hi = t < xs[0], t > xs[-1]
        if lo.any():
            val[lo] = self.y[0] + (t[lo] - xs[0]) * self.b[0]
            der[lo] = self.b[0]
            sec[lo] = 0.0
        if hi.any():
            val[hi] = self.y[-1] + (t[hi] - xs[-1]) * self.b[-1]
            der[hi] = self.b[-1]
            sec[hi] = 0.0
        out = [val]
        if order >= 1:
            out.append(der[:, None])
        if order >= 2:
            out.append(sec[:, None, None])
        return tuple(out)


@dataclass(frozen=True, eq=False)
class SimmSpline(_PiecewiseCubic):
    """OpenSim/SIMM interpolating cubic spline.

    The cubic through the knots (x_k, y_k) whose end conditions match the third
    derivative at each end to the third divided difference of the first (last)
    four knots (Forsythe, Malcolm & Moler 1977, the ``spline`` routine SIMM and
    OpenSim's ``SimmSpline`` use).  With 2 knots it is the line through them,
    with 3 knots the end conditions become y''' = 0 at both ends.  Outside
    [x_0, x_n-1] it continues linearly with the end slopes, as OpenSim does.
    """

    @staticmethod
    def _coefficients(x, y):
        n = x.size
        b = np.zeros(n)
        c = np.zeros(n)
        d = np.zeros(n)
        if n == 2:
            s = (y[1] - y[0]) / (x[1] - x[0])
            b[:] = s
            return b, c, d
        nm1, nm2 = n - 1, n - 2
        # Tridiagonal system: b diagonal, d off-diagonal, c right-hand side.
        d[0] = x[1] - x[0]
        c[1] = (y[1] - y[0]) / d[0]
        for i in range(1, nm1):
            d[i] = x[i + 1] - x[i]
            b[i] = 2.0 * (d[i - 1] + d[i])
            c[i + 1] = (y[i + 1] - y[i]) / d[i]
            c[i] = c[i + 1] - c[i]
        b[0] = -d[0]
        b[nm1] = -d[nm2]
        c[0] = 0.0
        c[nm1] = 0.0
        if n > 3:
            d31 = x[3] - x[1]
            d20 = x[2] - x[0]
            d1 = x[nm1] - x[n - 3]
            d2 = x[nm2] - x[n - 4]
            d30 = x[3] - x[0]
            d3 = x[nm1] - x[n - 4]
            c[0] = c[2] / d31 - c[1] / d20
            c[nm1] = c[nm2] / d1 - c[n - 3] / d2
            c[0] = c[0] * d[0] * d[0] / d30
            c[nm1] = -c[nm1] * d[nm2] * d[nm2] / d3
        for i in range(1, n):
            t = d[i - 1] / b[i - 1]
            b[i] -= t * d[i - 1]
            c[i] -= t * c[i - 1]
        c[nm1] /= b[nm1]
        for i in range(nm2, -1, -1):
            c[i] = (c[i] - d[i] * c[i + 1]) / b[i]
        b[nm1] = (y[nm1] - y[nm2]) / d[nm2] + d[nm2] * (c[nm2] + 2.0 * c[nm1])
        for i in range(nm1):
            b[i] = (y[i + 1] - y[i]) / d[i] - d[i] * (c[i + 1] + 2.0 * c[i])
            d[i] = (c[i + 1] - c[i]) / d[i]
            c[i] *= 3.0
        c[nm1] *= 3.0
        d[nm1] = d[nm2]
        return b, c, d


@dataclass(frozen=True, eq=False)
class NaturalCubicSpline(_PiecewiseCubic):
    """Natural cubic interpolating spline (y'' = 0 at both end knots), linear outside."""

    @staticmethod
    def _coefficients(x, y):
        from scipy.interpolate import CubicSpline

        cs = CubicSpline(x, y, bc_type="natural")
        n = x.size
        b = np.empty(n)
        c = np.empty(n)
        d = np.empty(n)
        d_, c_, b_ = cs.c[0], cs.c[1], cs.c[2]
        b[:-1], c[:-1], d[:-1] = b_, c_, d_
        h = x[-1] - x[-2]
        b[-1] = b_[-1] + 2 * c_[-1] * h + 3 * d_[-1] * h * h
        c[-1] = 0.0
        d[-1] = 0.0
        return b, c, d


@dataclass(frozen=True, eq=False)
class Multiplier(Function):
    """f(x) = scale * g(x)  (OpenSim ``MultiplierFunction``)."""

    function: Function
    scale: float = 1.0

    @property
    def n_inputs(self) -> int:  # type: ignore[override]
        return self.function.n_inputs

    def evaluate(self, x, order: int = 1):
        return tuple(self.scale * v for v in self.function.evaluate(x, order))


@dataclass(frozen=True, eq=False)
class MultivariateLinear(Function):
    """f(x) = intercept + sum_i coefficients_i x_i  (correlative form, Pronost et al. 2010 eq. 2)."""

    coefficients: np.ndarray
    intercept: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "coefficients", read_only(np.atleast_1d(self.coefficients)))

    @property
    def n_inputs(self) -> int:  # type: ignore[override]
        return int(self.coefficients.size)

    def evaluate(self, x, order: int = 1):
        x = _as_input(x, self.n_inputs)
        out = [x @ self.coefficients + self.intercept]
        if order >= 1:
            out.append(np.broadcast_to(self.coefficients, x.shape).copy())
        if order >= 2:
            out.append(np.zeros((x.shape[0], self.n_inputs, self.n_inputs)))
        return tuple(out)
