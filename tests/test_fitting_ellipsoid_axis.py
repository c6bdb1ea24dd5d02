"""Axis-constrained ellipsoid (`fit_ellipsoid_about_axis`): partial arcs, outliers, equivariance, errors."""
from __future__ import annotations

import numpy as np
import pytest

from personalize.fitting import DegenerateError
from personalize.fitting.ellipsoid import fit_ellipsoid_about_axis
from personalize.fitting.synthetic import add_outliers, random_rotation


def _condyle_arc(rng, n=1500, noise=0.3):
    """Posterior-distal arc (~200 degrees in the sagittal plane) of a condyle-like ellipsoid, mm."""
    a = np.array([28.0, 25.0, 13.5])
    Rm, c = random_rotation(rng), rng.uniform(-50, 50, 3)
    th = rng.uniform(np.radians(100), np.radians(300), n)      # x anterior, y proximal
    ph = rng.uniform(-0.6, 0.6, n)                              # medio-lateral latitude
    u = np.column_stack([np.cos(ph) * np.cos(th), np.cos(ph) * np.sin(th), np.sin(ph)])
    P = c + (u * a) @ Rm.T
    normals = (u / a) @ Rm.T
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    return a, Rm, c, P + noise * rng.standard_normal(n)[:, None] * normals


def test_recovers_centre_on_partial_arc_with_outliers():
    rng = np.random.default_rng(5)
    for _ in range(4):
        a, Rm, c, P = _condyle_arc(rng)
        Q, is_out = add_outliers(rng, P, 0.2)
        R0 = Rm @ np.array([[np.cos(0.2), -np.sin(0.2), 0], [np.sin(0.2), np.cos(0.2), 0], [0, 0, 1.0]])
        f = fit_ellipsoid_about_axis(Q, Rm[:, 2], centre0=c + 3.0, radii0=[26.0, 26.0, 15.0], rotation0=R0)
        assert np.linalg.norm(f.centre - c) < 0.3
        np.testing.assert_allclose(f.radii, a, atol=0.4)
        # the semi-axis along the given axis stays exactly on it
        assert np.max(np.abs(f.rotation.T @ Rm[:, 2])) > 1 - 1e-12
        assert f.inlier_weights[~is_out].mean() > 0.9 and f.inlier_weights[is_out].mean() < 0.3
        sd = np.sqrt(np.diag(f.covariance)[:3])
        assert np.all(np.isfinite(sd)) and np.all(sd < 0.2)


def test_rigid_motion_and_mirror_equivariance():
    rng = np.random.default_rng(3)
    a, Rm, c, P = _condyle_arc(rng, n=600)
    kw = dict(centre0=c + 1.0, radii0=[26.0, 26.0, 15.0], rotation0=Rm)
    f = fit_ellipsoid_about_axis(P, Rm[:, 2], **kw)
    G, t = random_rotation(rng), np.array([10.0, -4.0, 7.0])
    g = fit_ellipsoid_about_axis(P @ G.T + t, G @ Rm[:, 2], centre0=G @ kw["centre0"] + t,
                                 radii0=kw["radii0"], rotation0=G @ Rm)
    np.testing.assert_allclose(g.centre, G @ f.centre + t, atol=1e-6)
    np.testing.assert_allclose(g.radii, f.radii, atol=1e-6)
    M = np.diag([-1.0, 1.0, 1.0])
    h = fit_ellipsoid_about_axis(P @ M, -(M @ Rm[:, 2]), centre0=M @ kw["centre0"], radii0=kw["radii0"],
                                 rotation0=M @ Rm)
    np.testing.assert_allclose(h.centre, M @ f.centre, atol=1e-6)
    np.testing.assert_allclose(h.radii, f.radii, atol=1e-6)


@pytest.mark.parametrize("axis,radii0", [([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), ([np.nan, 0.0, 1.0], [1.0, 1.0, 1.0]),
                                         ([0.0, 0.0, 1.0], [1.0, -1.0, 1.0])])
def test_bad_axis_or_start_raises(axis, radii0):
    P = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(DegenerateError):
        fit_ellipsoid_about_axis(P, axis, centre0=np.zeros(3), radii0=radii0)
