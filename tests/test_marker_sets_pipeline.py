"""Marker sets through the pipeline: which set a subject uses, the internal-name view, the estimators the markers
allow, every static marker on the model (personalize.pipeline.markers, motion, marker_assignment)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kinematics.io.marker_sets import (MarkerDef, MarkerSet, canonical_names, detect_marker_set, preset,
                                       write_marker_set)
from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian


def _trial(labels, source="static.c3d", frames=5, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.normal(scale=0.3, size=(1, len(labels), 3)) + 0.001 * rng.normal(size=(frames, len(labels), 3))
    return MarkerTrial(tuple(labels), pos, 100.0, np.arange(frames) / 100.0, source)


@pytest.mark.parametrize("name", ["pig", "pig-sacr", "ior", "cast", "opensim"])
def test_preset_detected_from_the_labels(name):
    labels = [k for k, v in preset(name).markers.items() if v.segment != "torso"]   # torso markers not required
    m = detect_marker_set(_trial(labels))
    assert m.fits and m.marker_set.name == name and m.sides == ("r", "l") and m.missing == ()


def test_detection_ignores_extra_markers_and_a_missing_side():
    """A Plug-in-Gait set with medial markers and the left thigh wand lost: still pig, right side only."""
    labels = [k for k in preset("pig").markers if k != "LTHI"] + ["RKNEM", "RANKM", "C7", "T10"]
    m = detect_marker_set(_trial(labels))
    assert m.marker_set.name == "pig" and m.sides == ("r",)


def test_refusal_names_the_static_file_and_the_missing_markers(tmp_path):
    from personalize.pipeline.markers import subject_marker_set

    labels = [k for k in preset("pig").markers if k[1:] not in ("THI", "TOE")]   # no thigh wands, no toe markers
    with pytest.raises(InputError) as e:
        subject_marker_set(tmp_path, _trial(labels, source=str(tmp_path / "static.c3d")))
    msg = str(e.value)
    assert "static.c3d" in msg and "'pig'" in msg and "markers.json" in msg and "\n" not in msg
    for m in ("RTHI", "RTOE", "LTHI", "LTOE"):       # the nearest preset's missing markers, by name
        assert m in msg
    # a given set the trial does not fit: the missing markers of that set
    with pytest.raises(InputError, match=r"marker set 'ior'.*missing.*RTRO"):
        subject_marker_set(tmp_path, _trial(labels, source=str(tmp_path / "static.c3d")), "ior")


def test_placement_of_a_set_and_the_registration_it_implies(tmp_path):
    from kinematics.io.marker_sets import read_marker_set
    from personalize.landmarks import BoneLandmarks, Landmark
    from personalize.marker_registration import marker_correspondences

    assert preset("pig").on_joint_axes and preset("pig-sacr").on_joint_axes and not preset("ior").on_joint_axes
    f = tmp_path / "markers.json"
    write_marker_set(f, MarkerSet("lab", {"LM": MarkerDef("tibia_r", "RANK")}))
    assert read_marker_set(f).placement == "palpated"                      # a lab's own set: palpated sites
    f.write_text(json.dumps({"name": "lab", "placement": "joint-axis", "markers": {"LM": {"segment": "tibia_r"}}}))
    assert read_marker_set(f).on_joint_axes
    f.write_text(json.dumps({"name": "lab", "placement": "axis", "markers": {"LM": {"segment": "tibia_r"}}}))
    with pytest.raises(InputError, match=r"markers.json.*placement"):
        read_marker_set(f)
    # on the axis a malleolus 15 mm off it is projected onto it; palpated it is used where it is; `sites`
    # pairs the marker with another landmark (the tip)
    cov = 1e-6 * np.eye(3)
    tib = BoneLandmarks(bone="tibia_r", side="r", landmarks={"RANK": Landmark(np.array([0.0, 0.015, 0.03]), cov),
                                                            "lateral_malleolus_tip": Landmark(np.array([0.0, -0.01, 0.025]), cov)})
    static = {"RANK": Gaussian(np.array([0.0, 0.015, 0.05]), cov)}
    axis = (np.zeros(3), np.array([0.0, 0.0, 1.0]))
    on = marker_correspondences({"tibia_r": tib}, ["tibia_r"], ("RANK",), static, axis=axis)
    pal = marker_correspondences({"tibia_r": tib}, ["tibia_r"], ("RANK",), static)
    tip = marker_correspondences({"tibia_r": tib}, ["tibia_r"], ("RANK",), static, axis=axis,
                                 sites={"RANK": "lateral_malleolus_tip"})
    assert np.allclose(on.mri[0][:2], 0.0) and np.allclose(pal.mri[0], [0.0, 0.015, 0.03])
    assert np.allclose(tip.mri[0], [0.0, 0.0, 0.025])


def test_markers_json_renames_onto_internal_names(tmp_path):
    """A lab's own labels described in markers.json: the set wins over detection, landmarks give internal names."""
    from personalize.pipeline.inputs import check_same_subject
    from personalize.pipeline.markers import subject_marker_set

    ms = MarkerSet("lab", {"ASIS_R": MarkerDef("pelvis", "RASI"), "ASIS_L": MarkerDef("pelvis", "LASI"),
                           "SACRUM": MarkerDef("pelvis"), "EPI_LAT_R": MarkerDef("femur_r", "RKNE"),
                           "EPI_MED_R": MarkerDef("femur_r", "RMFC"), "TUB_R": MarkerDef("tibia_r", "RTTB"),
                           "MAL_R": MarkerDef("tibia_r", "RANK"), "HEEL_R": MarkerDef("calcn_r", "RHEE"),
                           "C7": MarkerDef("torso")})
    write_marker_set(tmp_path / "markers.json", ms)
    labels = [k for k in ms.markers if k != "C7"] + ["RKNE"]   # a stray label that clashes with a landmark name
    static = _trial(labels)
    got, sides, origin = subject_marker_set(tmp_path, static, "pig")       # markers.json beats --marker-set
    assert got == ms and sides == ("r",) and "markers.json" in origin
    names = canonical_names(got, static.names)
    assert names["ASIS_R"] == "RASI" and names["TUB_R"] == "RTTB" and names["SACRUM"] == "SACR"
    assert names["EPI_LAT_R"] == "EPI_LAT_R" and names["RKNE"] == "RKNE"   # RKNE is taken: no rename
    # three pelvis markers are enough to check that a trial is of the same subject
    check_same_subject(static, [static], got)
    moved = MarkerTrial(static.names, static.positions * 1.2, static.rate, static.time, "gait_01.c3d")
    with pytest.raises(InputError, match="gait_01.c3d.*another subject"):
        check_same_subject(static, [moved], got)
    # a body the model does not have is refused, naming the file
    (tmp_path / "markers.json").write_text(json.dumps({"markers": {"X": {"segment": "humerus_r"}}}))
    with pytest.raises(InputError, match="markers.json.*humerus_r"):
        subject_marker_set(tmp_path, static)


def _gauss(x, sd=0.0005):
    return Gaussian(np.asarray(x, float), sd**2 * np.eye(3))


def test_condylar_centre_and_axis_from_medial_and_lateral_markers():
    """Knee centre = epicondyle midpoint with the markers moved in by radius + tissue; axis = the marker line."""
    from kinematics.gait.soft_tissue import tissue_prior
    from personalize.pipeline.motion import condylar_axis, condylar_centre

    c, half = np.array([0.1, -0.1, 0.5]), 0.045              # true centre, half the epicondylar width (m)
    u = np.array([0.0, -1.0, 0.05]) / np.linalg.norm([0.0, -1.0, 0.05])     # right knee: lateral is -y
    r = 0.007
    t_l, t_m = tissue_prior("RKNE").mean, tissue_prior("RMFC").mean
    static = {"RKNE": _gauss(c + (half + t_l + r) * u), "RMFC": _gauss(c - (half + t_m + r) * u)}
    g = condylar_centre(static, "knee", "r", marker_radius=r)
    np.testing.assert_allclose(g.mean, c, atol=1e-12)
    sd = np.sqrt(np.linalg.eigvalsh(g.cov))
    assert 0.005 < sd.min() < sd.max() < 0.009                  # tissue along, palpation across, model term
    a = condylar_axis(static, "knee", "r")
    assert np.linalg.norm(np.cross(a.direction / np.linalg.norm(a.direction), u)) < 1e-12
    assert 4.0 < a.sd_deg < 10.0
    with pytest.raises(InputError, match="RMMA"):
        condylar_centre({"RANK": static["RKNE"]}, "ankle", "r")


def test_harrington_hip_in_the_pelvis_frame():
    """Harrington et al. 2007: x = -0.24 PD - 9.9, y(up) = -0.30 PW - 10.9, z(lateral) = 0.33 PW + 7.3 (mm), on the
    bony mid-ASIS; markers sit tissue + radius off the bone (here no tissue sd: the stated covariance is the
    regression's)."""
    from personalize.pipeline.motion import HARRINGTON_SD, harrington_hip

    pw, pd, r, t = 0.24, 0.16, 0.007, {"RASI": (0.01, 0.0), "LASI": (0.01, 0.0), "RPSI": (0.02, 0.0),
                                       "LPSI": (0.02, 0.0)}
    o = np.array([0.3, 0.1, 0.9])                              # bony mid-ASIS, lab axes = pelvis axes
    static = {"RASI": _gauss(o + [0.01 + r, -pw / 2, 0]), "LASI": _gauss(o + [0.01 + r, pw / 2, 0]),
              "RPSI": _gauss(o + [-pd - 0.02 - r, -0.04, 0]), "LPSI": _gauss(o + [-pd - 0.02 - r, 0.04, 0])}
    for side, sgn in (("r", -1.0), ("l", 1.0)):
        g = harrington_hip(static, side, np.eye(3), t, r, palpation=False)
        want = o + 1e-3 * np.array([-0.24 * pd * 1e3 - 9.9, sgn * (0.33 * pw * 1e3 + 7.3), -0.30 * pw * 1e3 - 10.9])
        np.testing.assert_allclose(g.mean, want, atol=1e-9)
        np.testing.assert_allclose(g.cov, HARRINGTON_SD**2 * np.eye(3), atol=1e-15)
        # the ASIS / PSIS markers' palpation through the pelvis frame: 4-6 mm more per axis for this pelvis
        gp = harrington_hip(static, side, np.eye(3), t, r)
        np.testing.assert_allclose(gp.mean, g.mean, atol=1e-15)
        extra = np.sqrt(np.diag(gp.cov) - HARRINGTON_SD**2)
        assert np.all((extra > 0.004) & (extra < 0.0065)), extra
    # the sacral marker stands in for the PSIS (OpenSim's V.Sacral)
    sac = {k: v for k, v in static.items() if "PSI" not in k}
    sac["SACR"] = _gauss(o + [-pd - 0.02 - r, 0, 0])
    np.testing.assert_allclose(harrington_hip(sac, "r", np.eye(3), {**t, "SACR": (0.02, 0.0)}, r).mean,
                               harrington_hip(static, "r", np.eye(3), t, r).mean, atol=1e-12)


def test_hip_range_of_motion_of_a_walk_and_a_star_arc():
    """Thigh cluster rotating in the pelvis: a walk-like ±20 deg flexion, ±5 deg abduction fails the functional
    rule, a star-arc ±25/±15 deg passes it."""
    from scipy.spatial.transform import Rotation

    from personalize.pipeline.motion import FUNCTIONAL_HIP_MIN_RANGE_DEG, hip_range_of_motion

    pel = np.array([[0.1, 0.12, 1.0], [0.1, -0.12, 1.0], [-0.06, 0.05, 1.02], [-0.06, -0.05, 1.02]])
    thi = np.array([[0.05, -0.12, 0.7], [0.0, -0.16, 0.6], [-0.04, -0.1, 0.65]])
    hip = np.array([0.0, -0.09, 0.92])
    names = ("RASI", "LASI", "RPSI", "LPSI", "RTHI", "RTHIP", "RTHIA")

    def trial(flex, abd):
        t = np.linspace(0, 2 * np.pi, 200)
        R = Rotation.from_euler("YX", np.column_stack([np.radians(flex) * np.sin(t),
                                                       np.radians(abd) * np.sin(2 * t)])).as_matrix()
        th = np.einsum("fij,mj->fmi", R, thi - hip) + hip
        pos = np.concatenate([np.broadcast_to(pel, (200, 4, 3)), th], axis=1)
        return MarkerTrial(names, pos, 100.0, t, "trial.c3d")

    static = MarkerTrial(names, np.concatenate([pel, thi])[None], 100.0, np.zeros(1), "static.c3d")
    ok = lambda rom: all(rom[k] >= v for k, v in FUNCTIONAL_HIP_MIN_RANGE_DEG.items())  # noqa: E731
    walk = hip_range_of_motion(static, trial(20.0, 5.0), "r", thigh=("RTHI", "RTHIP", "RTHIA"))
    star = hip_range_of_motion(static, trial(25.0, 15.0), "r", thigh=("RTHI", "RTHIP", "RTHIA"))
    assert walk["flexion"] == pytest.approx(40.0, abs=1.0) and walk["abduction"] == pytest.approx(10.0, abs=0.5)
    assert not ok(walk) and ok(star)


# --------------------------------------------------------------------------- a whole run with a lab's own labels
#: the phantom's Plug-in-Gait labels -> a lab's own, with their segment and landmark (markers.json); the wands
#: (THI, TIB) are dropped: no Plug-in-Gait reconstruction is possible.  ThighA is left out of markers.json
_OWN = {"ASI": ("ASIS", "pelvis", "ASI"), "PSI": ("PSIS", "pelvis", "PSI"), "KNE": ("EpiLat", "femur", "KNE"),
        "KNEM": ("EpiMed", "femur", "MFC"), "THIP": ("ThighP", "femur", None), "THIA": ("ThighA", None, None),
        "ANK": ("MalLat", "tibia", "ANK"), "ANKM": ("MalMed", "tibia", "MMA"), "TIBM1": ("Shank1", "tibia", None),
        "TIBM2": ("Shank2", "tibia", None), "TIBM3": ("Shank3", "tibia", None), "HEE": ("Heel", "calcn", "HEE"),
        "TOE": ("Toe", "calcn", None)}


@pytest.fixture(scope="module")
def own_labels_run(tmp_path_factory):
    """Analytic phantom (seed 3, 3 mm labels) relabelled to a lab's own names, one walk, no functional trial."""
    from kinematics.io.c3d import read_c3d, write_c3d
    from personalize.evaluation.phantom_subject import write_phantom_subject
    from personalize.pipeline import run_subject

    root = tmp_path_factory.mktemp("own_labels")
    subj = write_phantom_subject(root / "subject", seed=3, voxel_mm=3.0)
    for p in subj.glob("*.c3d"):
        if p.stem not in ("static", "gait_01"):
            p.unlink()
            continue
        t = read_c3d(p)
        keep = [n for n in t.names if n[1:] in _OWN]
        renamed = tuple(f"{n[0]}_{_OWN[n[1:]][0]}" for n in keep)
        pos = t.subset(keep).positions
        if p.stem == "static":              # a torso marker the set puts on "torso"
            renamed += ("C7",)
            pos = np.concatenate([pos, pos[:, :1] + [0.0, 0.0, 0.45]], axis=1)
        write_c3d(p, MarkerTrial(renamed, pos, t.rate, t.time, str(p)))
    markers = {}
    for s, side in (("R", "r"), ("L", "l")):
        for base, (own, seg, lm) in _OWN.items():
            if seg is not None:
                markers[f"{s}_{own}"] = MarkerDef(seg if seg == "pelvis" else f"{seg}_{side}", lm and s + lm)
    markers["C7"] = MarkerDef("torso")
    # the analytic phantom puts the knee and ankle markers on the joint axes (Plug-in-Gait's placement)
    write_marker_set(subj / "markers.json", MarkerSet("lab", markers, "joint-axis"))
    out = root / "out"
    return subj, out, run_subject(subj, out, report=False)


@pytest.mark.slow
def test_a_lab_marker_set_runs_end_to_end(own_labels_run):
    subj, out, s = own_labels_run
    src = s["sources"]
    assert "markers.json" in src["marker set"]
    for side in ("r", "l"):
        assert src[f"hip_{side}_motion"].startswith("Harrington")            # a walk does not qualify for SCoRE
        assert src[f"knee_centre_{side}_motion"].startswith("midpoint of the epicondyle markers EpiLat - EpiMed")
        assert src[f"ankle_centre_{side}_motion"].startswith("midpoint of the malleolus markers MalLat - MalMed")
    assert any("below the functional method's minimum" in n for n in s["notes"])
    e = s["errors"]
    assert e["hip_centre_mm"]["fused"] < 6.0 and e["knee_centre_mm"]["fused"] < 4.0 and e["ankle_centre_mm"]["fused"] < 4.0
    assert e["knee_axis_deg"]["fused"] < 4.0 and e["ankle_axis_deg"]["fused"] < 4.0
    # every static marker on the model under its own label, but the torso one; the one left out by nearest bone
    model = json.loads((out / "model.json").read_text())
    bodies = {m["name"]: m["body"] for m in model["markers"]}
    assert "C7" not in bodies and "C7" in s["markers"]["not_placed"]
    assert bodies["R_EpiMed"] == "femur_r" and bodies["L_Shank2"] == "tibia_l" and bodies["R_ASIS"] == "pelvis"
    thigh = s["markers"]["placed"]["R_ThighA"]
    assert thigh["from"] == "nearest bone" and thigh["body"] == "femur_r"
    assert 20.0 < thigh["nearest_bones_mm"]["femur_r"] < 80.0 < min(v for k, v in thigh["nearest_bones_mm"].items()
                                                                    if k != "femur_r")
    assert len(bodies) == 2 * len(_OWN)
    assert s["ik"]["gait_01"]["rms_mean_mm"] < 10.0


def test_real_lab_files_detected(shared_data):
    """OpenSim's gait2392 static (TRC, OpenSim names) and a Vicon Plug-in-Gait static (C3D, upper body too)."""
    from kinematics.io.c3d import read_c3d
    from kinematics.io.storage import read_trc

    osim = detect_marker_set(read_trc(shared_data / "opensim_gait2392" / "subject01_static.trc"))
    pig = detect_marker_set(read_c3d(shared_data / "mocap_pig" / "Static_trial.c3d"))
    assert (osim.marker_set.name, osim.sides, osim.found) == ("opensim", ("r", "l"), 39)   # torso markers too
    assert (pig.marker_set.name, pig.sides, pig.found) == ("pig", ("r", "l"), 16)
    # the walk lacks the medial and lateral knee and ankle markers (static-only in that lab): named as missing
    walk = detect_marker_set(read_trc(shared_data / "opensim_gait2392" / "subject01_walk1.trc"))
    assert not walk.fits and set(walk.missing) == {f"{S}.{m}" for S in "RL" for m in ("Knee.Lat", "Knee.Med",
                                                                                       "Ankle.Lat", "Ankle.Med")}


def test_davis_hip_moves_forward_with_the_asis_tissue_and_its_sd_says_so():
    """Plug-in-Gait's Davis centre with obese tissue (ASIS 30 mm, PSIS 40 mm, a 10 deg anteriorly tilted pelvis)
    against the same pelvis with bare markers: it lies 18-30 mm forward (the PSIS tissue, pushing up too, tilts the
    frame: under 12 mm across), and `davis_tissue_cov` states that shift
    along the pelvis x axis (sd sqrt(t² + σ²)), nothing across it."""
    from kinematics.gait.pig import davis_hip_offset, pelvis_frame
    from kinematics.gait.subject import SubjectMeasurements
    from personalize.pipeline.motion import davis_tissue_cov

    subj = SubjectMeasurements(left_leg_length=0.9, right_leg_length=0.9, left_knee_width=0.1, right_knee_width=0.1,
                               left_ankle_width=0.07, right_ankle_width=0.07)
    tilt = np.radians(10.0)
    fwd, up = np.array([np.cos(tilt), 0.0, -np.sin(tilt)]), np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    left = np.array([0.0, 1.0, 0.0])
    r = 0.007                                               # the markers' radius
    bone = {"RASI": -0.12 * left, "LASI": 0.12 * left, "RPSI": -0.15 * fwd - 0.04 * left,
            "LPSI": -0.15 * fwd + 0.04 * left}
    # the skin's normals: over the spines forward and out, over the PSIS backward and up
    normal = {k: v / np.linalg.norm(v) for k, v in {"RASI": fwd - 0.3 * left, "LASI": fwd + 0.3 * left,
                                                     "RPSI": -fwd + 0.5 * up, "LPSI": -fwd + 0.5 * up}.items()}
    tissue = {"RASI": 0.030, "LASI": 0.030, "RPSI": 0.040, "LPSI": 0.040}

    def davis(t):
        m = {k: p + (t.get(k, 0.0) + r) * normal[k] for k, p in bone.items()}
        pose = pelvis_frame(m["RASI"][None], m["LASI"][None], 0.5 * (m["RPSI"] + m["LPSI"])[None])
        iad = float(np.linalg.norm(m["RASI"] - m["LASI"]))
        return pose.to_lab(davis_hip_offset(subj, "R", iad)[None])[0], pose.axes[0]

    bare, axes = davis({})
    obese, _ = davis(tissue)
    shift = obese - bare
    assert 0.018 < shift @ fwd < 0.030 and np.linalg.norm(shift - (shift @ fwd) * fwd) < 0.012
    skin = {k: (v, 0.008) for k, v in tissue.items()}
    C = davis_tissue_cov({k: None for k in bone}, np.column_stack([fwd, left, up]), skin)
    np.testing.assert_allclose(fwd @ C @ fwd, 0.030 ** 2 + 0.008 ** 2, rtol=1e-12)
    np.testing.assert_allclose(C @ left, 0.0, atol=1e-15)
    assert (shift @ fwd) ** 2 <= fwd @ C @ fwd                # the shift within 1 stated sd along x
