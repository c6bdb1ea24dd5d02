"""Knee flexion axis: the cylinder through the posterior condyles (`femur.posterior_condyle_cylinder`).

Analytic cases: two coaxial circular condyles (tubes) in a random pose; the
cylinder fitted on their posterior-distal arcs must be their common axis,
from a first guess several degrees and millimetres off, and move rigidly
with the input.  With unequal radii the cylinder convention tilts away from
the line through the condyle centres (the reason the phantom's condyles
share one radius).
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from personalize.landmarks.surface import as_surface
from personalize.landmarks.femoral_condyles import posterior_condyle_cylinder


def _tube(radius, half_width, z0, n_theta=173, n_z=13):
    """Closed tube about the z axis (rings of vertices exactly on the cylinder, flat caps).

    173 vertices per ring: none lies exactly on the limits of the selected arc
    (a point on a threshold may fall on either side after a rigid motion).
    """
    th = np.linspace(0.0, 2.0 * np.pi, n_theta, endpoint=False)
    zs = z0 + np.linspace(-half_width, half_width, n_z)
    V = [np.column_stack([radius * np.cos(th), radius * np.sin(th), np.full(n_theta, z)]) for z in zs]
    V = np.concatenate(V + [[[0.0, 0.0, zs[0]], [0.0, 0.0, zs[-1]]]])
    F = []
    for k in range(n_z - 1):
        a = k * n_theta + np.arange(n_theta)
        b = k * n_theta + (np.arange(n_theta) + 1) % n_theta
        F += [np.column_stack([a, b, b + n_theta]), np.column_stack([a, b + n_theta, a + n_theta])]
    lo, hi = len(V) - 2, len(V) - 1
    ring0, ring1 = np.arange(n_theta), (n_z - 1) * n_theta + np.arange(n_theta)
    F += [np.column_stack([np.full(n_theta, lo), np.roll(ring0, -1), ring0]),
          np.column_stack([np.full(n_theta, hi), ring1, np.roll(ring1, -1)])]
    return trimesh.Trimesh(V, np.concatenate(F), process=False)


def _knee(r_med, r_lat, pose, sep=0.042, half_width=0.0135):
    m = trimesh.util.concatenate([_tube(r_med, half_width, -sep / 2), _tube(r_lat, half_width, sep / 2)])
    R, t = pose
    m.vertices = np.asarray(m.vertices) @ R.T + t
    return as_surface(m, "femur_r")


@pytest.fixture(scope="module")
def pose():
    return Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix(), np.array([0.12, -0.3, 0.05])


def _fit(surface, pose, sep=0.042, tilt_deg=3.0, shift=0.002):
    R, t = pose
    off = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([0.6, 0.8, 0.0])).as_matrix()
    axis0 = R @ off @ np.array([0.0, 0.0, 1.0])
    centre0 = t + R @ np.array([shift, -shift, 0.0])
    med, lat = t + R @ [0, 0, -sep / 2], t + R @ [0, 0, sep / 2]
    region = np.ones(len(surface.vertices), bool)
    # local +y is proximal ("up"), local +x anterior: the posterior-distal arc faces -x / -y
    return posterior_condyle_cylinder(surface, region, centre0, axis0, R @ [0, 1.0, 0], R @ [1.0, 0, 0], med, lat)


def test_equal_condyles_give_their_common_axis(pose):
    R, t = pose
    fit, sel, u = _fit(_knee(0.025, 0.025, pose), pose)
    z = R @ [0.0, 0.0, 1.0]
    assert np.degrees(np.arccos(min(1.0, abs(u @ z)))) < 0.02
    p = np.asarray(fit.point)
    assert np.linalg.norm(np.cross(p - t, z)) < 2e-5                      # the axis passes through the centres
    assert fit.radius == pytest.approx(0.025, abs=5e-5)
    assert sel.sum() > 100


def test_cylinder_moves_with_the_bone(pose):
    R, t = pose
    G = Rotation.from_rotvec([-1.3, 0.2, 0.7]).as_matrix()
    g = np.array([0.5, 0.1, -0.2])
    a = _fit(_knee(0.026, 0.024, pose), pose)
    moved = (G @ R, G @ t + g)
    b = _fit(_knee(0.026, 0.024, moved), moved)
    # the equivariance limits: 0.01 degree, 0.01 mm (the fit stops at its tolerance)
    assert np.degrees(np.arccos(min(1.0, abs((G @ a[2]) @ b[2])))) < 0.01
    pa, pb = G @ np.asarray(a[0].point) + g, np.asarray(b[0].point)
    assert np.linalg.norm(np.cross(pb - pa, b[2])) < 1e-5
    assert np.array_equal(a[1], b[1])


def test_unequal_condyles_tilt_the_cylinder_away_from_the_centre_line(pose):
    # convention check: with medial and lateral radii 26 and 24 mm the cylinder through
    # the posterior-distal arcs is no longer the line through the condyle centres (z)
    R, _ = pose
    _, _, u = _fit(_knee(0.026, 0.024, pose), pose)
    tilt = np.degrees(np.arccos(min(1.0, abs(u @ (R @ [0.0, 0.0, 1.0])))))
    assert 0.5 < tilt < 5.0


def test_too_few_points_returns_none(pose):
    s = _knee(0.025, 0.025, pose)
    R, t = pose
    region = np.zeros(len(s.vertices), bool)
    assert posterior_condyle_cylinder(s, region, t, R[:, 2], R[:, 1], R[:, 0], t - 0.021 * R[:, 2],
                                      t + 0.021 * R[:, 2]) is None
