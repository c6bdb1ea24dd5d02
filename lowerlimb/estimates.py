"""A Gaussian estimate: mean and covariance, the value every stage of the pipeline passes on.

An estimate x ~ N(mean, cov) of a vector quantity in SI units (a joint centre
in m with its covariance in m², a segment length in m with its variance in
m²).  Under a rigid transform y = R x + t (R known exactly) it becomes
N(R mean + t, R cov Rᵀ); a covariance scale k (a calibration of a source's
claimed uncertainty) gives N(mean, k cov).  Uncertainty of the transform
itself is the registration's job (`personalize.registration.Registration.transfer_point`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Gaussian"]


@dataclass(frozen=True)
class Gaussian:
    """x ~ N(mean, cov).

    mean : (n,) SI units; cov : (n, n), units of the mean squared (symmetric, positive semi-definite)
    """

    mean: np.ndarray
    cov: np.ndarray

    def __post_init__(self) -> None:
        m = np.atleast_1d(np.asarray(self.mean, float)).reshape(-1)
        c = np.asarray(self.cov, float)
        if c.ndim == 0:
            c = float(c) * np.eye(m.size)
        c = c.reshape(m.size, m.size)
        object.__setattr__(self, "mean", m)
        object.__setattr__(self, "cov", c)

    @classmethod
    def isotropic(cls, mean, sd: float) -> "Gaussian":
        """N(mean, sd² I)."""
        m = np.atleast_1d(np.asarray(mean, float)).reshape(-1)
        return cls(m, float(sd) ** 2 * np.eye(m.size))

    @property
    def dim(self) -> int:
        return int(self.mean.size)

    @property
    def sd(self) -> np.ndarray:
        """(n,) per-component standard deviations."""
        return np.sqrt(np.diag(self.cov))

    @property
    def rms_sd(self) -> float:
        """√(tr cov / n): one isotropic-equivalent sd."""
        return float(np.sqrt(np.trace(self.cov) / self.dim))

    def scaled(self, factor: float) -> "Gaussian":
        """The same mean with covariance factor × cov (a calibrated covariance scale)."""
        return Gaussian(self.mean, float(factor) * self.cov)

    def inflated(self, cov) -> "Gaussian":
        """The same mean with an independent error term added: cov + `cov`."""
        return Gaussian(self.mean, self.cov + np.asarray(cov, float).reshape(self.cov.shape))

    def transformed(self, R, t) -> "Gaussian":
        """N(R mean + t, R cov Rᵀ) under an exact rigid map y = R x + t."""
        R = np.asarray(R, float).reshape(self.dim, self.dim)
        return Gaussian(R @ self.mean + np.asarray(t, float).reshape(self.dim), R @ self.cov @ R.T)

    def mahalanobis2(self, x) -> float:
        """(x - mean)ᵀ cov⁻¹ (x - mean)."""
        r = np.asarray(x, float).reshape(self.dim) - self.mean
        return float(r @ np.linalg.solve(self.cov, r))

    def to_json(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.cov.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> "Gaussian":
        return cls(np.asarray(d["mean"], float), np.asarray(d["cov"], float))
