"""OpenSim import/export (kinematics.io.opensim_io)."""
from __future__ import annotations

import numpy as np
import pytest

from kin_helpers import leg_model
from kinematics.multibody.coupling import LinearCoupling
from lowerlimb.errors import InputError
from kinematics.algorithms.fk import marker_positions
from kinematics.multibody.functions import Multiplier, SimmSpline
from kinematics.io.opensim_io import load_osim, save_osim

GAIT = "opensim_gait2392/subject01_simbody_adjusted.osim"


def _opensim_markers(opensim, path, model, q):
    """Marker positions (N, M, 3) computed by OpenSim for the coordinates q (N, n_q) of `model`."""
    om = opensim.Model(str(path))
    s = om.initSystem()
    cs, ms = om.getCoordinateSet(), om.getMarkerSet()
    coords = [cs.get(c.name) for c in model.coordinates]
    mk = [ms.get(n) for n in model.marker_names]
    out = np.empty((len(q), len(mk), 3))
    for n in range(len(q)):
        for c, v in zip(coords, q[n]):
            c.setValue(s, float(v), False)
        om.realizePosition(s)
        for k, m in enumerate(mk):
            p = m.getLocationInGround(s)
            out[n, k] = (p.get(0), p.get(1), p.get(2))
    return out


def test_import_gait2392(shared_data, opensim):
    m = load_osim(shared_data / GAIT)
    assert m.n_q == 23 and len(m.markers) == 39 and m.n_bodies == 13
    knee = m.joint("knee_r")
    assert knee.kind == "custom" and knee.coordinates == ("knee_angle_r",)
    tx = knee.translations[0].function
    assert isinstance(tx, Multiplier) and isinstance(tx.function, SimmSpline)
    assert tx.scale == pytest.approx(1.14724)
    c = m.coordinates[m.coordinate_index("knee_angle_r")]
    assert c.range == pytest.approx((-2.0943951, 0.17453293))
    assert m.couplings is None and not m.couplers
    assert m.bodies[m.body_index("pelvis")].mass == pytest.approx(11.37517129)


def test_export_round_trip_matches_opensim(tmp_path, opensim):
    """An engine-built model, exported and loaded by OpenSim, gives the same markers within 1e-8 m."""
    m = leg_model()
    m = m.with_couplings(LinearCoupling.correlative(m.coordinate_names, "subtalar_angle", {"ankle_angle": 0.3}, 0.01))
    path = save_osim(m, tmp_path / "leg.osim")
    q = m.random_q(40, np.random.default_rng(5))
    x = marker_positions(m, q)
    np.testing.assert_allclose(_opensim_markers(opensim, path, m, q), x, rtol=0, atol=1e-8)
    back = load_osim(path)
    np.testing.assert_allclose(marker_positions(back, q), x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.couplings.matrix, m.couplings.matrix, atol=1e-15)
    np.testing.assert_allclose(back.couplings.rhs, m.couplings.rhs, atol=1e-15)
    assert [b.mass for b in back.bodies] == pytest.approx([b.mass for b in m.bodies])
    assert back.coordinates[back.coordinate_index("knee_angle")].range == pytest.approx(
        m.coordinates[m.coordinate_index("knee_angle")].range)


def test_standard_opensim_joints_import(tmp_path, opensim):
    """Pin, Slider, Universal, Gimbal, Ball, Free, Planar and Weld joints built with the OpenSim API."""
    osm = opensim
    om = osm.Model()
    rng = np.random.default_rng(0)
    parent = om.getGround()
    kinds = ["FreeJoint", "PinJoint", "SliderJoint", "UniversalJoint", "GimbalJoint", "BallJoint", "PlanarJoint",
             "WeldJoint"]
    for i, kind in enumerate(kinds):
        b = osm.Body(f"b{i}", 1.0, osm.Vec3(0.1, 0, 0), osm.Inertia(0.1, 0.1, 0.1))
        v = lambda: osm.Vec3(*[float(a) for a in rng.uniform(-0.3, 0.3, 3)])
        j = getattr(osm, kind)(f"j{i}", parent, v(), v(), b, v(), v())
        om.addBody(b)
        om.addJoint(j)
        om.addMarker(osm.Marker(f"m{i}", b, osm.Vec3(0.1, 0.2, -0.05)))
        parent = b
    om.finalizeConnections()
    path = tmp_path / "joints.osim"
    om.printToXML(str(path))
    m = load_osim(path)
    assert [j.kind for j in m.joints] == [k.replace("Joint", "").lower() for k in kinds]
    q = rng.uniform(-0.8, 0.8, (10, m.n_q))
    np.testing.assert_allclose(_opensim_markers(opensim, path, m, q), marker_positions(m, q), rtol=0, atol=1e-8)


def test_bad_model_files(tmp_path):
    p = tmp_path / "notes.osim"
    p.write_text("this is not xml at all")
    with pytest.raises(InputError, match="not an OpenSim model"):
        load_osim(p)
    q = tmp_path / "other.osim"
    q.write_text("<?xml version='1.0'?><svg></svg>")
    with pytest.raises(InputError, match="expected <OpenSimDocument>"):
        load_osim(q)
    with pytest.raises(InputError, match="not found"):
        load_osim(tmp_path / "missing.osim")
    bomb = tmp_path / "bomb.osim"
    bomb.write_text('<?xml version="1.0"?><!DOCTYPE l [<!ENTITY a "aaaa"><!ENTITY b "&a;&a;">]>'
                    '<OpenSimDocument><Model>&b;</Model></OpenSimDocument>')
    with pytest.raises(InputError, match="unsafe XML"):
        load_osim(bomb)


def test_coupler_constraint_scale_factor_matches_opensim(tmp_path, opensim):
    """OpenSim couples q_dep = scale_factor * f(q_indep); the import folds the factor into the row."""
    m = leg_model()
    m = m.with_couplings(LinearCoupling.correlative(m.coordinate_names, "subtalar_angle", {"ankle_angle": 0.3}, 0.01))
    path = save_osim(m, tmp_path / "c.osim")
    text = path.read_text()
    text = text.replace("<scale_factor>1</scale_factor>", "<scale_factor>2</scale_factor>") \
        if "<scale_factor>" in text else text.replace("</dependent_coordinate_name>",
                                                      "</dependent_coordinate_name><scale_factor>2</scale_factor>")
    p2 = tmp_path / "c2.osim"
    p2.write_text(text)
    om = opensim.Model(str(p2))
    s = om.initSystem()
    cs = om.getCoordinateSet()
    cs.get("ankle_angle").setValue(s, 0.5, False)
    cs.get("ankle_angle").setLocked(s, True)
    om.assemble(s)
    back = load_osim(p2)
    q = back.default_q
    q[back.coordinate_index("ankle_angle")] = 0.5
    q[back.coordinate_index("subtalar_angle")] = cs.get("subtalar_angle").getValue(s)
    assert abs(back.couplings.residual(q)[0]) < 1e-9


def test_multivariate_linear_matches_opensim_evaluation_both_ways(opensim):
    """Order-1 MultivariatePolynomialFunction coefficients map to the right inputs (OpenSim reverses them)."""
    from kinematics.multibody.functions import MultivariateLinear
    from kinematics.io.opensim_io import function_from_opensim, function_to_opensim

    f = MultivariateLinear(np.array([0.011, -0.023, 0.037]), 0.004)
    om = function_to_opensim(opensim, f)
    rng = np.random.default_rng(7)
    for x in rng.normal(size=(5, 3)):
        v = opensim.Vector(3, 0.0)
        for i in range(3):
            v.set(i, float(x[i]))
        assert abs(om.calcValue(v) - f.evaluate(x, order=0)[0][0]) < 1e-14
    back = function_from_opensim(opensim, om, "test", None)
    np.testing.assert_allclose(back.coefficients, f.coefficients, atol=1e-15)
    assert back.intercept == pytest.approx(f.intercept, abs=1e-15)
