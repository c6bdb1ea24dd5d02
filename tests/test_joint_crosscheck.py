"""Cross-checked joint estimates, both joint frames, model-error uncertainty (issue R2).

Analytic cases for `personalize.landmarks.crosscheck`; real bones with
expert-built models (ICL-MRI, LHDL-CT; skip without shared data) for the
accuracy, frame and coverage limits; VAKHUM-CT (no pelvis) for the hip from
the femoral head alone.
"""
from __future__ import annotations

import numpy as np
import pytest

from personalize.frames import MODEL_ERROR, Joint, joints_document, joints_from_landmarks
from personalize.landmarks import detect_landmarks
from personalize.landmarks.crosscheck import Estimate, cross_check, cross_check_directions
from personalize.evaluation.reference_models import (calibrate_model_error, compare_joints, coverage, error_rows,
                                          read_reference_joints)

SETS = ("ICL_MRI", "LHDL_CT")
FRAMES = [("hip_r", "parent"), ("hip_r", "child"), ("knee_r", "parent"), ("knee_r", "child"),
          ("ankle_r", "parent"), ("ankle_r", "child"), ("subtalar_r", "parent")]


# --------------------------------------------------------------------------- analytic
def _est(name, x, sd, model):
    return Estimate(name, np.asarray(x, float), sd ** 2 * np.eye(3), model)


def test_agreeing_estimates_give_the_precision_weighted_mean():
    a = _est("a", [0.0, 0.0, 0.0], 0.001, 0.0)
    b = _est("b", [0.002, 0.0, 0.0], 0.002, 0.0)          # 0.9 sd apart: agree
    r = cross_check([a, b])
    w = np.array([1 / 0.001 ** 2, 1 / 0.002 ** 2])
    assert r.agree and r.used == ("a", "b")
    assert np.allclose(r.value, [w[1] * 0.002 / w.sum(), 0, 0], atol=1e-12)
    assert np.allclose(r.cov_fit, np.eye(3) / w.sum(), rtol=1e-9)
    assert np.allclose(r.cov_spread, 0.0)


def test_an_outlier_is_left_out_and_its_spread_enters_the_covariance():
    es = [_est("primary", [0.010, 0, 0], 0.0005, 0.001), _est("b", [0.0, 0, 0], 0.0005, 0.001),
          _est("c", [0.0005, 0, 0], 0.0005, 0.001)]
    r = cross_check(es)
    assert r.left_out == ("primary",) and set(r.used) == {"b", "c"}
    assert np.allclose(r.value, [0.00025, 0, 0], atol=1e-9)
    d = 0.010 - 0.00025
    assert r.spread == pytest.approx(d, rel=1e-9)
    assert np.allclose(r.cov_spread, np.diag([d * d, 0, 0]), atol=1e-15)
    # the model sd decides: 10 mm apart with a 10 mm model sd is agreement
    r2 = cross_check([_est(e.source, e.value, 0.0005, 0.01) for e in es])
    assert r2.agree


def test_no_two_agree_keeps_the_primary_flagged():
    es = [_est("a", [0.0, 0, 0], 1e-4, 0.0), _est("b", [0.010, 0, 0], 1e-4, 0.0), _est("c", [0.004, 0, 0], 1e-4, 0.0)]
    r = cross_check(es)
    assert r.used == ("a",) and r.left_out == ("b", "c") and not r.agree
    assert np.allclose(r.value, 0.0)
    assert r.cov_spread[0, 0] == pytest.approx((0.010 ** 2 + 0.004 ** 2) / 2)


def test_checks_vote_but_do_not_move_the_value():
    a = _est("a", [0.0, 0, 0], 1e-4, 5e-4)
    chk = Estimate("coarse", np.array([0.003, 0, 0]), 1e-8 * np.eye(3), 0.005, check=True)
    r = cross_check([a, chk])
    assert r.agree and np.allclose(r.value, 0.0)
    # two agreeing checks cannot outvote the primary on their own
    chk2 = Estimate("coarse2", np.array([0.050, 0, 0]), 1e-8 * np.eye(3), 0.005, check=True)
    chk3 = Estimate("coarse3", np.array([0.051, 0, 0]), 1e-8 * np.eye(3), 0.005, check=True)
    r = cross_check([a, chk2, chk3])
    assert r.used == ("a",) and np.allclose(r.value, 0.0) and not r.agree
    assert r.cov_spread[0, 0] > 0.04 ** 2
    # against two agreeing estimates a disagreeing check is outweighed: left out, not counted
    b = _est("b", [0.0002, 0, 0], 1e-4, 5e-4)
    r = cross_check([a, b, chk2])
    assert r.left_out == ("coarse2",) and r.disagreeing == () and r.agree and np.allclose(r.cov_spread, 0.0)


def test_points_on_a_line_are_compared_across_it_only():
    u = np.array([0.0, 0.0, 1.0])
    es = [_est("a", [0, 0, 0], 2e-4, 5e-4), _est("b", [0, 0, 0.030], 2e-4, 5e-4)]   # 30 mm along the axis
    r = cross_check(es, plane_normal=u)
    assert r.agree and np.allclose(r.value, 0.0, atol=1e-12)
    es[1] = _est("b", [0.004, 0, 0.030], 2e-4, 5e-4)                                  # 4 mm across it
    assert not cross_check(es, plane_normal=u).agree


def test_directions_are_combined_on_the_sphere():
    rng = np.random.default_rng(3)
    u = np.array([1.0, 0, 0])
    t = np.radians(1.0)
    es = [Estimate("a", u, np.radians(0.5) ** 2 * np.eye(3), 0.0),
          Estimate("b", -np.array([np.cos(t), np.sin(t), 0]), np.radians(0.5) ** 2 * np.eye(3), 0.0)]  # sign free
    r = cross_check_directions(es)
    assert r.agree and np.linalg.norm(r.value) == pytest.approx(1.0)
    assert np.degrees(np.arctan2(r.value[1], r.value[0])) == pytest.approx(0.5, abs=1e-3)
    v = rng.normal(size=3)
    es.append(Estimate("c", v / np.linalg.norm(v), np.radians(0.5) ** 2 * np.eye(3), 0.0))
    assert "c" in cross_check_directions(es).left_out


# --------------------------------------------------------------------------- real bones
def _load(folder):
    """The set's bones (metres); until every mesh repair lands, a mesh the reader refuses is read as it is."""
    import trimesh

    from lowerlimb.errors import InputError
    from lowerlimb.bones import canonical_bone_name
    from personalize.surfaces import load_bones

    try:
        return load_bones(folder)
    except InputError:
        out = {}
        for f in sorted(folder.glob("*.ply")):
            n = canonical_bone_name(f.stem)
            if n is None or (n in out and f.stem != n):
                continue
            m = trimesh.load(str(f), process=False)
            out[n] = trimesh.Trimesh(np.asarray(m.vertices) * 1e-3, m.faces, process=True)
        return out


@pytest.fixture(scope="module")
def real(shared_data):
    out = {}
    for s in SETS:
        ls = detect_landmarks(_load(shared_data / "bones" / s))
        J, dropped = joints_from_landmarks(ls)
        ref = shared_data / "reference_models"
        out[s] = {"ls": ls, "joints": J, "dropped": dropped,
                  "manual": read_reference_joints(ref / f"manual_{s}.osim", use_opensim=False),
                  "staple": read_reference_joints(ref / f"automatic_{s}.osim", use_opensim=False)}
    return out


@pytest.mark.parametrize("s", SETS)
def test_every_joint_frame_within_staple_plus_1mm_1deg(real, s):
    r = real[s]
    worse = []
    for name, fr in FRAMES:
        o = compare_joints(r["joints"], r["manual"], [name], frame=fr)[name]
        st = compare_joints(r["staple"], r["manual"], [name], frame=fr)[name]
        if o["distance_mm"] > st["distance_mm"] + 1.0 or o["angle_deg"] > st["angle_deg"] + 1.0:
            worse.append((name, fr, round(o["distance_mm"], 2), round(st["distance_mm"], 2),
                          round(o["angle_deg"], 2), round(st["angle_deg"], 2)))
    assert not worse, worse


@pytest.mark.parametrize("s", SETS)
def test_knee_centre_within_2mm_of_the_expert(real, s):
    d = compare_joints(real[s]["joints"], real[s]["manual"], ["knee_r"])["knee_r"]
    assert d["distance_mm"] < 2.0
    assert d["angle_deg"] < 1.0


def test_lhdl_knee_cylinder_is_outvoted_and_flagged(real):
    """LHDL-CT: the posterior-condyle cylinder (distal surface dominant) lies 4.8 mm off; the others agree."""
    fem = real["LHDL_CT"]["ls"].bones["femur_r"]
    cc = fem.fits["knee_cross_check"]["centre"]
    assert cc["left_out"] == ["posterior_condyle_cylinder"]
    assert "low_confidence" in fem.flags
    j = real["LHDL_CT"]["joints"]["knee_r"]
    e = j.origin - real["LHDL_CT"]["manual"]["knee_r"].origin
    # the spread of the left-out estimate is in the stated covariance: the error is well inside it
    assert np.sqrt(e @ np.linalg.solve(j.origin_cov, e)) < 3.0
    assert np.sqrt(np.max(np.linalg.eigvalsh(j.origin_cov))) > 0.004
    # ICL-MRI: every knee estimate agrees, no flag
    icl = real["ICL_MRI"]["ls"].bones["femur_r"]
    assert icl.fits["knee_cross_check"]["centre"]["agree"] and "low_confidence" not in icl.flags


@pytest.mark.parametrize("s", SETS)
def test_mean_centre_distance_not_above_staple(real, s):
    """ICL-MRI 0.74 mm against STAPLE's 1.69; LHDL-CT 0.749 against 0.751 (at the limit)."""
    names = ["hip_r", "knee_r", "ankle_r", "subtalar_r"]
    r = real[s]
    o = compare_joints(r["joints"], r["manual"], names)
    st = compare_joints(r["staple"], r["manual"], names)
    assert np.mean([o[n]["distance_mm"] for n in names]) <= np.mean([st[n]["distance_mm"] for n in names])


@pytest.mark.parametrize("s", SETS)
def test_stated_uncertainty_covers_the_expert_model(real, s):
    c = coverage(error_rows(real[s]["joints"], real[s]["manual"]))
    assert c["total"] == 9
    assert c["fraction"] >= 0.95, c["rows"]


def test_model_error_chosen_on_one_set_checked_on_the_other(real):
    rows = {s: error_rows(real[s]["joints"], real[s]["manual"]) for s in SETS}
    on = {s: calibrate_model_error(rows[s]) for s in SETS}
    # in force: at least the larger of the two sets' calibrations (centre ICL-MRI's 0.018 R, axis LHDL-CT's
    # 1.0 deg), rounded up; it covers every centre and axis of both sets
    for k, up in (("centre", 0.003), ("axis_deg", 0.3)):
        big = max(on[s][k] for s in SETS)
        assert big <= MODEL_ERROR["knee"][k] <= big + up, (k, on)
    for s in SETS:
        assert coverage(rows[s], MODEL_ERROR["knee"])["fraction"] == 1.0
    # either set's own calibration alone misses on the other: ICL-MRI's axis term (0.6 deg) leaves LHDL-CT's
    # subtalar axis (2.9 deg) out, LHDL-CT's centre term (0.007 R) leaves ICL-MRI's knee and ankle centres out
    missed = {s: [o["what"] for o in coverage(rows[t], on[s])["rows"] if o["ratio"] > 3]
              for s, t in (("ICL_MRI", "LHDL_CT"), ("LHDL_CT", "ICL_MRI"))}
    assert missed["ICL_MRI"] and all(w.endswith("axis") for w in missed["ICL_MRI"]), missed
    assert missed["LHDL_CT"] and all(w.endswith("centre") for w in missed["LHDL_CT"]), missed
    # without the model term the fit covariance alone covers few of them
    bare = coverage(rows["LHDL_CT"], {"centre": 0.0, "axis_deg": 0.0})
    assert bare["fraction"] < 0.7


@pytest.mark.parametrize("s", SETS)
def test_both_frames_in_joints_json(real, s):
    doc = joints_document(real[s]["joints"], real[s]["dropped"], input=s)
    J = doc["joints"]
    assert J["hip_r"]["parent"]["body"] == "pelvis" and J["hip_r"]["child"]["body"] == "femur_r"
    assert J["knee_r"]["parent"]["body"] == "femur_r" and J["knee_r"]["child"]["body"] == "tibia_r"
    assert J["ankle_r"]["child"]["body"] == "talus_r" and J["subtalar_r"]["child"]["body"] == "calcn_r"
    for name, j in J.items():
        assert np.allclose(j["origin"], j["parent"]["origin"]) and np.allclose(j["rotation"], j["parent"]["rotation"])
        P, C = np.asarray(j["parent"]["rotation"]), np.asarray(j["child"]["rotation"])
        for R in (P, C):
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-8) and np.linalg.det(R) > 0
        if not name.startswith("hip"):
            assert np.allclose(P[:, 2], C[:, 2], atol=1e-8)          # same axis, each body's own Y
        jt = real[s]["joints"][name]
        v = jt.without_model_error()
        me = jt.model_error["centre_sd_m"]
        assert np.allclose(v.origin_cov, jt.origin_cov - me ** 2 * np.eye(3)) and v.axis_sd_deg < jt.axis_sd_deg
        assert Joint.from_json(name, j).without_model_error().axis_sd_deg == pytest.approx(v.axis_sd_deg, abs=1e-5)
    # the hip's child frame is the femur's: 14.5 deg from the pelvic frame on ICL-MRI, as in the expert model
    hp = J["hip_r"]
    turn = np.degrees(np.arccos((np.trace(np.asarray(hp["parent"]["rotation"]).T @ hp["child"]["rotation"]) - 1) / 2))
    ref = real[s]["manual"]["hip_r"]
    ref_turn = np.degrees(np.arccos((np.trace(ref.rotation.T @ ref.child_rotation) - 1) / 2))
    assert turn == pytest.approx(ref_turn, abs=3.0)


def test_hip_without_a_pelvis_from_the_femoral_head(shared_data, tmp_path):
    """VAKHUM-CT (femur, tibia, patella, talus): `personalize bones` gives the hip from the femoral head."""
    from personalize.bone_set import read_bone_set, write_bone_files

    bs = read_bone_set(shared_data / "bones" / "VAKHUM_CT")
    (tmp_path / "out").mkdir()
    write_bone_files(tmp_path / "out", bs)
    out = {"landmarks": bs.landmarks_json(), "joints": bs.joints_json()}
    J = out["joints"]["joints"]
    assert set(J) == {"hip_r", "knee_r", "ankle_r"} and "hip_r" not in out["joints"]["dropped"]
    hip = J["hip_r"]
    assert hip["parent"] == {"body": "pelvis", "missing": "no pelvis among the bones"}
    assert hip["child"]["body"] == "femur_r"
    fem = out["landmarks"]["bones"]["femur_r"]["landmarks"]
    assert np.allclose(hip["origin"], fem["femoral_head_centre"]["position"])
    assert np.allclose(hip["rotation"], hip["child"]["rotation"])
    # femur frame: Y from the knee centre to the hip centre, Z the knee axis made orthogonal to it
    R = np.asarray(hip["child"]["rotation"])
    y = np.subtract(fem["femoral_head_centre"]["position"], fem["intercondylar_midpoint"]["position"])
    assert np.degrees(np.arccos(min(1.0, R[:, 1] @ y / np.linalg.norm(y)))) < 1e-3
    # the file written is the document returned, with both frames of every joint
    import json

    doc = json.loads((tmp_path / "out" / "joints.json").read_text())
    assert doc["joints"]["knee_r"]["child"]["body"] == "tibia_r" and "model_error" in doc["joints"]["knee_r"]


@pytest.mark.parametrize("s", SETS)
def test_subtalar_talar_facet_checked_by_the_calcaneal_facet(real, s):
    """The calcaneus's posterior talar facet is the other side of the joint: its sphere centre lies within
    2 mm of the talar facet's across the subtalar axis on both expert sets, so the joint is not flagged, and
    the calcaneal facet, a check, does not move the origin (still within STAPLE + 1 mm of the expert's)."""
    j = real[s]["joints"]["subtalar_r"]
    cc = j.cross_check["centre"]
    assert cc["agree"] and cc["used"] == ["talar_facet", "calcaneal_facet"]
    assert 0.1 < cc["offsets_mm"]["calcaneal_facet"] < 2.0 and cc["offsets_mm"]["talar_facet"] == 0.0
    assert "low_confidence" not in j.flags
    d = np.linalg.norm(j.origin - real[s]["manual"]["subtalar_r"].origin)
    assert d < np.linalg.norm(real[s]["staple"]["subtalar_r"].origin - real[s]["manual"]["subtalar_r"].origin) + 1e-3
