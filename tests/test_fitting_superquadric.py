"""Superquadric recovery over the epsilon grid, with outliers, random poses and sizes."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from personalize.fitting import (NonFiniteError, TooFewPointsError, fit_superquadric)
from personalize.fitting.superquadric import _problem, _phi, sq_radial_distance
from personalize.fitting.synthetic import add_outliers, random_rotation, superquadric_surface

GRID = (0.3, 0.7, 1.0, 1.5)
POSES = 5


def _random_case(rng, e1, e2):
    # Distinct semi-axes (>= 15 % apart) so that every axis is defined;
    # a1 >= a2 as the fit orders them.
    while True:
        a = rng.uniform(10.0, 30.0, 3)
        s = np.sort(a)
        if s[1] > 1.15 * s[0] and s[2] > 1.15 * s[1]:
            break
    if a[1] > a[0]:
        a[[0, 1]] = a[[1, 0]]
    return a, random_rotation(rng), rng.uniform(-100, 100, 3)


def _success(f, a, Rm, c, e1, e2):
    size = a.mean()
    centre_ok = np.linalg.norm(f.centre - c) < 0.02 * size
    eps_ok = np.all(np.abs(f.shape - [e1, e2]) < 0.1)
    if e1 == e2:
        # All three labels are equivalent: match axes by size.
        order_t, order_f = np.argsort(a), np.argsort(f.scale)
        Rt, Rf = Rm[:, order_t], f.rotation[:, order_f]
    else:
        Rt, Rf = Rm, f.rotation
    cosines = np.abs(np.sum(Rt * Rf, axis=0))          # axes up to sign
    axes_ok = np.all(cosines > np.cos(np.radians(3.0)))
    return bool(centre_ok and eps_ok and axes_ok)


@pytest.fixture(scope="module")
def grid_results():
    rng = np.random.default_rng(2022)
    out = []
    for e1, e2 in itertools.product(GRID, GRID):
        for _ in range(POSES):
            a, Rm, c = _random_case(rng, e1, e2)
            P, _ = superquadric_surface(rng, 2400, a, (e1, e2), 0.01 * a.mean(), c, Rm)
            Q, _ = add_outliers(rng, P, 0.2)             # N = 3000, 20 % outliers
            f = fit_superquadric(Q, rng=rng.integers(1 << 30))
            out.append((e1, e2, _success(f, a, Rm, c, e1, e2), f))
    return out


def test_recovery_rate_over_epsilon_grid(grid_results):
    ok = [s for *_, s, _ in grid_results]
    failures = [(e1, e2, np.round(f.shape, 2)) for e1, e2, s, f in grid_results if not s]
    assert np.mean(ok) >= 0.95, failures


def test_every_result_is_finite_and_converged(grid_results):
    for *_, f in grid_results:
        assert f.converged
        assert np.all(np.isfinite(f.covariance))
        assert np.all((f.shape >= 0.1) & (f.shape <= 1.9))
        np.testing.assert_allclose(f.rotation.T @ f.rotation, np.eye(3), atol=1e-9)
        assert np.linalg.det(f.rotation) > 0
        assert f.scale[0] >= f.scale[1]


def test_analytic_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(40, 3))
    fun, retract = _problem(X)
    x = (np.array([0.1, 0.2, 0.3]), random_rotation(rng), np.log([1.0, 0.7, 0.5]),
         _phi(0.6), _phi(1.4))
    _, J = fun(x, True)
    h = 1e-6
    Jn = np.column_stack([
        (fun(retract(x, h * e), False)[0] - fun(retract(x, -h * e), False)[0]) / (2 * h)
        for e in np.eye(11)])
    np.testing.assert_allclose(J, Jn, atol=1e-6)


def test_powers_are_safe_for_extreme_exponents():
    rng = np.random.default_rng(3)
    P = rng.normal(size=(1000, 3)) * np.array([1e-9, 1.0, 1e3])
    P[0] = 0.0
    for e1, e2 in [(0.1, 0.1), (0.1, 1.9), (1.9, 0.1), (1.9, 1.9)]:
        d, parts = sq_radial_distance(P, np.log([0.5, 1.0, 2.0]), e1, e2, jac=True)
        assert np.all(np.isfinite(d))
        assert all(np.all(np.isfinite(p)) for p in parts)
    # Radial distance is exact along the axes.
    probes = np.array([[3.0, 0, 0], [0, 0, 1.0]])
    d, _ = sq_radial_distance(probes, np.log([1.0, 1.0, 2.0]), 0.1, 0.1)
    np.testing.assert_allclose(d, [2.0, -1.0], atol=1e-9)


def test_residuals_and_invariance_to_similarity_and_order():
    rng = np.random.default_rng(4)
    a, Rm, c = np.array([0.03, 0.02, 0.012]), random_rotation(rng), np.array([0.1, 0.2, 0.3])
    P, exact = superquadric_surface(rng, 1500, a, (0.5, 1.2), 0.0002, c, Rm)
    Q, _ = add_outliers(rng, P, 0.15)
    f = fit_superquadric(Q)
    assert np.median(np.abs(f.residuals(exact))) < 1e-4
    Rg, t, s = random_rotation(rng), np.array([1.0, -2.0, 0.5]), 1000.0
    perm = rng.permutation(len(Q))
    g = fit_superquadric(s * Q[perm] @ Rg.T + t)
    # Equal up to the stopping tolerance (1 % of the statistical standard deviation).
    sd = np.sqrt(np.diag(f.covariance))
    np.testing.assert_allclose(g.centre, s * Rg @ f.centre + t, atol=0.05 * s * sd[:3].max())
    np.testing.assert_allclose(g.scale, s * f.scale, atol=0.05 * s * sd[6:9].max())
    np.testing.assert_allclose(g.shape, f.shape, atol=0.05 * sd[9:].max())
    # Axes agree up to sign (the surface is symmetric under axis reflections).
    np.testing.assert_allclose(np.abs(g.rotation.T @ Rg @ f.rotation), np.eye(3),
                               atol=0.05 * sd[3:6].max())


def test_bad_input():
    with pytest.raises(TooFewPointsError):
        fit_superquadric(np.random.default_rng(0).normal(size=(10, 3)))
    P = np.random.default_rng(0).normal(size=(100, 3))
    P[3] = np.inf
    with pytest.raises(NonFiniteError):
        fit_superquadric(P)
