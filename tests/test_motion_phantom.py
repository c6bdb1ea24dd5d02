"""Motion phantoms: the skeleton model, trials, knee law, markers, STA, noise and the written files."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kinematics.io.c3d import read_c3d
from kinematics.mechanisms.correlative import CorrelativeLaw
from kinematics.algorithms.functional import joint_centre_from_clusters
from kinematics.io.storage import read_mot, read_trc
from kinematics.gait.subject import read_subject
from phantoms import make_phantom
from phantoms.motion import ANGLE_COLUMNS, make_trials, write_trials


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(0)


@pytest.fixture(scope="module")
def world(phantom):
    sk, trials, stm = make_trials(phantom, 0, rate=50, gait_trials=1, gait_cycles=1.0, crouch_angles=(0, 90, 180),
                                  crouch_duration=1.5, functional_ranges=(45,), functional_time_scale=0.5)
    return sk, {t.name: t for t in trials}, stm


def test_body_frames_are_the_anatomical_frames_and_coordinates_the_pig_angles(world):
    sk, trials, _ = world
    tr = trials["gait_01"]
    st = sk.state(tr.q)
    ang = sk.angles(st)
    ix = sk.model.coordinate_index
    for s in ("r", "l"):
        for j in ("hip", "knee"):
            q = tr.q[:, [ix(f"{j}_{c}_{s}") for c in ("flexion", "adduction", "rotation")]]
            np.testing.assert_allclose(ang[f"{j}_{s}"], q, atol=1e-9)
    # gait curves in the normative ranges of the issue
    k = np.degrees(ang["knee_r"][:, 0])
    h = np.degrees(ang["hip_r"][:, 0])
    assert 2 < k.min() < 7 and 54 < k.max() < 64
    assert -9 < h.min() < -3 and 33 < h.max() < 41


def test_standing_pose_puts_the_joint_centres_where_the_phantom_has_them(world, phantom):
    sk, trials, _ = world
    st = sk.state(sk.standing_q)
    c = sk.centres_lab(st)
    bt = phantom.body_truth()["bones"]
    from phantoms.skeleton import LAB_FROM_BODY

    H = LAB_FROM_BODY @ bt["femur_r"]["landmarks"]["femoral_head_centre"]
    K = LAB_FROM_BODY @ bt["femur_l"]["landmarks"]["intercondylar_midpoint"]
    np.testing.assert_allclose(c["hip_r"][0], H, atol=1e-12)
    np.testing.assert_allclose(c["knee_l"][0], K, atol=1e-12)


def test_knee_translations_follow_the_law_in_the_femur_frame(world):
    sk, trials, _ = world
    tr = trials["crouch_090_01"]
    st = sk.state(tr.q)
    seg = sk.segment_poses(st)
    ix = sk.model.coordinate_index
    for s, lat in (("r", -1.0), ("l", 1.0)):
        law = sk.knee_laws[s]
        pred = law.predict(tr.q[:, [ix(n) for n in law.independent]])
        np.testing.assert_allclose(tr.q[:, [ix(n) for n in law.dependent]], pred, atol=1e-15)
        # tibia's copy of the knee point relative to the femur's, in femur axes: (anterior, lateral, proximal)
        b = sk.model.body_index(f"femur_{s}")
        K_f = sk.model.joint(f"knee_{s}").parent_offset.translation
        K_f_lab = st.positions[:, b] + st.rotations[:, b] @ K_f
        K_t = sk.centres_lab(st)[f"knee_{s}"]
        d = seg[f"femur_{s}"].to_local(K_t) - seg[f"femur_{s}"].to_local(K_f_lab)
        np.testing.assert_allclose(np.column_stack([d[:, 0], d[:, 2], lat * d[:, 1]]), pred, atol=1e-12)
        # a few mm over the crouch, not zero
        assert 2e-3 < np.ptp(pred[:, 0]) < 15e-3


def test_bone_fixed_markers_have_no_artefact_and_skin_markers_do(world):
    sk, trials, stm = world
    tr = trials["gait_01"]
    names = tr.markers.names
    amp = {n: np.linalg.norm(tr.sta[:, names.index(n)], axis=1).max() for n in names}
    assert amp["RTIBM1"] == 0 and amp["LTIBM2"] == 0
    assert 5e-3 < amp["RTHI"] < 30e-3 and 5e-3 < amp["LTHI"] < 30e-3
    assert amp["RASI"] < 8e-3 and amp["LPSI"] < 8e-3
    assert amp["RANK"] < amp["RTIB"]
    assert 10e-3 <= stm.amplitude["femur_r"] <= 20e-3 and 5e-3 <= stm.amplitude["tibia_l"] <= 15e-3
    # static trial: no artefact, white noise of 0.5 mm
    st = trials["static"]
    e = st.markers.positions - st.clean
    assert np.all(st.sta == 0)
    assert 0.45e-3 < np.std(e) < 0.55e-3


def test_crouch_foot_angles(world):
    sk, trials, _ = world

    def feet_angle(tr):
        st = sk.state(tr.q[:1])
        p = sk.sites_lab(st, ["RHEE", "RTOE", "LHEE", "LTOE"])[0]
        r, l = p[1] - p[0], p[3] - p[2]
        return np.degrees(np.arccos(np.dot(r[:2], l[:2]) / np.linalg.norm(r[:2]) / np.linalg.norm(l[:2])))

    base = feet_angle(trials["crouch_000_01"])
    assert abs(feet_angle(trials["crouch_090_01"]) - base - 90) < 10
    assert feet_angle(trials["crouch_180_01"]) > 160
    k = np.degrees(sk.angles(sk.state(trials["crouch_000_01"].q))["knee_r"][:, 0])
    assert k.max() > 90


def test_crouch_knee_rotates_internally_and_into_varus_with_flexion_at_every_foot_angle(world):
    """Weight-bearing squats: 15-25 deg tibial internal rotation, mostly in the first 30 deg, 2-5 deg varus."""
    sk, trials, _ = world
    ix = sk.model.coordinate_index
    q0 = sk.standing_q
    for a in (0, 90, 180):
        q = trials[f"crouch_{a:03d}_01"].q
        for s in ("r", "l"):
            flex = q[:, ix(f"knee_flexion_{s}")] - q0[ix(f"knee_flexion_{s}")]
            rot = np.degrees(q[:, ix(f"knee_rotation_{s}")] - q0[ix(f"knee_rotation_{s}")])
            var = np.degrees(q[:, ix(f"knee_adduction_{s}")] - q0[ix(f"knee_adduction_{s}")])
            turnout = 0.3 * a / 2                       # the knee's share of the turnout (external, constant)
            ir = rot + turnout
            i = np.argmax(flex)
            assert 14.0 < ir[i] < 26.0 and abs(ir[0]) < 1e-9
            early = np.argmin(np.abs(flex[: i + 1] - np.radians(30)))
            assert ir[early] > 0.55 * ir[i]              # screw-home: most of it by 30 deg
            assert 1.9 < var[i] < 5.1


def test_crouch_thigh_artefact_in_published_range(world):
    """Thigh skin markers move 1-4 cm in deep flexion, shank markers less (Akbarshahi 2010; Fiorentino 2017)."""
    _, trials, _ = world
    tr = trials["crouch_000_01"]
    peak = dict(zip(tr.markers.names, 1e3 * np.linalg.norm(tr.sta, axis=-1).max(axis=0)))
    thigh = [peak[f"R{m}"] for m in ("THI", "THIP", "THIA")]
    shank = [peak[f"R{m}"] for m in ("TIB", "TIBM3", "ANK")]
    assert 10.0 < max(thigh) < 40.0
    assert max(shank) < max(thigh)


def test_functional_hip_centre_without_artefact_under_2mm(phantom):
    sk, trials, _ = make_trials(phantom, 0, rate=50, gait_trials=0, crouch_angles=(), functional_ranges=(45,),
                                sta=False, noise_sd=0.0005, static_duration=0.2)
    tr = trials[-1]
    truth = sk.centres_lab(sk.state(tr.q))["hip_r"]
    for method in ("ctt", "score", "sphere"):
        est, lab = joint_centre_from_clusters(tr.markers, ["RASI", "LASI", "RPSI", "LPSI"],
                                              ["RTHI", "RKNE", "RTHIP", "RTHIA"], method)
        err = np.linalg.norm(lab - truth, axis=1).mean()
        assert err < 2e-3, (method, err)
        assert np.all(est.sd_proximal < 2e-3)


def test_write_trials(tmp_path, phantom):
    res = write_trials(tmp_path, phantom, 3, rate=50, gait_trials=1, gait_cycles=1.5, crouch_angles=(30,),
                       crouch_duration=1.0, functional_ranges=(20, 45), functional_time_scale=0.3, gaps=True)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["crouch_030_01.c3d", "functional_hip.c3d", "functional_hip_20.c3d", "gait_01.c3d",
                     "static.c3d", "subject.json", "truth"]
    mot = read_mot(tmp_path / "truth" / "gait_01.mot")
    for c in ("knee_tx_r", "knee_ty_r", "knee_tz_r", "knee_flexion_r", "knee_adduction_r", "knee_rotation_r"):
        assert c in mot.columns
    ang = read_mot(tmp_path / "truth" / "gait_01_angles.mot")
    assert ang.columns == ANGLE_COLUMNS and ang.in_degrees
    np.testing.assert_allclose(ang.values[:, ANGLE_COLUMNS.index("knee_flexion_r")],
                               mot.values[:, mot.columns.index("knee_flexion_r")], atol=1e-6)
    law = CorrelativeLaw.from_json(json.loads(json.dumps(res["knee_law_r"])))
    ix = [mot.columns.index(n) for n in law.independent]
    dep = [mot.columns.index(n) for n in law.dependent]
    np.testing.assert_allclose(law.predict(np.radians(mot.values[:, ix])), mot.values[:, dep], atol=1e-8)
    c3d = read_c3d(tmp_path / "gait_01.c3d")
    assert "RTIBM3" in c3d.names and np.isnan(c3d.positions).any()       # the gaps are written as gaps
    clean = read_trc(tmp_path / "truth" / "gait_01_markers.trc")
    ok = np.isfinite(c3d.positions)
    assert np.abs(c3d.positions[ok] - clean.positions[ok]).max() < 0.05    # same frame and units (m)
    cen = read_trc(tmp_path / "truth" / "gait_01_centres.trc")
    assert cen.names == ("RHJC", "LHJC", "RKJC", "LKJC", "RAJC", "LAJC")
    subj = read_subject(tmp_path / "subject.json")
    assert 0.8 < subj.right_leg_length < 1.0 and 0.2 < subj.inter_asis_distance < 0.3
    assert res["motion"]["trials"][1]["name"] == "gait_01"


def test_pelvis_markers_sit_along_the_bone_normal_at_the_subjects_tissue_thickness(world, phantom):
    """ASIS/PSIS marker centre = landmark + (tissue + marker radius) n, n the pelvis SDF's outward normal."""
    from lowerlimb.geometry import DEFAULT_MARKER_RADIUS
    from phantoms.skeleton import LAB_FROM_BODY, phantom_skeleton

    sk, _, _ = world
    st = sk.state(sk.standing_q)
    names = ["RASI", "LASI", "RPSI", "LPSI"]
    bt = phantom.body_truth()["bones"]
    A = phantom.placement
    expect = []
    for n in names:
        p_body = np.asarray(bt["pelvis"]["landmarks"][n], float)
        # the bone normal, from the SDF in the scanner frame (finite differences at 0.1 mm)
        ps = A[:3, :3] @ p_body + A[:3, 3]
        g = np.array([phantom.sdf("pelvis", (ps + 1e-4 * e)[None])[0] - phantom.sdf("pelvis", (ps - 1e-4 * e)[None])[0]
                      for e in np.eye(3)])
        nrm = LAB_FROM_BODY @ (A[:3, :3].T @ g) / np.linalg.norm(g)
        assert abs(nrm[0]) < np.cos(np.radians(3.0))   # not the lab forward axis: tilted ~12 deg on these phantoms
        expect.append(LAB_FROM_BODY @ p_body + (sk.tissue_thickness[n[1:]] + DEFAULT_MARKER_RADIUS) * nrm)
    # the standing pose moves the pelvis rigidly: fit the expected sites + both hip centres onto the model's
    c = sk.centres_lab(st)
    P = np.array(expect + [LAB_FROM_BODY @ bt[f"femur_{s}"]["landmarks"]["femoral_head_centre"] for s in "rl"])
    Q = np.vstack([sk.sites_lab(st, names)[0], c["hip_r"][0], c["hip_l"][0]])
    pc, qc = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - pc).T @ (Q - qc))
    R = Vt.T @ np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    assert np.abs((P - pc) @ R.T + qc - Q).max() < 2e-5   # 0.02 mm: a 1 deg normal error is 0.3-0.5 mm here
    # one thickness per site and subject, seeded, positive and plausible (CT: ASIS 9.7 +- 7, PSIS 19.6 +- 10.9 mm)
    assert 0.0 < sk.tissue_thickness["ASI"] < 0.08 and 0.0 < sk.tissue_thickness["PSI"] < 0.12
    assert phantom_skeleton(phantom).tissue_thickness == sk.tissue_thickness
