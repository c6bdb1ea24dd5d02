"""The personalised model builder against the phantom skeleton's exact anatomy."""
from __future__ import annotations

import numpy as np
import pytest

from kinematics.algorithms.fk import forward_kinematics, marker_positions
from kinematics.algorithms.ik import solve_ik
from kinematics.io.markers import MarkerTrial
from personalize.model_builder import (DE_LEVA, FOOT_SPLIT, GROUND_FROM_INTERNAL, SideParameters, SubjectParameters,
                                       build_personal_model, default_knee_law, trial_in_ground)

G = GROUND_FROM_INTERNAL


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
        np.testing.assert_allclose(x[i], G @ p.markers[n], atol=1e-9)       # ground = G internal
    st = forward_kinematics(m, pm.standing_q[None])
    for s in ("r", "l"):
        # the hip centre is fixed in both pelvis and femur; the femur origin is the knee centre
        b = m.body_index(f"femur_{s}")
        np.testing.assert_allclose(st.positions[0, b], G @ p.sides[s].knee, atol=1e-9)
        j = m.joint(f"hip_{s}")
        hip = st.positions[0, b] + st.rotations[0, b] @ j.child_offset.translation
        np.testing.assert_allclose(hip, G @ p.sides[s].hip, atol=1e-9)
    # body_frames: the same static poses in the internal frame
    for b in m.body_names[1:]:
        o, R = pm.body_frames[b]
        np.testing.assert_allclose(st.positions[0, m.body_index(b)], G @ o, atol=1e-9)
        np.testing.assert_allclose(st.rotations[0, m.body_index(b)], G @ R, atol=1e-9)
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
        np.testing.assert_allclose(x[i], G @ p.markers[n], atol=1e-9)
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
    R = st1.rotations[0, b] @ st0.rotations[0, b].T          # rotation of the tibia in ground
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    axis = G @ p.sides["r"].knee_axis / np.linalg.norm(p.sides["r"].knee_axis)
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
    assert np.all(np.diag(I) > 0) and I[1, 1] < I[0, 0]      # the long axis (ISB Y) has the smallest moment


def test_ik_of_clean_gait_with_the_true_anatomy(phantom):
    """Exact anatomy, STA-free markers: residuals only from the default knee law (a few mm/rad)."""
    sk, trials = phantom
    pm = build_personal_model(_true_parameters(sk, trials["static"]))
    g = trials["gait_01"]
    res = solve_ik(pm.model, trial_in_ground(pm, MarkerTrial(g.markers.names, g.clean, g.markers.rate, g.time, "clean gait")))
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
    text = path.read_text()
    assert "<length_units>meters</length_units>" in text and "<force_units>N</force_units>" in text
    assert "personalize" in om.getCredits() and "binary STL in metres" in om.getCredits()
    back = load_osim(path)
    assert back.coordinate_names == pm.model.coordinate_names
    x0 = marker_positions(pm.model, pm.standing_q[None])[0]
    x1 = marker_positions(back, pm.standing_q[None], pm.model.marker_names)[0]
    np.testing.assert_allclose(x1, x0, atol=1e-9)
    # the mesh is in the femur frame: its centre near the body origin
    m = trimesh.load(tmp_path / "meshes" / "femur_r.stl")
    assert np.linalg.norm(m.bounds.mean(axis=0)) < 1e-6


def test_meshes_decimated_with_their_error_stated(tmp_path):
    """A dense sphere (81,920 faces, r 5 cm) is written at 20,000 faces, watertight, its stated Hausdorff distance at
    least pymeshlab's own (independent) Hausdorff distance from every source vertex to the written surface and under
    0.2 mm (measured 0.018 mm); ``max_faces=None`` writes it whole.  The STL header states units, frame and
    decimation."""
    from types import SimpleNamespace

    import trimesh

    from personalize.model_builder import MODEL_MESH_MAX_FACES, write_meshes

    pm = SimpleNamespace(body_frames={"femur_r": (np.array([0.1, 0.2, 0.9]), np.eye(3))})
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=0.05)
    sphere.apply_translation([0.1, 0.2, 0.9])
    assert len(sphere.faces) == 81920 and MODEL_MESH_MAX_FACES == 20000
    light = write_meshes(pm, {"femur_r": (sphere, "femur_r")}, tmp_path / "light" / "meshes", source="labels.nii.gz")
    mf = light["femur_r"]
    assert mf.body == "femur_r" and mf.file == "meshes/femur_r.stl" and mf.source == "labels.nii.gz: femur_r"
    assert 19000 <= mf.faces <= 20000 and mf.source_faces == 81920 and mf.watertight == (True, True)
    m = trimesh.load(tmp_path / "light" / "meshes" / "femur_r.stl")
    assert len(m.faces) == mf.faces and m.is_watertight
    src = trimesh.creation.icosphere(subdivisions=6, radius=0.05)        # the source in the body frame
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(src.vertices, float), np.asarray(src.faces, np.int32)))
    ms.add_mesh(pymeshlab.Mesh(np.asarray(m.vertices, float), np.asarray(m.faces, np.int32)))
    h = ms.get_hausdorff_distance(sampledmesh=0, targetmesh=1, samplevert=True, sampleface=False)["max"]
    assert 0.5 * mf.hausdorff_mm < 1e3 * h <= mf.hausdorff_mm + 1e-4        # float32 STL: 1e-4 mm
    assert mf.hausdorff_mm < 0.2 and 0 < mf.mean_mm < mf.hausdorff_mm
    head = (tmp_path / "light" / "meshes" / "femur_r.stl").read_bytes()[:80].decode()
    assert head.startswith("m; body femur_r frame;") and f"{mf.faces}/81920 faces" in head
    assert mf.to_json()["units"] == "m" and mf.to_json()["decimated"]
    full = write_meshes(pm, {"femur_r": (sphere, "femur_r")}, tmp_path / "full" / "meshes", max_faces=None)["femur_r"]
    assert full.faces == full.source_faces == 81920 and full.hausdorff_mm == 0.0 and not full.decimated
    assert len(trimesh.load(tmp_path / "full" / "meshes" / "femur_r.stl").faces) == 81920


# --------------------------------------------------------------------------- OpenSim's conventions
def _standing_model(phantom):
    sk, trials = phantom
    p = _true_parameters(sk, trials["static"])
    return p, build_personal_model(p)


def test_model_osim_in_opensim_conventions(phantom, opensim, tmp_path):
    """model.osim read with the opensim API: gravity along -Y, the pelvis height in pelvis_ty, ISB body frames,
    standing coordinates near zero (the pelvis tilt is the phantom's anatomical ASIS-PSIS tilt)."""
    from personalize.model_builder import save_model_osim

    p, pm = _standing_model(phantom)
    om = opensim.Model(str(save_model_osim(pm, tmp_path / "model.osim")))
    s = om.initSystem()
    g = om.getGravity()
    assert [g.get(i) for i in range(3)] == pytest.approx([0.0, -9.80665, 0.0])
    cs = om.getCoordinateSet()
    q = {cs.get(i).getName(): cs.get(i).getValue(s) for i in range(cs.getSize())}   # default = standing pose
    assert q["pelvis_ty"] == pytest.approx(p.pelvis_origin[2], abs=1e-9) and q["pelvis_ty"] > 0.7
    assert q["pelvis_tx"] == pytest.approx(p.pelvis_origin[0], abs=1e-9)
    assert q["pelvis_tz"] == pytest.approx(-p.pelvis_origin[1], abs=1e-9)            # Z right = -internal Y
    deg = {k: np.degrees(v) for k, v in q.items() if cs.get(k).getMotionType() == 1}
    for c in ("pelvis_list", "pelvis_rotation", "hip_flexion", "hip_adduction", "hip_rotation", "knee_flexion",
              "knee_adduction", "knee_rotation", "ankle_angle", "subtalar_angle"):
        for name in ([c] if c.startswith("pelvis") else [f"{c}_r", f"{c}_l"]):
            assert abs(deg[name]) < 10.0, (name, deg[name])
    # ISB pelvis: X in the ASIS/PSIS plane, so the standing tilt is the plane's (posterior tilt positive about Z)
    m = p.markers
    v = 0.5 * (m["RASI"] + m["LASI"]) - 0.5 * (m["RPSI"] + m["LPSI"])
    assert deg["pelvis_tilt"] == pytest.approx(np.degrees(np.arctan2(v[2], v[0])), abs=2.0)
    assert -20.0 < deg["pelvis_tilt"] < -5.0                 # the phantom's pelvis is tilted anteriorly
    # ISB body frames at the standing pose: X anterior, Y up, Z right, within the segments' own lean
    for b in ("pelvis", "femur_r", "tibia_l", "calcn_r"):
        R = np.array([[om.getBodySet().get(b).getTransformInGround(s).R().get(i, j) for j in range(3)] for i in range(3)])
        assert np.all(np.diag(R) > np.cos(np.radians(20))), (b, R)
    for s_ in ("r", "l"):
        o, R = pm.body_frames[f"femur_{s_}"]               # internal frame: Y towards the hip, Z to the right
        assert (p.sides[s_].hip - o) @ R[:, 1] == pytest.approx(np.linalg.norm(p.sides[s_].hip - o))
        assert R[:, 2] @ -pm.body_frames["pelvis"][1][:, 2] < 0  # both Z to the subject's right


def _child_rotation_axis(model, q, coordinate, step=1e-4):
    """Unit rotation axis in ground of the joint's child when `coordinate` grows by `step` (rad) from `q`."""
    j = next(j for j in model.joints if coordinate in j.coordinates)
    b = model.body_index(j.child)
    q1 = q.copy()
    q1[model.coordinate_index(coordinate)] += step
    R0, R1 = (forward_kinematics(model, x[None]).rotations[0, b] for x in (q, q1))
    D = R1 @ R0.T
    w = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
    return w / np.linalg.norm(w)


def test_coordinates_have_gait2392_axes_and_signs(phantom, shared_data, opensim):
    """Each leg coordinate turns its child body about the same ground direction as gait2392's at the standing
    pose (subject01_simbody_adjusted.osim read with the opensim API); the knee is the documented exception:
    knee_flexion is positive in flexion, gait2392's knee_angle negative."""
    from kinematics.io.opensim_io import load_osim

    _, pm = _standing_model(phantom)
    g = load_osim(shared_data / "opensim_gait2392" / "subject01_simbody_adjusted.osim")
    q_g = g.default_q.copy()
    q_g[[g.coordinate_index(c) for c in g.coordinate_names if g.coordinates[g.coordinate_index(c)].kind == "rotational"
         and not c.startswith("pelvis")]] = 0.0
    for s in ("r", "l"):
        pairs = [(f"{c}_{s}", f"{c}_{s}", 1.0) for c in ("hip_flexion", "hip_adduction", "hip_rotation", "ankle_angle",
                                                         "subtalar_angle", "mtp_angle")]
        pairs.append((f"knee_flexion_{s}", f"knee_angle_{s}", -1.0))
        for mine, theirs, sign in pairs:
            a = _child_rotation_axis(pm.model, pm.standing_q, mine)
            b = _child_rotation_axis(g, q_g, theirs)
            assert sign * (a @ b) > np.cos(np.radians(40)), (mine, a, b)
    for c in ("pelvis_tilt", "pelvis_list", "pelvis_rotation"):
        j_m, j_g = pm.model.joint("ground_pelvis"), g.joint("ground_pelvis")
        k_m, k_g = j_m.coordinates.index(c), j_g.coordinates.index(c)
        np.testing.assert_allclose(j_m.rotations[k_m].axis, j_g.rotations[k_g].axis)


def test_ik_enforces_the_coordinate_ranges(phantom):
    """Markers of a knee flexed to 140 deg (beyond the 120 deg of gait2392's range): IK stops at the bound."""
    _, pm = _standing_model(phantom)
    m = pm.model
    q = pm.standing_q.copy()
    q[m.coordinate_index("knee_flexion_r")] = np.radians(140.0)
    law = pm.knee_laws["r"]
    q[[m.coordinate_index(n) for n in law.dependent]] = law.predict(q[[m.coordinate_index(n) for n in law.independent]])
    x = marker_positions(m, q[None])
    trial = MarkerTrial(m.marker_names, np.repeat(x, 3, axis=0), 100.0, np.arange(3) / 100.0, "deep flexion")
    k = m.coordinate_index("knee_flexion_r")
    assert np.degrees(solve_ik(m, trial).q[:, k]) == pytest.approx(120.0, abs=1e-6)
    assert np.degrees(solve_ik(m, trial, limits="none").q[:, k]) == pytest.approx(140.0, abs=0.01)


def test_ik_angles_continuous_facing_back(phantom):
    """The phantom walk turned to face -X (pelvis_rotation near 180 deg, where the angle wraps): every rotational
    coordinate stays continuous (no step over 30 deg between frames) and the heading is within (-180, 180]."""
    sk, trials = phantom
    _, pm = _standing_model(phantom)
    g = trials["gait_01"]
    tr = trial_in_ground(pm, MarkerTrial(g.markers.names, g.clean, g.markers.rate, g.time, "clean gait"))
    turn = np.diag([-1.0, 1.0, -1.0])                        # 180 deg about ground Y
    back = MarkerTrial(tr.names, tr.positions @ turn.T, tr.rate, tr.time, "gait facing -X")
    res = solve_ik(pm.model, back)
    assert np.nanmax(res.rms) < 2.5e-3
    m = pm.model
    rot = [i for i, c in enumerate(m.coordinates) if c.kind == "rotational"]
    assert np.max(np.abs(np.diff(np.degrees(res.q[:, rot]), axis=0))) < 30.0
    heading = np.degrees(res.q[:, m.coordinate_index("pelvis_rotation")])
    assert -180.0 < heading[0] <= 180.0 and np.all(np.abs(np.abs(heading) - 180.0) < 15.0)


def test_undetermined_coordinates_are_named(phantom):
    """Without the foot markers (HEE, TOE) the ankle and subtalar of that side are undetermined and named."""
    sk, trials = phantom
    _, pm = _standing_model(phantom)
    g = trials["gait_01"]
    tr = trial_in_ground(pm, MarkerTrial(g.markers.names, g.clean[:5], g.markers.rate, g.time[:5], "clean gait"))
    assert not {"ankle_angle_r", "subtalar_angle_r"} & set(solve_ik(pm.model, tr).undetermined_coordinates)
    keep = [n for n in tr.names if n not in ("RHEE", "RTOE")]
    res = solve_ik(pm.model, tr.subset(keep))
    assert {"ankle_angle_r", "subtalar_angle_r"} <= set(res.undetermined_coordinates)
    assert not any(c.endswith("_l") or c.startswith(("hip", "knee")) for c in res.undetermined_coordinates)
