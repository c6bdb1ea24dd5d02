"""Analytic cases for the shared geometry helpers (lowerlimb.geometry)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lowerlimb.errors import InputError
from lowerlimb.geometry import (DEFAULT_MARKER_DIAMETER, DEFAULT_MARKER_RADIUS, frame_yz, frame_zy, kabsch, kabsch_rotation,
                                marker_radius, orient, skew, unit, vertex_normals)


def test_unit_single_and_batched():
    np.testing.assert_allclose(unit([3.0, 0.0, 4.0]), [0.6, 0.0, 0.8], atol=1e-15)
    u = unit(np.array([[0.0, 2.0, 0.0], [1.0, 1.0, 1.0]]))
    np.testing.assert_allclose(u, [[0, 1, 0], [3 ** -0.5] * 3], atol=1e-15)
    assert u.shape == (2, 3)


def test_unit_zero_vector_nan_or_refused():
    with np.errstate(invalid="ignore"):
        assert np.all(np.isnan(unit([0.0, 0.0, 0.0])))
    with pytest.raises(InputError, match="knee axis.*zero or non-finite"):
        unit([0.0, 0.0, 1e-14], where="knee axis")
    with pytest.raises(InputError):
        unit([[1.0, 0, 0], [np.nan, 0, 0]], where="x")


def test_skew_is_cross_product():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b), atol=1e-15)
    K = skew([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(K, [[0, -3, 2], [3, 0, -1], [-2, 1, 0]])
    np.testing.assert_array_equal(K, -K.T)


def test_frames_keep_one_axis_exact():
    z, yh = np.array([0.0, 0.0, 2.0]), np.array([0.3, 1.0, 0.5])
    R = frame_zy(z, yh)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(R[:, 1], unit([0.3, 1.0, 0.0]), atol=1e-15)  # hint minus its z part
    R2 = frame_yz([0.0, 5.0, 0.0], [1.0, 0.2, 1.0])
    np.testing.assert_allclose(R2[:, 1], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(R2[:, 2], unit([1.0, 0.0, 1.0]), atol=1e-15)
    np.testing.assert_allclose(R2[:, 0], np.cross(R2[:, 1], R2[:, 2]), atol=1e-15)
    with pytest.raises(InputError, match="model"):
        frame_zy([0, 0, 1], [0, 0, 3], where="model")        # hint parallel to the axis


def test_kabsch_recovers_rigid_motion_weighted_and_not():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(8, 3)) * 0.1
    R0 = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    t0 = np.array([0.1, -0.2, 0.3])
    Q = P @ R0.T + t0
    for w in (None, rng.uniform(0.5, 2.0, 8)):
        R, t = kabsch(P, Q, w)
        np.testing.assert_allclose(R, R0, atol=1e-12)
        np.testing.assert_allclose(t, t0, atol=1e-12)
    # a zero weight drops an outlier exactly
    Q[0] += 1.0
    w = np.ones(8)
    w[0] = 0.0
    R, t = kabsch(P, Q, w)
    np.testing.assert_allclose(R, R0, atol=1e-12)


def test_kabsch_planar_points_no_reflection_and_batched():
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    R0 = Rotation.from_rotvec([0, 0, 0.3]).as_matrix()
    R, _ = kabsch(P, P @ R0.T)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R, R0, atol=1e-12)
    # a reflected target must still give a proper rotation (det +1), not the mirror
    Rm, _ = kabsch(P, P * [1, 1, -1])
    assert np.linalg.det(Rm) == pytest.approx(1.0)
    H = np.stack([np.eye(3), R0.T])            # tr(R H) is maximal at R = H^T for a rotation H
    Rb, s = kabsch_rotation(H)
    np.testing.assert_allclose(Rb[1], R0, atol=1e-12)
    np.testing.assert_allclose(s, 1.0, atol=1e-12)
    _, s = kabsch_rotation(np.outer([1.0, 2, 3], [0.0, 1, 0]))   # collinear: one singular value
    assert s[1] < 1e-12 * s[0]


def test_vertex_normals_of_octahedron_point_outward():
    V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [5, 5, 5]], float)
    F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    N = vertex_normals(V, F)
    np.testing.assert_allclose(N[:6], V[:6], atol=1e-15)    # symmetric: the normal is the vertex direction
    np.testing.assert_array_equal(N[6], 0.0)                 # vertex on no face


def test_marker_radius_is_half_the_stated_diameter():
    assert marker_radius() == 0.007 == DEFAULT_MARKER_DIAMETER / 2 == DEFAULT_MARKER_RADIUS
    assert marker_radius(0.025) == 0.0125


def test_orient_flips_against_reference_only():
    np.testing.assert_array_equal(orient(np.array([1.0, -2, 0]), [0, 1, 0]), [-1, 2, 0])
    np.testing.assert_array_equal(orient(np.array([1.0, 2, 0]), [0, 1, 0]), [1, 2, 0])
    np.testing.assert_array_equal(orient(np.array([1.0, 0, 0]), [0, 1, 0]), [1, 0, 0])   # orthogonal: kept


def test_base_layers_import_nothing_above():
    """lowerlimb, kinematics and phantoms load (every module) without loading personalize; lowerlimb without either."""
    import subprocess
    import sys

    code = ("import importlib, pkgutil, sys\n"
            "for pkg in ('lowerlimb', 'kinematics', 'phantoms'):\n"
            "    p = importlib.import_module(pkg)\n"
            "    for m in pkgutil.walk_packages(p.__path__, pkg + '.'):\n"
            "        importlib.import_module(m.name)\n"
            "    loaded = {k.split('.')[0] for k in sys.modules}\n"
            "    above = {'lowerlimb': {'kinematics', 'phantoms', 'personalize'}}.get(pkg, {'personalize'})\n"
            "    assert not loaded & above, (pkg, loaded & above)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
