"""Plug-in-Gait: analytic round trips on synthetic legs, and agreement with Vicon Nexus' own outputs."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lowerlimb.errors import InputError
from kinematics.io.markers import MarkerTrial
from kinematics.gait.pig import (SegmentPose, chord_joint_centre, davis_hip_offset, joint_angles, plug_in_gait,
                            static_foot_offsets)
from kinematics.gait.subject import SubjectMeasurements, read_vsk, validate_static

SUBJECT = SubjectMeasurements(left_leg_length=0.90, right_leg_length=0.88, left_knee_width=0.11,
                              right_knee_width=0.105, left_ankle_width=0.075, right_ankle_width=0.07,
                              inter_asis_distance=0.24, left_static_plantar_flexion=0.0,
                              right_static_plantar_flexion=0.0, left_static_rotation_offset=0.0,
                              right_static_rotation_offset=0.0)


def _R(seq_angles):
    return Rotation.from_euler("YXZ", seq_angles).as_matrix()  # intrinsic Y-X'-Z''


def synthetic_legs(hip_deg, knee_deg, subject=SUBJECT, seed=0):
    """Markers of a pelvis and two legs posed by known PiG hip and knee angles (F, 3) in degrees.

    Returns the MarkerTrial (after an arbitrary rigid lab transform) and the true knee centres."""
    rng = np.random.default_rng(seed)
    F = len(hip_deg)
    a = subject.inter_asis_distance / 2
    lab = Rotation.random(random_state=rng)
    shift = rng.normal(0, 0.5, 3)
    pts = {"RASI": np.array([0, -a, 0]), "LASI": np.array([0, a, 0]),
           "RPSI": np.array([-0.16, -0.05, 0.0]), "LPSI": np.array([-0.16, 0.05, 0.0])}
    pts = {k: np.repeat(v[None], F, 0) for k, v in pts.items()}
    r = subject.marker_diameter / 2
    knees = {}
    for s, sgn in (("R", 1.0), ("L", -1.0)):
        m = subject.side(s)
        hip = davis_hip_offset(subject, s, subject.inter_asis_distance)
        fl, ad, ro = np.radians(hip_deg).T
        Rf = _R(np.stack([-fl, sgn * ad, sgn * ro], 1))
        kf, ka, kr = np.radians(knee_deg).T
        Rt = Rf @ _R(np.stack([kf, sgn * ka, sgn * kr], 1))
        lat = -sgn  # lateral is -y on the right, +y on the left
        knee = hip + Rf @ np.array([0, 0, -0.42])
        ankle = knee + Rt @ np.array([0, 0, -0.40])
        pts[f"{s}KNE"] = knee + Rf @ np.array([0, lat * (m["knee_width"] / 2 + r), 0])
        pts[f"{s}THI"] = knee + Rf @ np.array([0, lat * 0.07, 0.2])
        pts[f"{s}ANK"] = ankle + Rt @ np.array([0, lat * (m["ankle_width"] / 2 + r), 0])
        pts[f"{s}TIB"] = ankle + Rt @ np.array([0, lat * 0.06, 0.18])
        pts[f"{s}TOE"] = ankle + Rt @ np.array([0.14, 0, -0.05])
        pts[f"{s}HEE"] = ankle + Rt @ np.array([-0.05, 0, -0.05])
        knees[s] = lab.apply(knee) + shift
    names = tuple(pts)
    pos = np.stack([lab.apply(pts[n].reshape(-1, 3)).reshape(F, 3) + shift for n in names], 1)
    return MarkerTrial(names, pos, 100.0, np.arange(F) / 100.0, "synthetic"), knees


@pytest.fixture(scope="module")
def synthetic():
    rng = np.random.default_rng(42)
    F = 30
    hip = np.stack([rng.uniform(-20, 60, F), rng.uniform(-15, 15, F), rng.uniform(-20, 20, F)], 1)
    knee = np.stack([rng.uniform(0, 90, F), rng.uniform(-8, 8, F), rng.uniform(-20, 20, F)], 1)
    trial, knees = synthetic_legs(hip, knee)
    return trial, knees, hip, knee


def test_chord_function_geometry():
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 50, 3))
    b = c + 5 * (b - c) / np.linalg.norm(b - c, axis=1, keepdims=True)  # |b - c| = 5 > delta
    j = chord_joint_centre(a, b, c, 0.9)
    np.testing.assert_allclose(np.linalg.norm(j - c, axis=1), 0.9, atol=1e-12)  # at delta from the marker
    np.testing.assert_allclose(np.sum((j - c) * (j - b), axis=1), 0.0, atol=1e-12)  # right angle at J
    n = np.cross(a - c, b - c)
    np.testing.assert_allclose(np.sum((j - c) * n, axis=1), 0.0, atol=1e-12)  # in the marker plane
    # unreachable (marker closer to the proximal centre than delta): NaN, not a made-up point
    assert np.all(np.isnan(chord_joint_centre(a[:1], c[:1] + 0.1, c[:1], 0.9)))


def test_synthetic_knee_centres_and_angles_round_trip(synthetic):
    trial, knees, hip_deg, knee_deg = synthetic
    res = plug_in_gait(trial, SUBJECT)
    for s, sfx in (("R", "_r"), ("L", "_l")):
        np.testing.assert_allclose(res.centres[f"knee{sfx}"], knees[s], atol=1e-9)
        np.testing.assert_allclose(np.degrees(res.angles[f"hip{sfx}"]), hip_deg, atol=1e-7)
        np.testing.assert_allclose(np.degrees(res.angles[f"knee{sfx}"]), knee_deg, atol=1e-7)


def test_davis_hip_is_mirror_symmetric_and_inside_pelvis():
    sym = SubjectMeasurements(**{**SUBJECT.__dict__, "left_leg_length": 0.88, "source": None})
    r = davis_hip_offset(sym, "R", 0.24)
    l = davis_hip_offset(sym, "L", 0.24)
    np.testing.assert_allclose(r * [1, -1, 1], l, atol=1e-15)
    # posterior, right of the mid-line but medial to the ASIS, and below the ASIS
    assert r[0] < 0 and -0.12 < r[1] < 0 and r[2] < 0


def test_missing_markers_are_named(synthetic):
    trial = synthetic[0]
    keep = [n for n in trial.names if n not in ("RTHI", "LKNE")]
    with pytest.raises(InputError, match="RTHI.*LKNE"):
        plug_in_gait(trial.subset(keep), SUBJECT)


def test_marker_gap_gives_nan_not_invented(synthetic):
    trial = synthetic[0]
    pos = trial.positions.copy()
    pos[5:8, trial.index("RKNE")] = np.nan
    res = plug_in_gait(MarkerTrial(trial.names, pos, trial.rate, trial.time, "gappy"), SUBJECT)
    assert np.all(np.isnan(res.centres["knee_r"][5:8]))
    assert np.all(np.isfinite(res.centres["knee_r"][:5])) and np.all(np.isfinite(res.centres["knee_l"]))


def test_uncalibrated_feet_give_nan_ankle_angles_with_a_note(synthetic):
    sub = SubjectMeasurements(**{**SUBJECT.__dict__, "right_static_plantar_flexion": None})
    res = plug_in_gait(synthetic[0], sub)
    assert np.all(np.isnan(res.angles["ankle_r"])) and any("R foot offsets" in n for n in res.notes)
    assert np.all(np.isfinite(res.angles["ankle_l"]))


def test_leg_length_mismatch_is_refused(synthetic):
    other = SubjectMeasurements(**{**SUBJECT.__dict__, "right_leg_length": 0.70, "left_leg_length": 0.70})
    static, _ = synthetic_legs(np.zeros((5, 3)), np.zeros((5, 3)))
    validate_static(SUBJECT, static, tolerance=0.15)  # straight legs: ASIS-ankle about the leg length
    with pytest.raises(InputError, match="leg length"):
        validate_static(other, static)


# --------------------------------------------------------------------------- Vicon Nexus


@pytest.fixture(scope="module")
def nexus(shared_data):
    from kinematics.io.c3d import read_c3d, read_c3d_outputs

    d = shared_data / "mocap_pig"
    return {"vsk": read_vsk(d / "Test.vsk"),
            "static": read_c3d(d / "Static_trial.c3d"),
            "move": read_c3d(d / "Movement_trial.c3d"),
            "move_out": read_c3d_outputs(d / "Movement_trial.c3d"),
            "static_out": read_c3d_outputs(d / "Static_trial.c3d")}


def _nexus_pose(trial, seg):
    o = trial.marker(seg + "O")
    ax = [trial.marker(seg + k) - o for k in "ALP"]
    ax = [v / np.linalg.norm(v, axis=1, keepdims=True) for v in ax]
    return SegmentPose(o, np.stack(ax, -1))


def _angle_diff_deg(a, b):
    return np.abs((np.degrees(a - b) + 180) % 360 - 180)


def test_static_foot_offsets_match_nexus(nexus):
    cal = static_foot_offsets(nexus["static"], nexus["vsk"])
    v = nexus["vsk"]
    for name in ("right_static_plantar_flexion", "left_static_plantar_flexion",
                 "right_static_rotation_offset", "left_static_rotation_offset"):
        assert abs(getattr(cal, name) - getattr(v, name)) < 1e-5, name


def test_angle_convention_on_nexus_segment_frames(nexus):
    """joint_angles applied to Nexus' own segment axes reproduces Nexus' angles."""
    t, out = nexus["move"], nexus["move_out"]
    for s in "RL":
        pel, fe, ti, fo = (_nexus_pose(t, s_) for s_ in ("PEL", f"{s}FE", f"{s}TI", f"{s}FO"))
        for joint, p, d, name in (("hip", pel, fe, "HipAngles"), ("knee", fe, ti, "KneeAngles"), ("ankle", ti, fo, "AnkleAngles")):
            err = _angle_diff_deg(joint_angles(p, d, joint, s), out[f"{s}{name}"])
            assert np.nanmax(err) < 0.01, (s, joint, np.nanmax(err, axis=0))


@pytest.mark.parametrize("trial_key", ["move", "static"])
def test_plug_in_gait_matches_nexus(nexus, trial_key):
    trial = nexus[trial_key]
    out = nexus["move_out" if trial_key == "move" else "static_out"]
    sub = static_foot_offsets(nexus["static"], nexus["vsk"])
    validate_static(sub, nexus["static"])
    res = plug_in_gait(trial, sub)
    for s, sfx in (("R", "_r"), ("L", "_l")):
        for centre, seg in (("knee", "FEO"), ("ankle", "TIO")):
            err = np.linalg.norm(res.centres[centre + sfx] - trial.marker(s + seg), axis=1)
            assert np.nanmean(err) < 0.001, (s, centre, np.nanmean(err))
        for joint, name in (("hip", "HipAngles"), ("knee", "KneeAngles"), ("ankle", "AnkleAngles")):
            err = np.nanmean(_angle_diff_deg(res.angles[joint + sfx], out[s + name]), axis=0)
            if trial_key == "static" and joint == "ankle":
                # Nexus reports the static trial's ankle inversion as exactly 0 (its static foot is
                # defined without ab/adduction, vsk AnkleAbAdd = 0); the other two components must match.
                assert np.nanmax(np.abs(out[s + name][:, 1])) < 1e-6
                err = err[[0, 2]]
            assert np.all(err < 1.0), (s, joint, err)


def test_static_of_another_subject_is_refused(nexus):
    """Test.vsk with a 15 % shorter subject against the real static trial: a clear leg-length error."""
    from dataclasses import replace

    v = nexus["vsk"]
    validate_static(v, nexus["static"])
    other = replace(v, right_leg_length=v.right_leg_length * 0.85, left_leg_length=v.left_leg_length * 0.85)
    with pytest.raises(InputError, match=r"Static_trial\.c3d: R ASIS-ankle marker distance .* leg length"):
        validate_static(other, nexus["static"])


def test_real_trial_missing_markers_named(nexus):
    t = nexus["move"]
    with pytest.raises(InputError, match=r"Movement_trial\.c3d: missing Plug-in-Gait markers: RTIB"):
        plug_in_gait(t.subset([n for n in t.names if n != "RTIB"]), nexus["vsk"])


def test_unsupported_rotation_offsets_are_refused(synthetic):
    sub = SubjectMeasurements(**{**SUBJECT.__dict__, "right_thigh_rotation": 0.1, "source": "s.vsk"})
    with pytest.raises(InputError, match="s.vsk: non-zero right_thigh_rotation"):
        plug_in_gait(synthetic[0], sub)
