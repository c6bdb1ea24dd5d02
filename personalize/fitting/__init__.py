"""Robust geometric fitting of shape primitives (issue F2).

Every ``fit_*`` function takes ``points`` (N, 3), optional ``normals`` (N, 3)
and ``weights`` (N,), works in any length unit (the project passes metres) and
returns a frozen result with the shape parameters, ``covariance``, ``rms``,
``inlier_weights``, ``n_iterations``, ``converged`` and ``residuals(points)``.
Failures raise `FittingError` (a `lowerlimb.errors.FitError`) or one of its
subclasses: `TooFewPointsError`, `NonFiniteError`, `DegenerateError`,
`NotConvergedError`.

All fits are geometric (orthogonal distance for sphere, cylinder and plane;
radial distance for ellipsoid and superquadric), start from a closed-form
estimate, are refined with analytic Jacobians and are robust through a
Gaussian-uniform mixture (``inlier_weights`` = posterior inlier probability);
``robust=False`` gives plain least squares from the same start.  Covariances
are Gauss-Newton ones scaled by the inlier residual variance.

Example (femoral head centre from a segmented head surface, metres)::

    from personalize.fitting import fit_sphere
    head = fit_sphere(points)
    femoral_head_centre = head.centre                  # (3,) m
    femoral_head_centre_cov = head.covariance[:3, :3]  # (3, 3) m^2

`ransac` wraps any ``fit_*`` for majority clutter or competing surfaces;
`synthetic` generates point clouds with known truth for tests and benchmarks.
"""
from .base import (DegenerateError, FittingError, NonFiniteError, NotConvergedError,
                   TooFewPointsError)
from .cylinder import CylinderFit, fit_cylinder
from .ellipsoid import EllipsoidFit, fit_ellipsoid
from .plane import PlaneFit, fit_plane
from .ransac import RansacResult, ransac
from .sphere import SphereFit, fit_sphere
from .superquadric import SuperquadricFit, fit_superquadric

__all__ = [
    "FittingError", "TooFewPointsError", "NonFiniteError", "DegenerateError",
    "NotConvergedError",
    "SphereFit", "fit_sphere", "CylinderFit", "fit_cylinder", "PlaneFit", "fit_plane",
    "EllipsoidFit", "fit_ellipsoid", "SuperquadricFit", "fit_superquadric",
    "RansacResult", "ransac",
]
