"""The personalised model builder against the phantom skeleton's exact anatomy."""
from __future__ import annotations

import numpy as np
import pytest

from kinematics.algorithms.fk import forward_kinematics, marker_positions
from kinematics.algorithms.ik import solve_ik
from kinematics.io.markers import MarkerTrial
from personalize.model_builder import (DE_LEVA, FOOT_SPLIT, SideParameters, SubjectParameters, build_personal_model,
                                       default_knee_law)


@pytest.fixture(scope="module")
def phantom():
    from phantoms import make_phantom
    from phantoms.motion import make_trials

    ph = make_phantom(seed=3)
    sk, trials, _ = make_trials(ph, 3, gait_trials=1, gait_cycles=1.0, crouch_angles=(), functional_ranges=(45,),
                                functional_time_scale=0.5, static_duration=0.3, sta=False, noise_sd=0.0)
    return sk, {t.name: t for t in trials}


def _true_parameters(sk, static) -> SubjectParameters:
    """Subject parameters from the phantom's exact standing anatomy (lab frame)."""
    st = sk.state(static.q[:1])
    cen = sk.centres_lab(st)
    seg = sk.segment_poses(st)
    names = static.markers.names
    sides = {}
    for s in ("r", "l"):
        Rt = seg[f"tibia_{s}"].axes[0]
        knee_axis = seg[f"femur_{s}"].axes[0][:, 1]     # femur y = the knee axis made orthogonal to the femur
        ankle = sk.model.joint(f"ankle_{s}")
        a_ax = Rt @ ankle.rotations[0].axis
        sub = sk.model.joint(f"subtalar_{s}")
        st_ax = Rt @ sub.rotations[0].axis
        sub_pt = seg[f"talus_{s}"].origin[0] + seg[f"talus_{s}"].axes[0] @ sub.parent_offset.translation
        toe = static.clean[0, names.index(f"{s.upper()}TOE")]
        sides[s] = SideParameters(cen[f"hip_{s}"][0], seg[f"femur_{s}"].origin[0], knee_axis, cen[f"ankle_{s}"][0], a_ax,
                                  sub_pt, st_ax, toe - np.array([0, 0, 0.02]), Rt[:, 1])
    pel = seg["pelvis"]
    markers = {n: static.clean[0, i] for i, n in enumerate(names)}
    return SubjectParameters(pel.origin[0], pel.axes[0], sides, markers, 70.0, 1.75, {"test": "phantom truth"})


def test_static_pose_reproduces_markers_and_centres(phantom):
    sk, trials = phantom
    p = _true_parameters(sk, trials["static"])
    pm = build_personal_model(p)
    m = pm.model
    x = marker_positions(m, pm.standing_q[None])[0]
    for i, n in enumerate(m.marker_names):
        np.testing.assert_allclose(x[i], p.markers[n], atol=1e-9)
    st = forward_kinematics(m, pm.standing_q[None])
    for s in ("r", "l"):
        # the hip centre is fixed in both pelvis and femur; the femur origin is the knee centre
        b = m.body_index(f"femur_{s}")
        np.testing.assert_allclose(st.positions[0, b], p.sides[s].knee, atol=1e-9)
        j = m.joint(f"hip_{s}")
        hip = st.positions[0, b] + st.rotations[0, b] @ j.child_offset.translation
        np.testing.assert_allclose(hip, p.sides[s].hip, atol=1e-9)
    assert np.allclose(pm.standing_q, m.default_q)


def test_standing_translation_keeps_the_static_pose(phantom):
    """A law whose constant term (the standing knee translation) is not zero: the standing pose still puts every
    body where the static trial saw it, and the tibia's joint point is that far from the femur's."""
    from dataclasses import replace

    sk, trials = phantom
    p = _true_parameters(sk, trials["static"])
    law = default_knee_law("r")
    C = np.array(law.coefficients, float)
    C[:, -1] = [0.002, -0.001, 0.0015]                       # m: anterior, proximal, lateral
    p = replace(p, sides={**p.sides, "r": replace(p.sides["r"], knee_law=replace(law, coefficients=C))})
    pm = build_personal_model(p)
    m = pm.model
    x = marker_positions(m, pm.standing_q[None])[0]
    for i, n in enumerate(m.marker_names):
        np.testing.assert_allclose(x[i], p.markers[n], atol=1e-9)
    ix = [m.coordinate_index(n) for n in ("knee_tx_r", "knee_ty_r", "knee_tz_r")]
    np.testing.assert_allclose(pm.standing_q[ix], [0.002, -0.001, 0.0015], atol=1e-12)
    j = m.joint("knee_r")
    st = forward_kinematics(m, pm.standing_q[None])
    bt, bf = m.body_index("tibia_r"), m.body_index("femur_r")
    tib_pt = st.positions[0, bt] + st.rotations[0, bt] @ j.child_offset.translation
    fem_pt = st.positions[0, bf] + st.rotations[0, bf] @ j.parent_offset.translation
    assert np.linalg.norm(tib_pt - fem_pt) == pytest.approx(np.linalg.norm([0.002, 0.001, 0.0015]), abs=1e-9)


def test_knee_flexes_about_the_given_axis(phantom):
    sk, trials = phantom
    p = _true_parameters(sk, trials["static"])
    pm = build_personal_model(p)
    m = pm.model
    q = pm.standing_q.copy()
    q[m.coordinate_index("knee_flexion_r")] += 0.5            # 0.5 rad from the standing pose
    law = pm.knee_laws["r"]
    q[[m.coordinate_index(n) for n in law.dependent]] = law.predict(q[[m.coordinate_index(n) for n in law.independent]])
    st0 = forward_kinematics(m, pm.standing_q[None])
    st1 = forward_kinematics(m, q[None])
    b = m.body_index("tibia_r")
    R = st1.rotations[0, b] @ st0.rotations[0, b].T          # rotation of the tibia in the lab
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    axis = p.sides["r"].knee_axis / np.linalg.norm(p.sides["r"].knee_axis)
    ang = np.degrees(np.arccos(min(1.0, abs(w @ axis) / np.linalg.norm(w))))
    assert ang < 1e-6
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(np.degrees(0.5), abs=1e-9)


def test_mass_properties_follow_de_leva(phantom):
    sk, trials = phantom
    pm = build_personal_model(_true_parameters(sk, trials["static"]))
    m = pm.model
    assert m.bodies[m.body_index("femur_r")].mass == pytest.approx(DE_LEVA["thigh"][0] * 70.0)
    foot = sum(m.bodies[m.body_index(f"{b}_l")].mass for b in FOOT_SPLIT)
    assert foot == pytest.approx(DE_LEVA["foot"][0] * 70.0)
    I = m.bodies[m.body_index("tibia_r")].inertia
    assert np.all(np.diag(I) > 0) and I[2, 2] < I[0, 0]      # the long axis has the smallest moment


def test_ik_of_clean_gait_with_the_true_anatomy(phantom):
    """Exact anatomy, STA-free markers: residuals only from the default knee law (a few mm/rad)."""
    sk, trials = phantom
    pm = build_personal_model(_true_parameters(sk, trials["static"]))
    g = trials["gait_01"]
    res = solve_ik(pm.model, MarkerTrial(g.markers.names, g.clean, g.markers.rate, g.time, "clean gait"))
    assert np.nanmax(res.rms) < 2.5e-3
    # anatomical knee flexion (tibia vs femur mechanical axes, as the phantom's), standing offset included
    k = res.q[:, pm.model.coordinate_index("knee_flexion_r")]
    kt = g.q[:, sk.model.coordinate_index("knee_flexion_r")]
    assert np.max(np.abs(k - kt)) < np.radians(2.0)
    assert abs(np.mean(k - kt)) < np.radians(0.5)


def test_standing_knee_angles_are_anatomical(phantom):
    """Standing knee flexion and varus of the model = the truth's (the phantom stands ~2 deg hyperextended)."""
    sk, trials = phantom
    pm = build_personal_model(_true_parameters(sk, trials["static"]))
    m = pm.model
    for s in ("r", "l"):
        for c in ("knee_flexion", "knee_adduction"):
            true = sk.standing_q[sk.model.coordinate_index(f"{c}_{s}")]
            assert abs(true) > np.radians(0.5)                # a non-trivial standing angle
            assert pm.standing_q[m.coordinate_index(f"{c}_{s}")] == pytest.approx(true, abs=np.radians(0.3))
        # the law's translations vanish at the standing pose (the fused centre is the standing one)
        law = pm.knee_laws[s]
        q = pm.standing_q[[m.coordinate_index(n) for n in law.independent]]
        np.testing.assert_allclose(law.predict(q), 0.0, atol=1e-12)


def test_default_law_is_zero_standing():
    law = default_knee_law("l")
    np.testing.assert_allclose(law.predict(np.zeros((1, 3))), 0.0)
    assert law.dependent == ("knee_tx_l", "knee_ty_l", "knee_tz_l")


def test_osim_export_with_meshes_loads(phantom, opensim, tmp_path):
    import trimesh

    from kinematics.io.opensim_io import load_osim
    from personalize.model_builder import save_model_osim, write_meshes

    sk, trials = phantom
    pm = build_personal_model(_true_parameters(sk, trials["static"]))
    box = trimesh.creation.box((0.05, 0.05, 0.3))
    box.apply_translation(pm.body_frames["femur_r"][0])
    files = write_meshes(pm, {"femur_r": (box, "femur_r")}, tmp_path / "meshes")
    path = save_model_osim(pm, tmp_path / "model.osim", files)
    om = opensim.Model(str(path))
    om.initSystem()
    assert om.getBodySet().get("femur_r").get_attached_geometry(0).getConcreteClassName() == "Mesh"
    back = load_osim(path)
    assert back.coordinate_names == pm.model.coordinate_names
    x0 = marker_positions(pm.model, pm.standing_q[None])[0]
    x1 = marker_positions(back, pm.standing_q[None], pm.model.marker_names)[0]
    np.testing.assert_allclose(x1, x0, atol=1e-9)
    # the mesh is in the femur frame: its centre near the body origin
    m = trimesh.load(tmp_path / "meshes" / "femur_r.stl")
    assert np.linalg.norm(m.bounds.mean(axis=0)) < 1e-6
