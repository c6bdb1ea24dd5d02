"""Talar trochlea in STAPLE's talus-intrinsic convention (`personalize.landmarks.trochlea`)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from personalize.landmarks.surface import as_surface
from personalize.landmarks.trochlea import _section_areas, staple_trochlea_cylinder


def test_section_areas_of_a_prism_are_its_polygon_area():
    # a 24-sided prism: every section across its axis is the regular polygon
    # of circumradius r, area (n/2) r^2 sin(2 pi / n)
    n, r = 24, 0.012
    m = trimesh.creation.cylinder(radius=r, height=0.04, sections=n)
    R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    V = m.vertices @ R.T + [0.1, -0.2, 0.05]
    axis = R[:, 2]
    h0 = float(np.array([0.1, -0.2, 0.05]) @ axis)
    areas = _section_areas(V, np.asarray(m.faces), axis, h0 + np.array([-0.015, 0.0, 0.012]))
    assert np.allclose(areas, 0.5 * n * r * r * np.sin(2 * np.pi / n), rtol=1e-9)
    # outside the prism there is no section
    assert _section_areas(V, np.asarray(m.faces), axis, np.array([h0 + 0.03]))[0] == 0.0


@pytest.fixture(scope="module")
def icl_talus(shared_data):
    from personalize.surfaces import load_bones

    return load_bones(shared_data / "bones" / "ICL_MRI")["talus_r"].mesh


def test_reproduces_the_staple_model_on_icl(icl_talus, shared_data):
    # STAPLE's own selection (no hint): its ankle in automatic_ICL_MRI.osim is the
    # reference; differences left: curvature estimator (libigl vs patch fit) and the
    # cylinder fitter's start
    from personalize.evaluation.reference_models import read_reference_joints

    auto = read_reference_joints(shared_data / "reference_models" / "automatic_ICL_MRI.osim",
                                 use_opensim=False)["ankle_r"]
    tc = staple_trochlea_cylinder(as_surface(icl_talus, "talus_r"))
    assert np.linalg.norm(tc.point - auto.origin) < 0.4e-3
    assert np.degrees(np.arccos(abs(tc.axis @ auto.rotation[:, 2]))) < 0.8
    assert 0.020 < tc.radius < 0.026
    # the selected trochlea faces the talus-intrinsic superior direction
    m = trimesh.Trimesh(icl_talus.vertices, icl_talus.faces, process=False)
    fn = m.face_normals * np.sign(m.volume)
    assert float(np.mean(fn[tc.faces] @ tc.superior)) > 0.7


def test_rigid_motion_equivariance(icl_talus):
    S = as_surface(icl_talus, "talus_r")
    a = staple_trochlea_cylinder(S, centre="mid")
    R = Rotation.from_rotvec([0.7, -0.4, 1.1]).as_matrix()
    t = np.array([0.05, -0.12, 0.3])
    moved = trimesh.Trimesh(S.vertices @ R.T + t, S.faces, process=False)
    b = staple_trochlea_cylinder(as_surface(moved, "talus_r"), centre="mid")
    assert np.linalg.norm(b.point - (R @ a.point + t)) < 1e-5
    assert np.degrees(np.arccos(min(1.0, abs(b.axis @ (R @ a.axis))))) < 0.01
    assert b.radius == pytest.approx(a.radius, abs=1e-6)
